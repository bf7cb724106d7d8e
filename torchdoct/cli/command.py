"""The shape of a command and how a parsed command runs: the ground floor of the command line.

Every command of ``torchdoct`` and every benchmark of ``torchdoct bench``, built in or added by another
installed package (:mod:`torchdoct.cli.extensions`), is one entry of a table with the same four names:
``HELP`` (one line), ``DESCRIPTION`` (or ``None``), ``add_arguments(parser)`` and ``run(args) -> int``. A
built-in entry is a :class:`Command`; an extension's entry is the module it registers, with those names.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

__all__ = ["Command", "add_parsers", "add_threads", "run_parsed", "command_main", "parse_floats", "workers"]


class Command(NamedTuple):
    """One entry of a command table (the names an extension's command module has too)."""

    HELP: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]
    DESCRIPTION: str | None = None


def add_parsers(sub: Any, table: dict[str, Any], *, dest: str = "func") -> None:
    """One parser per entry of ``table`` (name → command) under the subparsers ``sub``; the entry's
    ``run`` is stored as ``dest`` of the parsed arguments."""
    for name, command in table.items():
        sp = sub.add_parser(name, help=command.HELP, description=command.DESCRIPTION)
        command.add_arguments(sp)
        sp.set_defaults(**{dest: command.run})


#: Commands that only list or describe: no --threads.
NO_COMPUTE = {"scenes", "phantoms", "plan", "bench", "cog"}


def add_threads(sub: Any) -> None:
    """One knob on every command that computes: ``--threads N`` (:mod:`torchdoct.runtime.threads`); also on the
    subcommands of a command whose parser holds them as ``subcommands`` (``bench``)."""
    for name, sp in sub.choices.items():
        inner = getattr(sp, "subcommands", None)
        if inner is not None:
            add_threads(inner)
        if name in NO_COMPUTE or any("--threads" in a.option_strings for a in sp._actions):
            continue
        sp.add_argument(
            "--threads",
            type=int,
            default=None,
            metavar="N",
            help="cores to use (default: the usable cores, or $TORCHDOCT_THREADS); each works "
            "with one torch thread, so other busy processes do not stall it; results do "
            "not depend on N",
        )


def add_no_progress(sub: Any) -> None:
    """``--no-progress`` on every command, the same everywhere: no progress bar (as ``TQDM_DISABLE=1``)."""
    for sp in sub.choices.values():
        inner = getattr(sp, "subcommands", None)
        if inner is not None:
            add_no_progress(inner)
        if not any("--no-progress" in a.option_strings for a in sp._actions):
            sp.add_argument("--no-progress", action="store_true", help="no progress bar (as TQDM_DISABLE=1)")


def run_parsed(args: argparse.Namespace) -> int:
    """Run a parsed command: set the threads, check ``--device``, call its ``run``; bad input is one
    ``error:`` line and exit 2, a refused read or write exit 1 (:data:`torchdoct.cli.EXIT_CODES`)."""
    from ..runtime.interrupt import silence_progress
    from ..runtime.threads import limit_process_threads, set_default_threads
    from ..sim import config

    silence_progress(args)
    try:
        set_default_threads(getattr(args, "threads", None))
    except ValueError as err:
        print(f"error: --threads: {err}", file=sys.stderr)
        return 2
    limit_process_threads()  # parallel work runs over independent pieces (torchdoct.runtime.threads)
    try:
        if getattr(args, "device", None) is not None:  # every command with --device (simulate, render, maps)
            from ..runtime.device import check_device

            check_device(args.device)
        return int(args.func(args))
    except (config.SceneError, TypeError, ValueError, FileNotFoundError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # the reader of the output went away: torchdoct.runtime.interrupt ends quietly
        raise
    except OSError as err:  # the system refused a read or write (permissions, disk full)
        print(f"error: {err}", file=sys.stderr)
        return 1


def command_main(table: dict[str, Any], prog: str = "torchdoct") -> Callable[[Sequence[str]], int]:
    """``main(argv)`` of a parser over the commands of ``table`` alone (with ``--threads``): parse, then
    :func:`run_parsed`."""

    def main(argv: Sequence[str]) -> int:
        p = argparse.ArgumentParser(prog=prog)
        sub = p.add_subparsers(dest="command", required=True)
        add_parsers(sub, table)
        add_threads(sub)
        return run_parsed(p.parse_args(argv))

    return main


def parse_floats(text: str, n: int | None = None, what: str = "value") -> list[float]:
    """Comma-separated numbers of an option (``n`` of them when given); a ``ValueError`` naming ``what``."""
    try:
        vals = [float(v) for v in str(text).replace(" ", "").split(",") if v != ""]
    except ValueError:
        raise ValueError(f"{what} must be comma-separated numbers; got {text!r}") from None
    if n is not None and len(vals) != n:
        raise ValueError(f"{what} needs {n} numbers; got {text!r}")
    return vals


def workers(args: argparse.Namespace) -> int:
    """Cells side by side: ``--workers``, else ``--threads``, else the usable cores (one torch thread each)."""
    from ..runtime.threads import resolve_threads

    if args.workers is not None:
        return args.workers
    return resolve_threads(getattr(args, "threads", None))
