"""What other installed packages add to torchdoct's commands: a table filled through entry points.

torchdoct never imports such a package by name (no arrow from ``torchdoct`` to ``classifier``); a package
declares its parts in its ``pyproject.toml`` and the command line looks them up here:

* group :data:`BENCH` (``torchdoct.bench``), name ``NAME``: ``torchdoct bench NAME``. The entry point is an
  object (a module) with ``HELP``, ``DESCRIPTION``, ``add_arguments(parser)`` and
  ``benchmark(args) -> (compute, format)``: ``compute()`` returns the result dict (written as JSON with
  ``--out``), ``format(result)`` its table;
* group :data:`TRADEOFFS` (``torchdoct.tradeoffs``), name ``PART``: ``torchdoct bench tradeoffs --part PART``.
  The entry point is an object (a module) with ``compute(*, quick, progress) -> dict``,
  ``format_table(result) -> str`` and ``plot(result, path)``.

* group :data:`COMMANDS` (``torchdoct.commands``), name ``NAME``: the command ``torchdoct NAME``. The entry
  point is an object (a module) with ``HELP``, ``DESCRIPTION``, ``add_arguments(parser)`` and
  ``run(args) -> int``.

Commands and benchmarks join the built-in ones in one table each (:func:`torchdoct.cli.commands`,
:func:`torchdoct.cli.bench.benchmarks`).

The classifier fills all three (``classify``; ``classifier``; ``translate``).
"""

from __future__ import annotations

from importlib.metadata import entry_points
from typing import Any

__all__ = ["BENCH", "TRADEOFFS", "COMMANDS", "load", "commands", "benchmarks"]

BENCH = "torchdoct.bench"
TRADEOFFS = "torchdoct.tradeoffs"
COMMANDS = "torchdoct.commands"


def _group(group: str) -> list[tuple[str, Any]]:
    return sorted(((ep.name, ep.load()) for ep in entry_points(group=group)), key=lambda t: t[0])


def commands() -> list[tuple[str, Any]]:
    """``(name, command object)`` of every installed command of group :data:`COMMANDS`, by name."""
    return _group(COMMANDS)


def benchmarks() -> list[tuple[str, Any]]:
    """``(name, benchmark object)`` of every installed benchmark of group :data:`BENCH`, by name."""
    return _group(BENCH)


def load(group: str, name: str, *, command: str) -> Any:
    """The object registered as ``name`` in entry-point ``group``; a ``ValueError`` naming ``command`` and
    the fix when no installed package provides it."""
    for ep in entry_points(group=group):
        if ep.name == name:
            return ep.load()
    raise ValueError(
        f"`{command}` needs the package that provides {name!r} (entry-point group {group!r}): "
        "install the project with its classifier (pip install .)"
    )
