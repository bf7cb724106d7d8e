"""File helpers shared by every command (standard library only): refuse to overwrite without
``force``, write atomically, find the files shipped with the project."""

from __future__ import annotations

import os
import tempfile
from importlib import resources
from pathlib import Path
from typing import Callable, Sequence

__all__ = ["check_out", "atomic_write", "shipped_files", "file_or_shipped"]


def check_out(path: str | os.PathLike | None, force: bool, suffix: str | Sequence[str],
              what: str = "--out") -> Path | None:
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
    if out.exists() and not force:
        raise ValueError(f"{what}: {out} exists; pass --force to overwrite it")
    if not out.parent.exists():
        raise ValueError(f"{what}: directory {out.parent} does not exist; create it first")
    return out


def atomic_write(path: str | os.PathLike, write: Callable[[str], None]) -> None:
    """Call ``write(tmp)`` on a temporary file in ``path``'s directory, then rename it over ``path``.

    A crash or kill mid-write never leaves a partial file under the final name; the temporary file
    is removed on error. ``tmp`` keeps ``path``'s suffix so writers that pick a format by suffix work.
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{path.suffix}", dir=path.parent)
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


def shipped_files(package: str, folder: str, suffix: str = ".toml") -> dict[str, Path]:
    """Name (file name without ``suffix``) -> path of every ``folder/*suffix`` file shipped in ``package``."""
    root = resources.files(package).joinpath(*folder.split("/"))
    return {p.name[: -len(suffix)]: Path(str(p)) for p in sorted(root.iterdir(), key=lambda q: q.name)
            if p.name.endswith(suffix)}


def file_or_shipped(key: str | os.PathLike, shipped: dict[str, Path]) -> Path | None:
    """``key`` if it is a file, else the shipped file of that name, else ``None``."""
    p = Path(key)
    if p.is_file():
        return p
    return shipped.get(str(key))
