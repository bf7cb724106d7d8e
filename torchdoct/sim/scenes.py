"""Shipped example scenes (TOML files in ``torchdoct/data/scenes``)."""

from __future__ import annotations

from pathlib import Path

from ..files import file_or_shipped, shipped_files

__all__ = ["shipped_scenes", "resolve_scene_path"]


def shipped_scenes() -> dict[str, Path]:
    """Name -> path of every scene shipped with torchdoct."""
    return shipped_files("torchdoct", "data/scenes")


def resolve_scene_path(scene: str | Path) -> Path:
    """A scene file path, or the path of the shipped scene of that name."""
    shipped = shipped_scenes()
    found = file_or_shipped(scene, shipped, "scene file")
    if found is not None:
        return found
    raise FileNotFoundError(
        f"scene file {str(scene)!r} not found; give a path to a .toml scene file or the name of a "
        f"shipped scene: {', '.join(shipped)}"
    )
