"""Clean interruption of every command (standard library only: ``doct-classify`` loads it without torch).

:func:`entry_point` wraps the console entry points (``torchdoct``, ``doct-train``, ``doct-classify``):

* **Ctrl-C (SIGINT)** and **SIGTERM** end the command with one line on stderr that says what was kept
  and how to resume (:func:`note` lets a command add what it kept, e.g. the finished cells of a
  sweep in its cache), and the exit code of the signal: 130 (SIGINT) or 143 (SIGTERM); no traceback.
  SIGTERM raises :class:`Terminated`, a :class:`KeyboardInterrupt`, so the clean-up that runs for
  Ctrl-C (temporary files removed, staged outputs discarded, worker processes stopped) runs for both.
  A second signal during that clean-up ends the process at once.
* A progress bar shows only after :data:`PROGRESS_DELAY_S` (1 s): a short run prints none.
* A **closed output pipe** (``| head``) ends the command quietly with exit code 141 (128 + SIGPIPE),
  the shell's code for a reader that went away.
* :func:`deferred` holds both signals back while an output set is renamed into place
  (:func:`torchdoct.files.output_set`), so a set appears whole or not at all.
* A command that needs an **optional dependency** the install left out (torch on the base install
  that ``doct-classify`` needs) ends with one line naming the extra to install (:data:`EXTRAS`),
  exit code 1, no traceback.
* :func:`worker_init` makes a worker process ignore Ctrl-C (its parent stops it) and die with its
  parent, even when the parent is killed with SIGKILL (Linux).
"""

from __future__ import annotations

import contextlib
import functools
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from types import SimpleNamespace
from typing import Any

__all__ = [
    "Terminated",
    "entry_point",
    "progress_disabled",
    "silence_progress",
    "note",
    "deferred",
    "worker_init",
    "EXIT_SIGINT",
    "EXIT_SIGTERM",
    "EXTRAS",
    "EXIT_PIPE",
    "missing_extra",
]

EXIT_SIGINT = 128 + signal.SIGINT  # 130
EXIT_SIGTERM = 128 + signal.SIGTERM  # 143
EXIT_PIPE = 128 + 13  # 141: SIGPIPE, the reader of the output went away

#: Optional top-level modules → the extra of ``pyproject.toml`` that installs them.
EXTRAS = {
    **dict.fromkeys(("torch", "scipy", "pandas", "pyarrow", "threadpoolctl"), "sim"),
    **dict.fromkeys(("sklearn", "onnx"), "train"),
    **dict.fromkeys(("dask", "distributed"), "dask"),
    **dict.fromkeys(("napari", "npe2"), "napari"),
}

_NAMES: dict[int, str] = {signal.SIGINT: "Ctrl-C", signal.SIGTERM: "SIGTERM"}
#: A command's progress bar shows only once its run has taken this long (s); ``$TQDM_DELAY`` overrides.
PROGRESS_DELAY_S = 1.0


class Terminated(KeyboardInterrupt):
    """Raised in the main thread on SIGTERM (a :class:`KeyboardInterrupt`: the same clean-up runs)."""


#: The signal received, signals held back, what was kept, and whether an entry point is running.
_STATE = SimpleNamespace(signum=None, defer=0, pending=None, kept={}, resume=None, active=False)


def _state() -> SimpleNamespace:
    return _STATE


def active() -> bool:
    """Whether an :func:`entry_point` runs (its handlers are installed)."""
    return _STATE.active


def _raise_for(signum: int) -> None:
    raise Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()


def _handler(signum: int, frame: Any) -> None:
    s = _state()
    if s.signum is not None and s.pending is None:  # a second signal while cleaning up: end now
        os._exit(128 + signum)
    s.signum = signum
    if s.defer:
        s.pending = signum
        return
    _raise_for(signum)


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """Hold SIGINT/SIGTERM back inside the block (it must run in the main thread); a signal that
    arrived meanwhile is raised when the block ends."""
    s = _state()
    s.defer += 1
    try:
        yield
    finally:
        s.defer -= 1
        if s.defer == 0 and s.pending is not None:
            signum, s.pending = s.pending, None
            _raise_for(signum)


def note(kept: str | None = None, resume: str | None = None, key: str = "") -> None:
    """Say, should the command be interrupted, what it has kept and how to resume.

    ``kept``: a phrase such as ``"4 finished cells in the cache out/cache"``; a later note with the
    same ``key`` replaces it, notes with other keys are joined. ``resume``: replaces the default
    ``"rerun the same command"``.
    """
    s = _state()
    if kept:
        s.kept[key] = kept
    if resume:
        s.resume = resume


def message(signum: int) -> str:
    """The one line printed when the command is interrupted by ``signum``."""
    s = _state()
    what = (
        f"kept {'; '.join(s.kept.values())}" if s.kept else "no output was written (outputs appear only when complete)"
    )
    return f"interrupted ({_NAMES.get(signum, f'signal {signum}')}): {what}; {s.resume or 'rerun the same command'}"


def _quiet_pipe() -> None:
    """Point stdout (and stderr if it is the same pipe) at /dev/null so nothing more is written or
    reported when Python flushes them at exit."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    for stream in (sys.stdout, sys.stderr):
        try:
            fd = stream.fileno()
        except (AttributeError, OSError, ValueError):
            continue
        try:
            stream.flush()
        except (BrokenPipeError, OSError, ValueError):
            pass
        try:
            os.fstat(fd)
            os.dup2(devnull, fd)
        except OSError:
            pass
    os.close(devnull)


def _flush() -> None:
    """Flush stdout inside the wrapper, so a closed pipe is seen here and not at interpreter exit."""
    if sys.stdout is not None:
        sys.stdout.flush()


def progress_disabled(progress: bool = True) -> bool:
    """Whether a progress bar is off: the caller's ``progress=False`` (``--no-progress``) or
    ``TQDM_DISABLE`` set in the environment (read at the call, so it holds wherever tqdm was imported)."""
    return not progress or os.environ.get("TQDM_DISABLE", "").strip().lower() in ("1", "true", "yes", "on")


def silence_progress(args: Any) -> None:
    """``--no-progress`` given (``args.no_progress``): every progress bar of the run is off, as with
    ``TQDM_DISABLE=1`` (which :func:`progress_disabled` and tqdm read)."""
    if getattr(args, "no_progress", False):
        os.environ["TQDM_DISABLE"] = "1"


def entry_point(fn: Callable[..., int]) -> Callable[..., int]:
    """Wrap a console entry point ``fn(argv) -> exit code`` (module docstring): install the SIGINT and
    SIGTERM handlers for its duration (main thread only), turn an interruption into one line and the
    signal's exit code, and a closed output pipe into a quiet exit 141."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> int:
        s = _state()
        if s.active:  # nested (e.g. `bench all` running each benchmark): the outer wrapper handles it
            return fn(*args, **kwargs)
        s.signum, s.pending, s.defer, s.kept, s.resume, s.active = None, None, 0, {}, None, True
        # progress bars (tqdm, imported later) appear only after PROGRESS_DELAY_S: none on a short run
        os.environ.setdefault("TQDM_DELAY", f"{PROGRESS_DELAY_S:g}")
        tqdm_disable = os.environ.get("TQDM_DISABLE")  # --no-progress sets it for this call only
        previous = {}
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                previous[sig] = signal.signal(sig, _handler)
        try:
            code = fn(*args, **kwargs)
            _flush()
            return code
        except KeyboardInterrupt:
            signum = s.signum or signal.SIGINT
            try:
                print(message(signum), file=sys.stderr, flush=True)
            except (BrokenPipeError, OSError, ValueError):
                pass
            return 128 + signum
        except BrokenPipeError:
            _quiet_pipe()
            return EXIT_PIPE
        except ModuleNotFoundError as err:
            line = missing_extra(err)
            if line is None:
                raise
            print(line, file=sys.stderr, flush=True)
            return 1
        finally:
            s.active = False
            if tqdm_disable is None:
                os.environ.pop("TQDM_DISABLE", None)
            else:
                os.environ["TQDM_DISABLE"] = tqdm_disable
            for sig, h in previous.items():
                signal.signal(sig, h)

    return wrapper


def missing_extra(err: ModuleNotFoundError) -> str | None:
    """The ``error:`` line for a missing optional dependency (:data:`EXTRAS`), or ``None`` for another module."""
    top = (err.name or "").split(".")[0]
    extra = EXTRAS.get(top)
    if extra is None:
        return None
    pin = "torch==2.13.0 " if extra in ("sim", "train") else ""  # the CPU build of torch, pinned first
    return (
        f"error: this command needs {top}, which the install left out; install the {extra!r} extra: "
        f"pip install {pin}'torchdoct[{extra}]'"
    )


def worker_init(parent_pid: int | None = None) -> None:
    """In a worker process: ignore Ctrl-C (the terminal sends it to the whole process group; the parent
    stops its workers) and die with the parent (Linux: ``PR_SET_PDEATHSIG``; if the parent is already
    gone, exit at once)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, int(signal.SIGTERM), 0, 0, 0)  # PR_SET_PDEATHSIG = 1
        except (OSError, AttributeError):  # pragma: no cover - no prctl
            pass
    if parent_pid is not None and os.getppid() != parent_pid:
        os._exit(EXIT_SIGTERM)
