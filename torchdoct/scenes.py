"""Shipped example scenes (TOML files in ``torchdoct/data/scenes``)."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

__all__ = ["shipped_scenes", "resolve_scene_path"]


def _scene_dir() -> Path:
    return Path(str(resources.files("torchdoct") / "data" / "scenes"))


def shipped_scenes() -> dict[str, Path]:
    """Name -> path of every scene shipped with torchdoct."""
    return {p.stem: p for p in sorted(_scene_dir().glob("*.toml"))}


def resolve_scene_path(scene: str | Path) -> Path:
    """A scene file path, or the path of the shipped scene of that name."""
    p = Path(scene)
    if p.is_file():
        return p
    shipped = shipped_scenes()
    if str(scene) in shipped:
        return shipped[str(scene)]
    if p.exists():
        raise FileNotFoundError(f"scene {str(scene)!r} is not a file")
    raise FileNotFoundError(
        f"scene file {str(scene)!r} not found; give a path to a .toml scene file or the name of a "
        f"shipped scene: {', '.join(shipped)}")
