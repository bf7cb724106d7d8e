"""A time sequence of OCT frames and its metadata (numpy only, no torch): :class:`SequenceData`,
:class:`BlockRaster` and :func:`validate_meta`, shared by every sequence reader
(:mod:`torchdoct.measured.formats`) and the writer (:mod:`torchdoct.measured.io`).

Metadata (the sidecar / attribute JSON)::

    {"axes": "TZX" | "TYZX", "pitch_um": {"z": .., "x": .., ["y": ..]}, "frame_times_s": [...],
     "system": {"name": .., "wavelength_um": .., "lateral_resolution_um": .., "axial_resolution_um": ..,
                "refractive_index": ..}, ...optional extra keys}

``pitch_um["z"]`` is the in-medium depth step. Orientation: in a frame, rows are depth (z, the optical
axis) and columns the fast lateral axis (x); in a volume the B-scan index is y and Z is depth.

**Block raster protocol** (paper Section 2.1.2; El-Sadek 2021): the en-face field is split into
``n_blocks`` blocks of ``bscans_per_block`` B-scan positions; each block is raster-scanned
``n_repeats`` times before the next. A stack stored in acquisition order ``[n_blocks·n_repeats·
bscans_per_block, Z, X]`` is unpacked to ``[T = n_repeats, Y = n_blocks·bscans_per_block, Z, X]``
(:meth:`BlockRaster.unpack`). The B-scans next to block boundaries have a ~6.6 s acquisition gap to
their neighbours; :meth:`BlockRaster.keep_y` marks the ``drop_boundary`` B-scans on each side of every
inner boundary for exclusion (the paper drops one).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Mapping
from collections.abc import Sequence as _Seq
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "SequenceData",
    "BlockRaster",
    "validate_meta",
    "sidecar_path",
    "sidecar_exists",
    "finite_positive",
    "check_axes",
    "CANONICAL_AXES",
    "HOW",
]

CANONICAL_AXES = ("TZX", "TYZX")
#: How to give each metadata key that a file may lack (the option or the sidecar key), for the errors.
HOW = {
    "axes": "give --axes (e.g. TZX, TYZX, or the stored order such as XZT) or 'axes' in the sidecar JSON",
    "pitch_um": "give --pitch-um z=..,x=..[,y=..] (µm) or 'pitch_um' in the sidecar JSON",
    "frame_times_s": "give --frame-interval-s DT, --frame-times-s t0,t1,.. or 'frame_times_s' in the sidecar JSON",
    "system": (
        "give --wavelength-um, --lateral-resolution-um and --axial-resolution-um or 'system' in the sidecar JSON"
    ),
}


def sidecar_path(path: str | os.PathLike) -> Path:
    """The JSON sidecar of a sequence file: same directory and stem, suffix ``.json``."""
    return Path(path).with_suffix(".json")


def sidecar_exists(side: Path) -> bool:
    """Whether the sidecar ``side`` exists (a link to nothing counts: its reader names it). A legal
    sequence name whose derived sidecar name is longer than the file system allows (a 255-character
    ``.npy`` or ``.npz`` name gives a 256-character ``.json``) has no sidecar."""
    try:
        return os.path.lexists(side)
    except (OSError, ValueError):
        return False


# ----------------------------------------------------------------------------------------------
# data classes


@dataclass(frozen=True, kw_only=True)
class BlockRaster:
    """The paper's 3D block raster protocol (Section 2.1.2): blocks × repeats × B-scans per block.

    ``drop_boundary``: how many B-scans on each side of every inner block boundary to exclude from
    the analysis (the paper: 1). Use more when the lateral Gaussian of a resolution reduction reaches
    further than one B-scan pitch across the boundary.
    """

    n_blocks: int
    n_repeats: int
    bscans_per_block: int
    drop_boundary: int = 1

    def __post_init__(self) -> None:
        for key in ("n_blocks", "n_repeats", "bscans_per_block", "drop_boundary"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                raise TypeError(f"block raster {key} must be an integer; got {v!r}")
            object.__setattr__(self, key, int(v))
        for key in ("n_blocks", "bscans_per_block"):
            if getattr(self, key) < 1:
                raise ValueError(f"block raster {key} must be >= 1; got {getattr(self, key)}")
        if self.n_repeats < 2:
            raise ValueError(f"block raster n_repeats must be >= 2 (frames per location); got {self.n_repeats}")
        if self.drop_boundary < 0 or 2 * self.drop_boundary >= self.bscans_per_block:
            raise ValueError(
                f"block raster drop_boundary must be >= 0 and leave B-scans in each block "
                f"(< bscans_per_block/2 = {self.bscans_per_block / 2:g}); got {self.drop_boundary}"
            )

    @classmethod
    def parse(cls, text: str, drop_boundary: int = 1) -> BlockRaster:
        """From ``"BLOCKS:REPEATS:BSCANS"`` (e.g. ``"8:32:16"``, the paper's protocol)."""
        parts = str(text).replace("x", ":").split(":")
        if len(parts) != 3:
            raise ValueError(f"--block-raster must be BLOCKS:REPEATS:BSCANS_PER_BLOCK (e.g. 8:32:16); got {text!r}")
        try:
            b, r, k = (int(p) for p in parts)
        except ValueError:
            raise ValueError(f"--block-raster must be three integers BLOCKS:REPEATS:BSCANS; got {text!r}") from None
        return cls(n_blocks=b, n_repeats=r, bscans_per_block=k, drop_boundary=drop_boundary)

    @property
    def n_bscans(self) -> int:
        """Total B-scans acquired: ``n_blocks·n_repeats·bscans_per_block``."""
        return self.n_blocks * self.n_repeats * self.bscans_per_block

    @property
    def n_y(self) -> int:
        """B-scan positions of the volume: ``n_blocks·bscans_per_block``."""
        return self.n_blocks * self.bscans_per_block

    def unpack(self, data: np.ndarray) -> np.ndarray:
        """``[n_bscans, Z, X]`` in acquisition order → ``[n_repeats, n_y, Z, X]`` (a view when possible).

        Acquisition index of (block b, repeat r, position k) is ``(b·n_repeats + r)·bscans_per_block + k``.
        """
        if data.ndim != 3 or data.shape[0] != self.n_bscans:
            raise ValueError(
                f"block raster {self.n_blocks}:{self.n_repeats}:{self.bscans_per_block} needs data "
                f"[{self.n_bscans}, Z, X] in acquisition order; got shape {list(data.shape)}"
            )
        z, x = data.shape[1:]
        a = data.reshape(self.n_blocks, self.n_repeats, self.bscans_per_block, z, x)
        return a.transpose(1, 0, 2, 3, 4).reshape(self.n_repeats, self.n_y, z, x)

    def keep_y(self) -> np.ndarray:
        """Boolean ``[n_y]``: False for the ``drop_boundary`` B-scans on each side of inner boundaries."""
        keep = np.ones(self.n_y, dtype=bool)
        d = self.drop_boundary
        for b in range(1, self.n_blocks):
            edge = b * self.bscans_per_block
            keep[edge - d : edge + d] = False
        return keep

    def to_dict(self) -> dict[str, int]:
        return dataclasses.asdict(self)


@dataclass(frozen=True, kw_only=True, eq=False)
class SequenceData:
    """A time sequence of OCT frames with validated metadata.

    ``data``: numpy array in canonical order ``[T, Z, X]`` or ``[T, Y, Z, X]``: complex64/complex128
    (complex OCT) or float (linear intensity, e.g. a TIFF stack). May be a read-only memory map.
    ``meta``: the metadata dict (canonical ``axes``, ``pitch_um``, ``frame_times_s``, optional
    ``system`` and extra keys). ``labels`` / ``label_params``: optional arrays stored with the data.
    ``source``: the file name it was read from (no directory). ``nonfinite_samples``: how many samples
    of ``data`` are NaN or infinite (counted by :func:`read_sequence`; the maps mask their pixels).
    """

    data: np.ndarray
    meta: dict[str, Any]
    labels: np.ndarray | None = None
    label_params: np.ndarray | None = None
    source: str | None = None
    nonfinite_samples: int = 0

    @property
    def axes(self) -> str:
        return self.meta["axes"]

    @property
    def pitch_um(self) -> dict[str, float]:
        """The pixel pitch (µm); a ``ValueError`` says how to give it when the metadata have none (only a
        resolution change needs it)."""
        pitch = self.meta.get("pitch_um")
        if pitch is None:
            raise ValueError(f"{self.source or 'sequence'}: missing 'pitch_um' (µm per pixel); {HOW['pitch_um']}")
        return dict(pitch)

    @property
    def frame_times_s(self) -> list[float]:
        return list(self.meta["frame_times_s"])

    @property
    def n_frames(self) -> int:
        return int(self.data.shape[0])

    @property
    def is_complex(self) -> bool:
        return bool(np.iscomplexobj(self.data))

    @property
    def system(self) -> dict[str, Any]:
        """The system dict; a ``ValueError`` says how to give it when it is missing or incomplete."""
        sysd = self.meta.get("system")
        missing = [
            k
            for k in ("wavelength_um", "lateral_resolution_um", "axial_resolution_um")
            if not isinstance(sysd, Mapping) or sysd.get(k) is None
        ]
        if missing:
            raise ValueError(
                f"{self.source or 'sequence'}: system metadata missing {', '.join(missing)}; {HOW['system']}"
            )
        assert isinstance(sysd, Mapping)  # else every key is missing (raised above)
        return dict(sysd)

    @property
    def block_raster(self) -> BlockRaster | None:
        br = self.meta.get("block_raster")
        return None if br is None else BlockRaster(**br)


# ----------------------------------------------------------------------------------------------
# metadata


def finite_positive(where: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{where} must be a number; got {type(value).__name__} {value!r}")
    try:
        v = float(value)
    except OverflowError:  # an integer of hundreds of digits
        raise ValueError(
            f"{where} must be a finite number > 0; got an integer of {len(str(abs(int(value))))} digits"
        ) from None
    if not math.isfinite(v) or v <= 0:
        raise ValueError(f"{where} must be a finite number > 0; got {value!r}")
    return v


def check_axes(axes: Any, ndim: int | None, where: str) -> str:
    if not isinstance(axes, str):
        raise TypeError(f"{where}: axes must be a string such as 'TZX' or 'TYZX'; got {axes!r}")
    a = axes.upper()
    if sorted(a) not in (sorted("TZX"), sorted("TYZX")):
        raise ValueError(
            f"{where}: axes {axes!r} must be a permutation of TZX or TYZX (T frames, Y slow lateral, "
            "Z depth, X fast lateral)"
        )
    if ndim is not None and len(a) != ndim:
        raise ValueError(
            f"{where}: axes {axes!r} has {len(a)} letters but the data have {ndim} dimensions; "
            "give --axes matching the stored array"
        )
    return a


def validate_meta(
    meta: Mapping[str, Any],
    shape: _Seq[int],
    *,
    where: str = "metadata",
    require_system: bool = False,
    require_pitch: bool = False,
) -> dict[str, Any]:
    """Check metadata against canonical-order data of ``shape``; return a cleaned copy.

    Checks: ``axes`` is ``TZX`` or ``TYZX`` and matches the rank; ``pitch_um`` (when present, or when
    ``require_pitch``; only a resolution change needs it) has a positive entry for every spatial axis
    (and no other key); ``frame_times_s`` has ``T`` finite, strictly increasing
    entries; ``system`` (when present, or when ``require_system``) has positive ``wavelength_um``,
    ``lateral_resolution_um``, ``axial_resolution_um`` (µm) and ``refractive_index`` ≥ 1.
    """
    if not isinstance(meta, Mapping):
        raise TypeError(f"{where} must be a dict; got {type(meta).__name__}")
    out = dict(meta)
    for key in ("axes", "frame_times_s") + (("pitch_um",) if require_pitch else ()):
        if out.get(key) is None:
            raise ValueError(f"{where}: missing {key!r}; {HOW[key]}")
    axes = check_axes(out["axes"], len(shape), where)
    if axes not in CANONICAL_AXES:
        raise ValueError(f"{where}: axes {axes!r} is not canonical (TZX or TYZX); transpose the data first")
    out["axes"] = axes
    pitch = out.get("pitch_um")
    if pitch is None:  # only a resolution change needs it (SequenceData.pitch_um says how to give it)
        out.pop("pitch_um", None)
    else:
        if not isinstance(pitch, Mapping):
            raise TypeError(f"{where}: pitch_um must be a dict like {{'z': 1.5, 'x': 2.0}}; got {pitch!r}")
        spatial = [c.lower() for c in axes if c != "T"]
        extra = sorted(set(pitch) - set(spatial))
        if extra:
            raise ValueError(f"{where}: pitch_um has keys {extra} for axes not in {axes!r}; allowed: {spatial}")
        missing = [c for c in spatial if pitch.get(c) is None]
        if missing:
            raise ValueError(f"{where}: pitch_um is missing {missing} (µm per pixel); {HOW['pitch_um']}")
        out["pitch_um"] = {c: finite_positive(f"{where}: pitch_um[{c!r}] (µm)", pitch[c]) for c in spatial}
    times = out["frame_times_s"]
    if isinstance(times, (str, bytes)) or not hasattr(times, "__len__"):
        raise TypeError(f"{where}: frame_times_s must be a list of times in s; got {times!r}")
    t = []
    for i, v in enumerate(times):  # numbers only: strings are refused here as they are for pitch_um
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
            raise TypeError(
                f"{where}: frame_times_s[{i}] must be a number of seconds; got {type(v).__name__} {str(v)[:40]!r}"
            )
        try:
            t.append(float(v))
        except OverflowError:
            raise ValueError(
                f"{where}: frame_times_s[{i}] must be a finite number of seconds; got an integer of "
                f"{len(str(abs(int(v))))} digits"
            ) from None
    if len(t) != shape[0]:
        raise ValueError(
            f"{where}: frame_times_s has {len(t)} entries but the data have T = {shape[0]} frames; "
            f"{HOW['frame_times_s']}"
        )
    bad = next((i for i, v in enumerate(t) if not math.isfinite(v)), None)
    if bad is not None:
        raise ValueError(f"{where}: frame_times_s[{bad}] must be a finite number of seconds; got {times[bad]!r}")
    from ..sim.config import MAX_DURATION_S

    if t and not t[-1] - t[0] <= MAX_DURATION_S:  # as in scene files (an infinite span too)
        raise ValueError(
            f"{where}: frame_times_s spans {t[0]:g} to {t[-1]:g} s, over {MAX_DURATION_S:g} s as in scene "
            "files; times are in seconds (204.8 ms is 0.2048)"
        )
    if any(b <= a for a, b in zip(t, t[1:])):
        raise ValueError(f"{where}: frame_times_s must be strictly increasing (s)")
    out["frame_times_s"] = t
    sysd = out.get("system")
    if sysd is not None or require_system:
        if not isinstance(sysd, Mapping):
            raise ValueError(f"{where}: missing 'system'; {HOW['system']}")
        s = dict(sysd)
        for key in ("wavelength_um", "lateral_resolution_um", "axial_resolution_um"):
            if s.get(key) is None:
                if require_system:
                    raise ValueError(f"{where}: system is missing {key!r}; {HOW['system']}")
                continue
            s[key] = finite_positive(f"{where}: system.{key}", s[key])
        if s.get("wavelength_um") is not None and not (0.1 <= s["wavelength_um"] <= 20.0):
            raise ValueError(
                f"{where}: system.wavelength_um = {s['wavelength_um']} is outside 0.1-20 µm; "
                "wavelengths are in micrometres (840 nm is 0.84)"
            )
        n = s.get("refractive_index", 1.0)
        s["refractive_index"] = finite_positive(f"{where}: system.refractive_index", 1.0 if n is None else n)
        from ..conventions import REFRACTIVE_INDEX_RANGE

        lo_n, hi_n = REFRACTIVE_INDEX_RANGE
        if not lo_n <= s["refractive_index"] <= hi_n:
            raise ValueError(
                f"{where}: system.refractive_index must be within [{lo_n:g}, {hi_n:g}] (the phase index "
                f"of the medium, tissue about 1.38); got {s['refractive_index']}"
            )
        s.setdefault("name", "system")
        out["system"] = s
    br = out.get("block_raster")
    if br is not None:
        raster = BlockRaster(**br) if isinstance(br, Mapping) else br
        if not isinstance(raster, BlockRaster):
            raise TypeError(f"{where}: block_raster must be a dict; got {br!r}")
        if axes != "TYZX" or shape[1] != raster.n_y or shape[0] != raster.n_repeats:
            raise ValueError(
                f"{where}: block_raster {raster.to_dict()} does not match data {list(shape)} "
                f"({axes}): need T = n_repeats and Y = n_blocks·bscans_per_block"
            )
        out["block_raster"] = raster.to_dict()
    try:
        json.dumps(out)
    except TypeError as err:
        raise TypeError(f"{where}: metadata must be JSON-serializable ({err})") from None
    return out
