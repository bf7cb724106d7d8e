"""Research behind the shipped models, outside the installed packages: which signature features
(:mod:`~research.ablation`), accuracy against training size (:mod:`~research.learning_curve`), the
DLS-OCT g1 fit compared with the network (:mod:`~research.g1fit`), ``doct-train --like`` end to end on
other systems (:mod:`~research.systems`) and translation against directly rendered maps
(:mod:`~research.translation`). Their reports are in ``research/results/`` (README.md says which
command writes which).

These modules use only public names of :mod:`classifier` and :mod:`torchdoct`; no installed module
imports them. Run them from the repository root as ``python -m research.ablation`` and so on.
"""


def torchdoct_command(argv: list[str]) -> None:
    """Run ``torchdoct ARGV`` in this process, as a user would from the shell; ``RuntimeError`` unless it
    exits 0 (the research chains stop at the first failing step)."""
    from torchdoct.cli import main

    code = main(argv)
    if code != 0:
        raise RuntimeError(f"`torchdoct {' '.join(argv)}` exited {code}")
