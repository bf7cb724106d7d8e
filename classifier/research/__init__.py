"""Research behind the shipped models, outside the product path: which signature features
(:mod:`~classifier.research.ablation`), accuracy against training size
(:mod:`~classifier.research.learning_curve`), the DLS-OCT g1 fit compared with the network
(:mod:`~classifier.research.g1fit`), ``doct-train --like`` end to end on other systems
(:mod:`~classifier.research.systems`), translation against directly rendered maps
(:mod:`~classifier.research.translation`) and what accuracy costs in time (:mod:`~classifier.research.tradeoffs`,
also ``torchdoct bench tradeoffs --part classifier`` through the entry-point table).

These modules use only public names of :mod:`classifier` and :mod:`torchdoct`; ``doct-classify``,
``doct-train`` and the ``torchdoct`` commands never import them (the benchmark finds the trade-offs part
through ``torchdoct/extensions.py``). Run them as ``python -m classifier.research.ablation`` and so on.
"""


def torchdoct_command(argv: list[str]) -> None:
    """Run ``torchdoct ARGV`` in this process, as a user would from the shell; ``RuntimeError`` unless it
    exits 0 (the research chains stop at the first failing step)."""
    from torchdoct.cli import main

    code = main(argv)
    if code != 0:
        raise RuntimeError(f"`torchdoct {' '.join(argv)}` exited {code}")
