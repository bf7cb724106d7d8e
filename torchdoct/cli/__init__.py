"""Command line: ``torchdoct COMMAND``. Parse, call one library function, print.

One table of commands (:func:`commands`): the built-in ones (:mod:`.simulate`, :mod:`.render`,
:mod:`.data`, :mod:`.study`, :mod:`.bench`) and those other installed packages add through the entry-point
group ``torchdoct.commands`` (:mod:`torchdoct.cli.extensions`: ``translate``). Every entry has the same four
names (:class:`~torchdoct.cli.command.Command`): ``HELP``, ``DESCRIPTION``, ``add_arguments(parser)``,
``run(args) -> int``; :func:`~torchdoct.cli.command.run_parsed` runs the parsed one.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from typing import Any

from ..runtime.interrupt import entry_point
from . import bench, data, render, simulate, study
from .command import add_no_progress, add_parsers, add_threads, run_parsed

__all__ = ["build_parser", "commands", "main", "EXIT_CODES"]

#: Exit codes of every command (``torchdoct``, ``doct-train``, ``doct-classify``; README, Command line).
EXIT_CODES = {
    0: "done",
    1: "failed for a reason other than the input: the system refused a read or write (permissions, disk "
    "full; one `error:` line), another run was writing the same outputs (a write conflict naming it) or an "
    "internal error (a traceback: please report it)",
    2: "bad input or usage: unknown option, missing, empty or corrupt file, invalid value, unusable "
    "device, output that exists without --force (one `error:` line naming the file or option and "
    "the fix; nothing is written)",
    130: "interrupted by Ctrl-C: one line says what was kept and how to resume (torchdoct.runtime.interrupt)",
    141: "the output pipe closed early (`| head`): ended quietly",
    143: "terminated by SIGTERM: one line says what was kept and how to resume",
}


def commands() -> dict[str, Any]:
    """Every command of ``torchdoct``, by name: the built-in ones, then those other installed packages add
    (entry-point group ``torchdoct.commands``)."""
    from . import extensions

    table: dict[str, Any] = {}
    for module in (simulate, render, data, study, bench):
        table.update(module.COMMANDS)
    for name, command in extensions.commands():
        if name in table:
            raise ValueError(f"an installed package adds the command {name!r}, which torchdoct already has")
        table[name] = command
    return table


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="torchdoct", description="Dynamic OCT simulation and metrics.")
    sub = p.add_subparsers(dest="command", required=True)
    add_parsers(sub, commands())
    add_threads(sub)
    add_no_progress(sub)
    return p


@entry_point  # Ctrl-C/SIGTERM: one line, exit 130/143; a closed output pipe: quiet exit 141
def main(argv: Sequence[str] | None = None) -> int:
    return _main(argv)


def _main(argv: Sequence[str] | None = None) -> int:
    return run_parsed(build_parser().parse_args(argv))
