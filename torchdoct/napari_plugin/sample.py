"""npe2 sample data: shipped phantoms rendered on demand (:func:`torchdoct.image.render`, the phantom's own
seed, so the same data every time) and shown as the dB intensity over time, scaled in µm."""

from __future__ import annotations

from typing import Any


def _rendered(name: str) -> list[tuple[Any, dict[str, Any], str]]:
    import numpy as np

    from ..image.phantom import load_phantom
    from ..image.render import render

    res = render(load_phantom(name), systems=None)
    meta = res.metadata(0)
    field = res.data[0].cpu().numpy()
    inten = (field.real**2 + field.imag**2) if np.iscomplexobj(field) else field
    with np.errstate(divide="ignore"):
        db = (10 * np.log10(inten)).astype(np.float32)
    pitch = meta["pitch_um"]
    scale = (1.0, *(float(pitch[c.lower()]) for c in meta["axes"][1:]))
    return [(db, {"name": f"{name} (dB)", "scale": scale, "colormap": "gray", "metadata": {"sequence": meta}}, "image")]


def vessel_slab() -> list[tuple[Any, dict[str, Any], str]]:
    return _rendered("vessel-slab")


def motion_types() -> list[tuple[Any, dict[str, Any], str]]:
    return _rendered("motion-types")
