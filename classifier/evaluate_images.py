"""Scores of a ``doct-classify`` output against the ground truth of a rendered phantom.

The image chain is ``torchdoct render`` (a phantom's complex sequence with its ground truth:
``labels``, the motion code per pixel, and ``label_params``, D in µm²/s and speed in µm/s per pixel;
README "Images") → ``torchdoct maps --signature`` → ``doct-classify``. :func:`score_images` compares
the classification directory with the labels:

* only *labelled moving* pixels count: codes 2 (diffusion), 3 (random-ballistic), 4 (flow) of
  ``torchdoct.image.phantom.MOTION_CODES``; static, empty and mixed pixels, and pixels that
  ``doct-classify`` masked (background or NaN features), are not scored;
* ``edge_um`` leaves out pixels closer than that to a pixel of another label (a box of half-width
  ``edge_um`` per axis, pitch from ``legend.json``): the axial and lateral reductions and ``--pool``
  mix the features of neighbouring regions there;
* **coverage** = decided share (not ``indeterminate``) of the scored pixels; **recall** per motion type
  = share of its decided pixels given the right type; **balanced accuracy** = the mean recall over the
  motion types present; **accuracy** = right share of all decided pixels (the definitions of the
  model reports, :mod:`classifier.report`, with "identifiable" replaced by "labelled moving");
* **magnitude** (when ``magnitude.tif`` exists and ``label_params`` are given): on the pixels decided
  with the right type, ``log10`` of the predicted D or v minus ``log10`` of the rendered one; the
  median ``|error|`` and the shares inside the model's 68 % and 95 % intervals;
* per region: pixels grouped by (motion type, rendered magnitude), each with the same scores.

numpy and tifffile only (the classify path: no torch).
"""

from __future__ import annotations

import json
import math
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from torchdoct.files import read_capped
from torchdoct.measured.guards import json_loads
from torchdoct.runtime import interrupt as _interrupt

#: Motion codes of rendered labels (``torchdoct.image.phantom.MOTION_CODES``) → classifier class names.
MOVING_CODES = {2: "diffusion", 3: "ballistic", 4: "flow"}
#: Row of ``label_params`` holding the magnitude of each motion type (D in µm²/s; speed in µm/s).
PARAM_ROW = {"diffusion": 0, "ballistic": 1, "flow": 1}
_MASKED = 255

__all__ = ["MOVING_CODES", "read_rendered_labels", "score_images", "format_scores", "main"]


def read_rendered_labels(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """``(labels, label_params)`` of a ``torchdoct render`` output (``.npz`` or ``.h5``).

    ``label_params`` is ``None`` when the file has none. Raises ``ValueError`` naming the file and
    the fix when it is missing, unreadable or holds no ``labels``.
    """
    from torchdoct.files import check_regular_file

    p = Path(path)
    try:
        check_regular_file(p, "sequence file")
    except FileNotFoundError:
        raise ValueError(
            f"{p}: no such file; give the sequence file that `torchdoct render` wrote (.npz or .h5)"
        ) from None
    from torchdoct.measured.guards import check_declared_size, check_npz_sizes

    if p.suffix == ".npz":
        check_npz_sizes(p)  # every member's declared size before any is decompressed
        try:
            with np.load(p, allow_pickle=False) as z:
                names = set(z.files)
                labels = z["labels"] if "labels" in names else None
                params = z["label_params"] if "label_params" in names else None
        except (OSError, ValueError, EOFError) as exc:
            raise ValueError(f"{p}: not a readable .npz file ({exc}); render the phantom again") from None
    elif p.suffix in (".h5", ".hdf5"):
        import h5py

        try:
            with h5py.File(p, "r") as fh:
                for key in ("labels", "label_params"):
                    if key in fh and hasattr(fh[key], "shape"):
                        check_declared_size(f"{p.name}[{key}]", fh[key].shape, fh[key].dtype.itemsize, "dataset")
                labels = fh["labels"][()] if "labels" in fh else None
                params = fh["label_params"][()] if "label_params" in fh else None
        except OSError as exc:
            raise ValueError(f"{p}: not a readable HDF5 file ({exc}); render the phantom again") from None
    else:
        raise ValueError(f"{p}: labels are stored in .npz or .h5 files by `torchdoct render`; got {p.suffix!r}")
    if labels is None:
        raise ValueError(f"{p}: no 'labels' array; give the file that `torchdoct render` wrote for a phantom")
    return np.asarray(labels), None if params is None else np.asarray(params, np.float64)


def _read_classified(out_dir: Path) -> tuple[np.ndarray, dict[str, Any], np.ndarray | None]:
    import tifffile

    if not out_dir.is_dir():
        raise ValueError(f"{out_dir}: not a directory; give the --out directory of doct-classify")
    for name in ("classes.tif", "legend.json"):
        if not (out_dir / name).is_file():
            raise ValueError(f"{out_dir}: {name} is missing; run doct-classify with --out {out_dir}")
    try:
        legend = json_loads(read_capped(out_dir / "legend.json", "legend.json").decode("utf-8"))
        classes = tifffile.imread(out_dir / "classes.tif")
    except (OSError, ValueError) as exc:
        raise ValueError(f"{out_dir}: unreadable doct-classify output ({exc}); run doct-classify again") from None
    mag = None
    if (out_dir / "magnitude.tif").is_file():
        from torchdoct.measured.imagej import restore_channels

        from .outputs import MAGNITUDE_CHANNELS

        with tifffile.TiffFile(out_dir / "magnitude.tif") as tf:
            mag = tf.asarray().astype(np.float64)
            if classes.ndim == 3:  # a volume's ImageJ pages: channel fastest, back to [C, Y, Z, X]
                mag = restore_channels(mag, len(MAGNITUDE_CHANNELS), tf)
    return classes, legend, mag


def _interior(labels: np.ndarray, edge_px: tuple[int, ...]) -> np.ndarray:
    """True where every pixel of the box of half-widths ``edge_px`` (per axis; clipped at the image
    border) has the pixel's label: the minimum and the maximum label over the box equal it."""
    lo = labels.astype(np.int64)
    hi = lo
    for axis, r in enumerate(edge_px):
        if r == 0:
            continue
        pad = [(0, 0)] * lo.ndim
        pad[axis] = (r, r)
        lo = np.lib.stride_tricks.sliding_window_view(np.pad(lo, pad, mode="edge"), 2 * r + 1, axis=axis).min(-1)
        hi = np.lib.stride_tricks.sliding_window_view(np.pad(hi, pad, mode="edge"), 2 * r + 1, axis=axis).max(-1)
    return (lo == labels) & (hi == labels)


def _scores(
    truth: np.ndarray, decided: np.ndarray, mag_err: np.ndarray | None, in68: np.ndarray | None, in95: np.ndarray | None
) -> dict[str, Any]:
    """Scores of the scored pixels: ``truth`` and ``decided`` index the motion types
    (``list(MOVING_CODES.values())``); ``decided`` is -1 where indeterminate."""
    names = list(MOVING_CODES.values())
    out: dict[str, Any] = {"pixels": int(truth.size)}
    dec = decided >= 0
    out["decided"] = int(dec.sum())
    out["coverage"] = float(dec.mean()) if truth.size else None
    per: dict[str, Any] = {}
    recalls = []
    for k, name in enumerate(names):
        t = truth == k
        if not t.any():
            continue
        d = t & dec
        rec = float((decided[d] == k).mean()) if d.any() else None
        per[name] = {
            "pixels": int(t.sum()),
            "coverage": float(d.sum() / t.sum()),
            "recall": rec,
            "decided_as": {n: int((decided[t] == j).sum()) for j, n in enumerate(names)},
        }
        if rec is not None:
            recalls.append(rec)
    out["per_class"] = per
    out["balanced_accuracy"] = float(np.mean(recalls)) if recalls and len(recalls) == len(per) else None
    out["accuracy"] = float((decided[dec] == truth[dec]).mean()) if dec.any() else None
    if mag_err is not None:
        assert in68 is not None and in95 is not None  # given with mag_err
        right = dec & (decided == truth) & np.isfinite(mag_err)
        out["magnitude"] = {
            "pixels": int(right.sum()),
            "median_abs_log10_error": float(np.median(np.abs(mag_err[right]))) if right.any() else None,
            "median_log10_error": float(np.median(mag_err[right])) if right.any() else None,
            "in_68": float(in68[right].mean()) if right.any() else None,
            "in_95": float(in95[right].mean()) if right.any() else None,
        }
    return out


def score_images(
    classified_dir: str | os.PathLike,
    labels: np.ndarray | str | os.PathLike,
    label_params: np.ndarray | None = None,
    *,
    edge_um: float = 0.0,
) -> dict[str, Any]:
    """Scores of the ``doct-classify`` output in ``classified_dir`` against rendered labels (module docstring).

    ``labels``: the motion codes per pixel (same spatial shape as ``classes.tif``), or the path of the
    ``torchdoct render`` output (then ``label_params`` are read from it too). ``label_params``:
    ``[2, *shape]`` D (µm²/s) and speed (µm/s), for the magnitude error and the per-region table.
    ``edge_um``: leave out pixels within this distance (µm, per axis) of a pixel of another label.

    Returns a JSON-able dict: ``overall`` (pixels, decided, coverage, accuracy, balanced_accuracy,
    per_class, magnitude), ``regions`` (one entry per motion type and rendered magnitude ``value`` in
    ``unit``, the same scores), ``pool`` (from ``summary.json``), ``edge_um``.
    """
    out_dir = Path(classified_dir)
    if isinstance(labels, (str, os.PathLike)):
        labels, file_params = read_rendered_labels(labels)
        label_params = file_params if label_params is None else label_params
    labels = np.asarray(labels)
    classes, legend, mag = _read_classified(out_dir)
    if classes.shape != labels.shape:
        raise ValueError(
            f"{out_dir}/classes.tif has shape {classes.shape} but the labels have {labels.shape}; "
            "give the labels of the phantom rendering that these maps were computed from"
        )
    try:
        values = {str(c["name"]): int(c["value"]) for c in legend["classes"]}
    except (KeyError, TypeError, ValueError):
        raise ValueError(
            f"{out_dir}/legend.json: no list of classes with 'name' and 'value'; run doct-classify again"
        ) from None
    names = list(values)
    missing = [n for n in MOVING_CODES.values() if n not in names]
    if missing:
        raise ValueError(f"{out_dir}/legend.json: the model has no class {missing}; score a motion-type classification")
    moving = list(MOVING_CODES.values())
    decided = np.full(classes.shape, -1, np.int64)  # classes.tif value -> motion-type index, -1 otherwise
    for k, name in enumerate(moving):
        decided[classes == values[name]] = k
    edge_um = float(edge_um)
    if not (math.isfinite(edge_um) and edge_um >= 0):
        raise ValueError(f"edge_um must be a finite distance >= 0 µm; got {edge_um!r}")
    axes = str(legend.get("axes", ""))
    pitch = legend.get("pitch_um") or {}
    if edge_um > 0 and (len(axes) != labels.ndim or any(a.lower() not in pitch for a in axes)):
        raise ValueError(
            f"{out_dir}/legend.json: no pixel pitch per axis ({axes!r}, {pitch!r}); "
            "edge_um needs maps with a pitch (torchdoct maps --pitch-um)"
        )
    edge_px = tuple(int(math.floor(edge_um / float(pitch[a.lower()]) + 1e-9)) for a in axes) if edge_um > 0 else ()
    keep = _interior(labels, edge_px) if edge_px else np.ones(labels.shape, bool)
    keep &= np.isin(labels, list(MOVING_CODES)) & (classes != _MASKED)

    truth = np.full(labels.shape, -1, np.int64)
    for k, code in enumerate(MOVING_CODES):
        truth[labels == code] = k
    magnitude = None
    if label_params is not None:
        label_params = np.asarray(label_params, np.float64)
        if label_params.shape != (2, *labels.shape):
            raise ValueError(
                f"label_params has shape {label_params.shape}; want (2, *labels.shape) = "
                f"{(2, *labels.shape)} (D in µm²/s and speed in µm/s per pixel)"
            )
        magnitude = np.full(labels.shape, np.nan)
        for code, name in MOVING_CODES.items():
            sel = labels == code
            magnitude[sel] = label_params[PARAM_ROW[name]][sel]
    mag_err = in68 = in95 = None
    if mag is not None and magnitude is not None:
        with np.errstate(divide="ignore", invalid="ignore"):
            true_log = np.log10(magnitude)
        mag_err = mag[0] - true_log
        in68 = (mag[1] <= true_log) & (true_log <= mag[2])
        in95 = (mag[3] <= true_log) & (true_log <= mag[4])

    def sub(sel: np.ndarray) -> dict[str, Any]:
        return _scores(
            truth[sel],
            decided[sel],
            None if mag_err is None else mag_err[sel],
            None if in68 is None else in68[sel],
            None if in95 is None else in95[sel],
        )

    result: dict[str, Any] = {"edge_um": edge_um, "overall": sub(keep)}
    summary = out_dir / "summary.json"
    if summary.is_file():
        try:
            result["pool"] = (
                json_loads(read_capped(summary, "summary.json").decode("utf-8")).get("info", {}).get("pool")
            )
        except (ValueError, AttributeError):  # not doct-classify's summary: no pool recorded
            result["pool"] = None
    regions = []
    if magnitude is not None:
        for code, name in MOVING_CODES.items():
            sel = keep & (labels == code)
            for value in np.unique(magnitude[sel]):
                r = sub(sel & (magnitude == value))
                r.pop("balanced_accuracy", None)
                regions.append(
                    {"motion": name, "value": float(value), "unit": "µm²/s" if name == "diffusion" else "µm/s", **r}
                )
    result["regions"] = regions
    return result


def format_scores(scores: dict[str, Any]) -> str:
    """A few lines of text: the overall scores and one line per region."""

    def f(v: Any) -> str:
        return "n/a" if v is None else f"{v:.3f}"

    o = scores["overall"]
    lines = [
        f"pool {scores.get('pool')}, edge {scores['edge_um']:g} µm: {o['pixels']} labelled moving pixels, "
        f"coverage {f(o['coverage'])}, balanced accuracy {f(o['balanced_accuracy'])}, accuracy {f(o['accuracy'])}"
    ]
    m = o.get("magnitude")
    if m:
        lines.append(
            f"  magnitude (right type, {m['pixels']} px): median |log10 error| {f(m['median_abs_log10_error'])}, "
            f"in 68 % / 95 % interval {f(m['in_68'])} / {f(m['in_95'])}"
        )
    for r in scores["regions"]:
        c = r["per_class"].get(r["motion"], {})
        mm = r.get("magnitude") or {}
        lines.append(
            f"  {r['motion']:>9} {r['value']:<7g} {r['unit']:<5}: {r['pixels']:5d} px, coverage {f(r['coverage'])}, "
            f"recall {f(c.get('recall'))}, decided as {c.get('decided_as')}, "
            f"median |log10 error| {f(mm.get('median_abs_log10_error'))}"
        )
    return "\n".join(lines)


@_interrupt.entry_point  # a closed output pipe (| head) ends quietly; Ctrl-C: one line (torchdoct.runtime.interrupt)
def main(argv: list[str] | None = None) -> int:
    """``python -m classifier.evaluate_images CLASSIFIED RENDERED [--edge-um E] [--json]``: print the scores."""
    import argparse

    ap = argparse.ArgumentParser(
        prog="python -m classifier.evaluate_images",
        description="Score a doct-classify output against the labels of a rendered phantom.",
    )
    ap.add_argument("classified", help="the --out directory of doct-classify")
    ap.add_argument("rendered", help="the sequence file of `torchdoct render` (.npz or .h5) the maps came from")
    ap.add_argument(
        "--edge-um",
        type=float,
        default=0.0,
        help="leave out pixels within this distance (µm, per axis) of another label (default 0)",
    )
    ap.add_argument("--json", action="store_true", help="print the scores as JSON")
    ap.add_argument(
        "--no-progress", action="store_true", help="accepted as on every command; scoring shows no progress bar"
    )
    args = ap.parse_args(argv)
    try:
        scores = score_images(args.classified, args.rendered, edge_um=args.edge_um)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(scores, indent=1) if args.json else format_scores(scores))
    return 0


if __name__ == "__main__":
    sys.exit(main())
