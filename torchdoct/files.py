"""File helpers shared by every command (standard library only): refuse to overwrite without
``force``, write atomically, write a set of outputs whole or not at all, check names that become
file names and the nesting depth of parsed files, find the files shipped with the project.

Reading (the one reader-side check of every input file): :func:`check_regular_file` refuses a path that
is not a regular file (a FIFO, a character or block device, a socket, a directory) at once, with
"is not a regular file", before anything opens it (opening a FIFO would block until a writer comes;
``/dev/zero`` never ends); :func:`open_regular` opens without blocking and checks the opened file again
(a path swapped for a FIFO in between); :func:`read_capped` reads a small text file (JSON sidecar, TOML
scene, spec, prior) whole only when it is at most :data:`MAX_TEXT_BYTES` long."""

from __future__ import annotations

import contextlib
import errno
import glob
import os
import re
import shutil
import stat
import tempfile
import threading
from collections.abc import Callable, Iterable, Iterator, Sequence
from importlib import resources
from pathlib import Path
from typing import Any, overload

__all__ = [
    "check_out",
    "atomic_write",
    "output_set",
    "OutputSet",
    "safe_name",
    "check_nesting",
    "MAX_NESTING",
    "shipped_files",
    "file_or_shipped",
    "NotRegularFileError",
    "check_regular_file",
    "open_regular",
    "read_capped",
    "MAX_TEXT_BYTES",
    "WriteConflictError",
    "check_name_lengths",
    "toml_loads",
    "check_folder_files",
]

#: Deepest nesting of arrays/tables (TOML) or arrays/objects (JSON) that any input file may have: the
#: project's own files need 5 at most; far deeper ones would exhaust the parser's recursion.
MAX_NESTING = 64

#: Largest text file (JSON sidecar or metadata, TOML scene, phantom, sweep, study, spec or prior) read
#: whole: the project's own are a few KiB; a file (or a link to a device) longer than this is refused.
MAX_TEXT_BYTES = 16 << 20


class NotRegularFileError(ValueError):
    """A path given as an input file names a FIFO, a device, a socket or a directory (exit 2)."""


def _kind(mode: int) -> str:
    return (
        "a directory"
        if stat.S_ISDIR(mode)
        else "a FIFO (named pipe)"
        if stat.S_ISFIFO(mode)
        else "a character device"
        if stat.S_ISCHR(mode)
        else "a block device"
        if stat.S_ISBLK(mode)
        else "a socket"
        if stat.S_ISSOCK(mode)
        else "a special file"
    )


def _not_regular(what: str, path: Path, mode: int) -> NotRegularFileError:
    return NotRegularFileError(
        f"{what} {path} is not a regular file (it is {_kind(mode)}); give the path of the file itself"
    )


def check_regular_file(path: str | os.PathLike, what: str = "input file") -> Path:
    """``path`` as a :class:`~pathlib.Path` when it names a regular file (symbolic links followed).

    Else, without opening anything: :class:`NotRegularFileError` (a ``ValueError``: exit 2) reading
    "``what`` PATH is not a regular file (it is a FIFO ...)" for a FIFO, a device, a socket or a
    directory; ``FileNotFoundError`` "``what`` PATH: no such file" for a missing path (or a link to
    one); ``ValueError`` for a name the system cannot hold (too long). ``what`` names the role of the
    file in the command (``"sequence file"``, ``"--mask"``, ...).
    """
    p = Path(path)
    try:
        st = os.stat(p)
    except (FileNotFoundError, NotADirectoryError):
        if os.path.islink(p):
            raise FileNotFoundError(
                f"{what} {p} is a symbolic link to {os.readlink(p)}, which does not exist; "
                "point the link at the file itself"
            ) from None
        raise FileNotFoundError(f"{what} {p}: no such file") from None
    except OSError as err:
        if err.errno == errno.ENAMETOOLONG:
            raise ValueError(
                f"{what} {p}: the name is too long for the file system ({err.strerror}); "
                "rename the file or move it to a shorter path"
            ) from None
        if err.errno == errno.ELOOP:
            raise ValueError(f"{what} {p}: a loop of symbolic links; point the link at the file itself") from None
        raise
    if not stat.S_ISREG(st.st_mode):
        raise _not_regular(what, p, st.st_mode)
    return p


def check_folder_files(path: str | os.PathLike[str], what: str = "folder") -> None:
    """Every entry under the folder ``path`` is a folder or a regular file (:func:`check_regular_file` on each
    file, by ``stat`` alone), before a reader opens any: a FIFO or a device among a Zarr store's metadata or
    chunks would block the read or never end."""
    for root, _dirs, names in os.walk(path):
        for name in names:
            check_regular_file(Path(root) / name, f"a file of the {what} {Path(path).name}:")


def open_regular(path: str | os.PathLike, what: str = "input file"):
    """A binary file object of the regular file ``path`` (:func:`check_regular_file` first), opened with
    ``O_NONBLOCK`` and checked again after opening, so that a FIFO put in its place meanwhile is
    refused too instead of blocking the command."""
    p = check_regular_file(path, what)
    fh = open(p, "rb", opener=lambda name, flags: os.open(name, flags | getattr(os, "O_NONBLOCK", 0)))
    try:
        mode = os.fstat(fh.fileno()).st_mode
        if not stat.S_ISREG(mode):
            raise _not_regular(what, p, mode)
    except BaseException:
        fh.close()
        raise
    return fh


def read_capped(path: str | os.PathLike, what: str = "input file", limit: int = MAX_TEXT_BYTES) -> bytes:
    """The bytes of the regular file ``path`` (:func:`open_regular`), refused with a ``ValueError``
    naming ``what`` and the limit when longer than ``limit`` bytes (by its size, and by reading at most
    ``limit + 1`` bytes: a file that grows while read is refused too)."""
    with open_regular(path, what) as fh:
        size = os.fstat(fh.fileno()).st_size
        data = fh.read(limit + 1) if size <= limit else b""
    if size > limit or len(data) > limit:
        raise ValueError(
            f"{what} {Path(path)}: {max(size, len(data))} bytes, over the {limit >> 20} MiB a text "
            "file of its kind may have (the project's own are a few KiB); check that this is the "
            "right file"
        )
    return data


@overload
def check_out(path: None, force: bool, suffix: str | Sequence[str], what: str = "--out") -> None: ...
@overload
def check_out(path: str | os.PathLike, force: bool, suffix: str | Sequence[str], what: str = "--out") -> Path: ...
def check_out(
    path: str | os.PathLike | None, force: bool, suffix: str | Sequence[str], what: str = "--out"
) -> Path | None:
    """Validate an output path before any work is done.

    ``suffix`` is one allowed suffix or a sequence of them. Raises ``ValueError`` naming ``what`` and
    the fix when the suffix is wrong, the file exists and ``force`` is false, or the directory is missing.
    """
    if path is None:
        return None
    out = Path(path)
    allowed = (suffix,) if isinstance(suffix, str) else tuple(suffix)
    if out.suffix not in allowed:
        raise ValueError(f"{what} must end in {' or '.join(allowed)}; got {str(path)!r}")
    check_name_lengths([out], what)
    if out.is_dir():
        raise ValueError(f"{what}: {out} is a directory; give a file name")
    if out.exists() and not force:
        raise ValueError(f"{what}: {out} exists; pass --force to overwrite it")
    if not out.parent.exists():
        raise ValueError(f"{what}: directory {out.parent} does not exist; create it first")
    return out


def atomic_write(path: str | os.PathLike, write: Callable[[str], object]) -> None:
    """Call ``write(tmp)`` on a temporary file in ``path``'s directory, then rename it over ``path``.

    A crash or kill mid-write never leaves a partial file under the final name; the temporary file
    is removed on error. ``tmp`` keeps ``path``'s suffix so writers that pick a format by suffix work.
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(
        prefix=f"{_temp_stem(path.parent, path.name)}.{os.getpid()}.", suffix=f".tmp{path.suffix[:8]}", dir=path.parent
    )
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    try:
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the file the usual permissions
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _name_max(directory: Path) -> int:
    """The longest file name the file system of ``directory`` allows (255 where it does not say)."""
    try:
        return int(os.pathconf(directory, "PC_NAME_MAX"))
    except (OSError, ValueError):
        return 255


#: Characters a temporary file's name adds to ``.NAME``: the process number, the random part, ``.stage``,
#: ``.tmp`` and a suffix of up to 8.
_TEMP_EXTRA = 48


def _temp_stem(directory: Path, name: str) -> str:
    """``.NAME`` of the temporary files of ``name``, NAME cut so that their whole names stay within the file
    system's limit (a legal 255-character output name has temporaries too)."""
    return "." + name[: max(1, _name_max(directory) - _TEMP_EXTRA)]


def check_name_lengths(paths: Iterable[str | os.PathLike], what: str = "--out") -> None:
    """A ``ValueError`` naming ``what`` and the fix when a file name of ``paths`` (an output, or one derived
    from it: a sidecar, a PNG per channel) is longer than its file system allows, before anything is written."""
    for p in paths:
        p = Path(p)
        limit = _name_max(p.parent if p.parent.is_dir() else Path("."))
        if len(os.fsencode(p.name)) > limit:
            raise ValueError(
                f"{what}: the file name {p.name[:40]}… is {len(os.fsencode(p.name))} bytes, longer than "
                f"the file system allows ({limit}); give a shorter --out (the names of the files "
                "written beside it add to its name)"
            )


def _temporaries(directory: Path, name: str) -> list[Path]:
    """Temporary files of ``name`` in ``directory``: :func:`atomic_write`'s ``.NAME.PID.XXXX.tmpSUFFIX`` and
    :func:`output_set`'s ``.NAME.stage.PID.tmp.XXXX`` (PID: the writing process; NAME cut by
    :func:`_temp_stem`)."""
    stem = glob.escape(_temp_stem(directory, name))
    return [Path(p) for p in glob.glob(os.path.join(glob.escape(str(directory)), f"{stem}.*.tmp*"))]


def _writer_pid(temporary: Path, name: str) -> int | None:
    """The process number in a temporary file's name of ``name`` (:func:`_temporaries`), or None (an older
    run's name without one)."""
    m = re.match(r"(?:stage\.)?(\d+)\.", temporary.name[len(_temp_stem(temporary.parent, name)) + 1 :])
    return int(m.group(1)) if m else None


def _live_writer(pid: int | None) -> str | None:
    """``"process PID (its command)"`` while process ``pid`` runs and is a writer of this project; None when
    it has ended (its temporaries are a killed run's leftovers, to be removed) or its number was reused."""
    if pid is None:
        return None
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return None
    except PermissionError:
        pass  # alive, another user's
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            command = fh.read(4096).replace(b"\0", b" ").decode("utf-8", "replace").strip()
    except OSError:
        return f"process {pid}"
    if not any(word in command for word in ("torchdoct", "doct-", "classifier", "python", "pytest")):
        return None
    return f"process {pid} ({command[:120]})"


def _stale_temporaries(directory: Path, name: str) -> list[Path]:
    """Temporary files of ``name`` left in ``directory`` by a killed run (their writer has ended)."""
    return [p for p in _temporaries(directory, name) if _live_writer(_writer_pid(p, name)) is None]


class WriteConflictError(OSError):
    """Another process is writing the same output now: not bad input (exit 1 at the command line)."""


def _check_no_other_writer(finals: Sequence[Path], what: str) -> None:
    """A :class:`WriteConflictError` naming the other process when one is writing any of ``finals`` now (its
    temporary files are there and it runs): two runs writing one output is a write conflict, not bad input."""
    for p in finals:
        for tmp in _temporaries(p.parent, p.name):
            pid = _writer_pid(tmp, p.name)
            writer = None if pid == os.getpid() else _live_writer(pid)
            if writer is not None:
                raise WriteConflictError(
                    f"{what}: write conflict: {writer} is writing {p} now; wait for it to end, or "
                    f"give this run another {what}"
                )


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


def _note_written(files: list[Path]) -> None:
    """Should the command be interrupted after this set is in place, its one line says so."""
    from .runtime import interrupt

    if interrupt.active() and files:
        more = f" and {len(files) - 1} more" if len(files) > 1 else ""
        interrupt.note(kept=f"the complete outputs {files[0]}{more}", key=f"outputs {files[0]}")


def _signals_held():
    """Ctrl-C and SIGTERM held back while an output set is renamed (:func:`torchdoct.runtime.interrupt.deferred`;
    in the main thread of a command, where its handlers run)."""
    from .runtime import interrupt

    if interrupt.active() and threading.current_thread() is threading.main_thread():
        return interrupt.deferred()
    return contextlib.nullcontext()


class OutputSet:
    """Staging paths of an :func:`output_set`: ``stage(final)`` is where to write ``final``."""

    def __init__(self, finals: Sequence[Path], stages: dict[Path, Path]):
        self.finals = list(finals)
        self._stages = stages

    def __call__(self, final: str | os.PathLike) -> Path:
        final = Path(final)
        if final not in self.finals:
            raise KeyError(f"{final} is not a file of this output set")
        return self._stages[final.parent] / final.name


@contextlib.contextmanager
def output_set(paths: Iterable[str | os.PathLike], force: bool, what: str = "--out") -> Iterator[OutputSet]:
    """Write the files ``paths`` together: whole or not at all.

    ``with output_set(paths, force) as stage: write(stage(p)) ...``: every file is written into a hidden
    staging folder beside it (``.FIRST.stage.tmp.XXXX``) and all are renamed into place when the block
    ends without an error, with Ctrl-C and SIGTERM held back meanwhile (:mod:`torchdoct.runtime.interrupt`);
    on an error or an interruption the staging folder is removed and the files already there are
    untouched. ``paths`` lists every file the set may hold: at the end, one the block did not write is
    removed when it exists (the earlier run's file, e.g. ``magnitude.tif`` of another model), so the
    folder holds this run's set only. An existing file is an error unless ``force``; temporary files
    of the set left by a killed run are removed first, while another process writing the same files now
    (its temporary files carry its process number) is a write conflict naming it, checked at the start and
    again before the renames. The folders must exist.
    """
    finals = [Path(p) for p in paths]
    if len(set(finals)) != len(finals):
        raise ValueError(f"{what}: a file is listed twice in one output set")
    check_name_lengths(finals, what)
    if not force:
        clash = [str(p) for p in finals if p.exists()]
        if clash:
            raise ValueError(f"{what}: {', '.join(clash)} exist(s); pass --force to overwrite")
    parents = list(dict.fromkeys(p.parent for p in finals))
    for d in parents:
        if not d.is_dir():
            raise ValueError(f"{what}: directory {d} does not exist; create it first")
    _check_no_other_writer(finals, what)
    for p in finals:
        for stale in _stale_temporaries(p.parent, p.name):
            _remove(stale)
    first = {d: next(p.name for p in finals if p.parent == d) for d in parents}
    stages: dict[Path, Path] = {}
    try:
        for d in parents:
            stages[d] = Path(tempfile.mkdtemp(prefix=f"{_temp_stem(d, first[d])}.stage.{os.getpid()}.tmp.", dir=d))
        yield OutputSet(finals, stages)
        extra = [
            str(q)
            for d, st in stages.items()
            for q in st.iterdir()
            if d / q.name not in finals and not q.name.startswith(".")
        ]
        if extra:
            raise RuntimeError(f"files written outside their output set: {extra}")
        _check_no_other_writer(finals, what)  # one that began meanwhile: neither set lands
        with _signals_held():
            for p in finals:
                staged = stages[p.parent] / p.name
                if staged.exists():
                    os.replace(staged, p)
                elif p.exists() or p.is_symlink():
                    _remove(p)
            _note_written([p for p in finals if p.exists()])
    finally:
        for st in stages.values():
            shutil.rmtree(st, ignore_errors=True)


_UNSAFE = re.compile(r"[\x00-\x1f\x7f-\x9f/\\]")


def safe_name(name: str, what: str, fix: str = "rename it") -> str:
    """``name`` if it can be part of a file name as it is: no path separator, no control character
    (newline, BEL, ...), not empty, ``.`` or ``..``, at most 100 characters. Else ``ValueError``
    naming ``what`` and the fix."""
    bad = _UNSAFE.search(name) if isinstance(name, str) else None
    if not isinstance(name, str) or bad or name.strip() in ("", ".", "..") or len(name) > 100:
        why = (
            f"holds {bad.group()!r}"
            if bad
            else "is too long (over 100 characters)"
            if len(str(name)) > 100
            else "is empty, '.' or '..'"
        )
        raise ValueError(
            f"{what} {name!r} becomes part of a file name but {why}: no path separators or control characters; {fix}"
        )
    return name


def toml_loads(text: str) -> dict[str, Any]:
    """``tomllib.loads(text)``; an integer beyond Python's digit limit (thousands of digits, far beyond TOML's
    64-bit integers) is a ``tomllib.TOMLDecodeError`` naming its line and key, instead of Python's message
    about ``sys.set_int_max_str_digits`` that names neither."""
    import tomllib

    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError:
        raise
    except ValueError as err:
        if "integer string conversion" not in str(err):
            raise
        for i, line in enumerate(text.splitlines(), 1):
            m = re.search(r"([\w.\-\"']+)\s*=\s*[+-]?(\d[\d_]{299,})", line)
            if m:
                raise tomllib.TOMLDecodeError(
                    f"line {i}: {m.group(1)} is an integer of {len(m.group(2))} digits, far "
                    "beyond TOML's 64-bit integers; check the value"
                ) from None
        raise tomllib.TOMLDecodeError(
            "an integer of thousands of digits, far beyond TOML's 64-bit integers; check the values"
        ) from None


_JSON_TOKENS = re.compile(r'"(?:\\.|[^"\\])*"|[\[\]{}]')
_TOML_TOKENS = re.compile(r'"""[\s\S]*?"""|\'\'\'[\s\S]*?\'\'\'|"(?:\\.|[^"\\\n])*"|\'[^\'\n]*\'|#[^\n]*|[\[\]{}]')


def check_nesting(data: Any, where: str, *, toml: bool = False, limit: int = MAX_NESTING) -> None:
    """Refuse input nested deeper than ``limit`` before it reaches a recursive parser or validator.

    ``data``: the text (``str``/``bytes``) of a JSON (or, with ``toml``, TOML) file, scanned without
    recursion (strings and comments skipped), or an already parsed object (dicts and lists walked
    without recursion: TOML dotted keys nest tables without brackets). ``where`` names the file.
    """
    if isinstance(data, (bytes, bytearray)):
        data = bytes(data).decode("utf-8", errors="replace")
    depth = 0
    if isinstance(data, str):
        if data.count("[") + data.count("{") <= limit:
            return
        for m in (_TOML_TOKENS if toml else _JSON_TOKENS).finditer(data):
            t = m.group()
            if t in "[{":
                depth += 1
                if depth > limit:
                    break
            elif t in "]}":
                depth -= 1
    else:
        stack = [(data, 1)]
        while stack and depth <= limit:
            obj, d = stack.pop()
            if isinstance(obj, dict):
                obj = list(obj.values())
            elif not isinstance(obj, (list, tuple)):
                continue
            depth = max(depth, d)
            stack.extend((v, d + 1) for v in obj if isinstance(v, (dict, list, tuple)))
    if depth > limit:
        raise ValueError(
            f"{where}: nested more than {limit} levels deep (arrays or tables inside each other); "
            "valid files nest a few levels: check that this is the right file"
        )


def shipped_files(package: str, folder: str, suffix: str = ".toml") -> dict[str, Path]:
    """Name (file name without ``suffix``) -> path of every ``folder/*suffix`` file shipped in ``package``."""
    root = resources.files(package).joinpath(*folder.split("/"))
    return {
        p.name[: -len(suffix)]: Path(str(p))
        for p in sorted(root.iterdir(), key=lambda q: q.name)
        if p.name.endswith(suffix)
    }


def file_or_shipped(key: str | os.PathLike, shipped: dict[str, Path], what: str = "file") -> Path | None:
    """``key`` if it is a regular file, else the shipped file of that name, else ``None``; a path that
    exists but is not a regular file (FIFO, device, directory) and is no shipped name is a
    :class:`NotRegularFileError` naming ``what`` (:func:`check_regular_file`), never "not found"."""
    p = Path(key)
    try:
        return check_regular_file(p, what)
    except FileNotFoundError:
        return shipped.get(str(key))
    except NotRegularFileError:
        if str(key) in shipped:  # a folder named like a shipped scene in the working directory
            return shipped[str(key)]
        raise
