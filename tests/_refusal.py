"""The README's promise for bad input, as one test helper: exit 2 (or the code given), one ``error:`` line
naming the file or option, no traceback, nothing written."""

from __future__ import annotations

from pathlib import Path


def tree(d: Path) -> dict[str, int]:
    """Every path under ``d`` with its modification time (ns): equal before and after = nothing written."""
    return {str(p.relative_to(d)): p.stat().st_mtime_ns for p in d.rglob("*")}


def refused(
    capsys, tmp_path: Path, argv: list[str], *names: str, code: int = 2, run=None, absent: tuple[str, ...] = ()
) -> str:
    """``run(argv)`` (default: the ``torchdoct`` command) exits with ``code`` and one ``error:`` line naming
    every one of ``names`` and none of ``absent``, no traceback, and writes nothing under ``tmp_path``."""
    if run is None:
        from torchdoct.cli import main as run
    before = tree(tmp_path)
    got = run(argv)
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert got == code, err
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in err
    for n in names:
        assert n in lines[0], (n, lines[0])
    for n in absent:
        assert n not in lines[0], (n, lines[0])
    assert tree(tmp_path) == before, "nothing may be written"
    return lines[0]
