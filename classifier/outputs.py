"""Outputs of the classify path: the :class:`Classification` result and the files ``doct-classify`` writes
(numpy, tifffile, matplotlib; no torch).

``classes.tif`` (uint8: class index 0…C−1, the model's classes with ``indeterminate`` last, and
:data:`MASKED` for background/NaN pixels) with its ``legend.json``, ``probabilities.tif`` (float32
``[C, *S]``, NaN where masked), ``summary.json``, ``overlay.png`` (the classes on the mean intensity in
colour-blind-safe colours, masked pixels black, the model named) and, for models with a magnitude head,
``magnitude.tif`` (:data:`MAGNITUDE_CHANNELS`) and its picture ``magnitude.png`` (D in µm²/s, speed in
µm/s). The TIFFs carry ImageJ metadata (pixel size in µm, channel names: :mod:`torchdoct.measured.imagej`).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from torchdoct import figures  # torch-free: the project's axes and colours

from .rule import INDETERMINATE
from .runtime import ClassifierModel

__all__ = [
    "MASKED",
    "CLASS_COLORS",
    "MASKED_COLOR",
    "OUTPUT_FILES",
    "MAGNITUDE_FILES",
    "MAGNITUDE_CHANNELS",
    "Classification",
    "magnitude_maps",
    "write_classification",
]

#: Class-map value of background and NaN pixels.
MASKED = 255
#: Colours of the classes in the legend and overlay: the Okabe-Ito palette, told apart with any of the
#: common colour-vision deficiencies (blue, orange, bluish green; indeterminate reddish purple).
CLASS_COLORS = {c: figures.CLASS_COLORS[c] for c in ("diffusion", "ballistic", "flow", INDETERMINATE)}
#: Set labels of the conformal decision (two motion classes, :mod:`classifier.conformal`): neutral greys,
#: distinct from every class colour and from each other.
SET_COLORS = {"diffusion-or-ballistic": "#9A9A9A", "diffusion-or-flow": "#C4C4C4", "ballistic-or-flow": "#E8E8E8"}


def label_color(name: str) -> str:
    """The colour of a class or set label (:data:`CLASS_COLORS`, :data:`SET_COLORS`)."""
    return CLASS_COLORS.get(name) or SET_COLORS.get(name, "#000000")


#: Overlay colour of masked pixels (background or a NaN feature): black, unlike every class.
MASKED_COLOR = "#000000"


@dataclass
class Classification:
    """Result of :func:`classify_maps` (arrays over the maps' spatial shape ``S``)."""

    labels: np.ndarray  # uint8 [*S]: class index, MASKED for background/NaN
    probabilities: np.ndarray  # float32 [C, *S], NaN where masked
    classes: list[str]
    mask: np.ndarray  # bool [*S]: True where classified
    background: np.ndarray  # bool [*S]: True where masked as background (not NaN)
    intensity_db: np.ndarray | None
    model: ClassifierModel
    sources: list[str]
    axes: str
    pitch_um: dict[str, Any] | None
    info: dict[str, Any] = field(default_factory=dict)
    #: float32 [5, *S] (:data:`MAGNITUDE_CHANNELS`), NaN where masked or indeterminate; None without a magnitude head
    magnitude: np.ndarray | None = None
    #: labels of prediction sets of two classes (values ``len(classes) + j``; conformal decision only)
    set_labels: list[str] = field(default_factory=list)

    @property
    def label_names(self) -> list[str]:
        """The names of the values of ``labels``: the model's classes, then the set labels."""
        return list(self.classes) + list(self.set_labels)

    def counts(self) -> dict[str, int]:
        out = {c: int((self.labels == i).sum()) for i, c in enumerate(self.label_names)}
        out["masked"] = int((self.labels == MASKED).sum())
        return out


OUTPUT_FILES = ("classes.tif", "probabilities.tif", "legend.json", "summary.json", "overlay.png")
#: Written beside :data:`OUTPUT_FILES` by models with a magnitude head (the stack and its picture).
MAGNITUDE_FILES = ("magnitude.tif", "magnitude.png")
#: ``magnitude.tif`` (models with a magnitude head): log10 magnitude of the decided class and its intervals.
MAGNITUDE_CHANNELS = ("log10_magnitude", "lower_68", "upper_68", "lower_95", "upper_95")

#: z of the two-sided 95 % interval of a Gaussian.
_Z95 = 1.959964


def magnitude_maps(
    labels: np.ndarray, mean: np.ndarray, sd: np.ndarray, idx: np.ndarray, shape: tuple[int, ...]
) -> np.ndarray:
    """The ``magnitude.tif`` stack ``[5, *shape]`` (:data:`MAGNITUDE_CHANNELS`): at the decided pixels
    (``labels`` < K, the motion classes), the log10 magnitude of the decided class and its 68 % / 95 %
    intervals (mean ± SD, mean ± 1.96 SD of the model's Gaussian predictive distribution); NaN elsewhere.

    ``labels [N]``: the rule's decisions of the classified pixels, ``idx [N]`` their flat indices;
    ``mean``, ``sd [N, K]``: the model's magnitude head.
    """
    size = int(np.prod(shape))
    magnitude = np.full((len(MAGNITUDE_CHANNELS), size), np.nan, np.float32)
    k = mean.shape[1]
    motion = labels < k  # decided pixels: the magnitude of the decided class
    rows = np.flatnonzero(motion)
    m, s_ = mean[rows, labels[rows]], sd[rows, labels[rows]]
    for c, v in enumerate((m, m - s_, m + s_, m - _Z95 * s_, m + _Z95 * s_)):
        magnitude[c, idx[rows]] = v
    return magnitude.reshape((len(MAGNITUDE_CHANNELS), *shape))


def _cite_repository(text: str) -> str:
    """Bare ``physics.md N`` citations (in model metadata) as the repository file ``docs/physics.md §N``."""
    import re

    return re.sub(r"(?<!docs/)physics\.md\s*§?\s*(?=\d)", "docs/physics.md §", text)


def _legend(res: Classification) -> dict[str, Any]:
    rule = dict(res.model.rule)
    if isinstance(rule.get("definition"), str):
        rule["definition"] = _cite_repository(rule["definition"])
    return {
        "classes": [
            {"value": i, "name": c, "color": label_color(c)}
            for i, c in enumerate(getattr(res, "label_names", res.classes))
        ],
        "masked_value": MASKED,
        "masked_meaning": "background (mean dB intensity below the threshold) or a NaN feature",
        "rule": rule,
        "min_probability": res.info["min_probability"],
        # the decision that made the labels: "rule" (above) or "conformal" (prediction sets at alpha)
        "decision": res.info.get("decision", "rule"),
        **(
            {
                "conformal": {k: v for k, v in res.info["conformal"].items() if k != "set_sizes"},
                "set_labels": "a set of two classes: the pixel is one of them, the data do not tell which "
                "(docs/abstention.md)",
            }
            if res.info.get("conformal")
            else {}
        ),
        "axes": res.axes,
        "pitch_um": res.pitch_um,
    }


def _overlay(res: Classification, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import to_rgb
    from matplotlib.patches import Patch

    labels = res.labels
    inten = res.intensity_db
    title_extra = ""
    if labels.ndim == 3:
        mid = labels.shape[0] // 2
        labels = labels[mid]
        inten = inten[mid] if inten is not None else None
        title_extra = f", B-scan y = {mid}"
    if inten is not None and np.isfinite(inten).any():
        fin = inten[np.isfinite(inten)]
        lo, hi = np.percentile(fin, [1, 99.5])
        grey = np.clip((np.nan_to_num(inten, nan=lo, neginf=lo, posinf=hi) - lo) / max(hi - lo, 1e-9), 0, 1)
    else:
        grey = np.full(labels.shape, 0.5)
    rgb = np.repeat(grey[..., None], 3, axis=-1)
    for i, c in enumerate(res.label_names):
        sel = labels == i
        rgb[sel] = 0.45 * rgb[sel] + 0.55 * np.array(to_rgb(label_color(c)))
    masked = labels == MASKED  # no class tint: the intensity darkened towards black
    rgb[masked] = 0.45 * rgb[masked] + 0.55 * np.array(to_rgb(MASKED_COLOR))
    extent, _ = figures.image_extent(labels.shape, res.pitch_um)
    h = 5.0
    wdt = h * (extent[1] - extent[0]) / max(extent[2] - extent[3], 1e-9)
    fig, ax = plt.subplots(figsize=(min(max(wdt, 4.0), 14.0) + 2.0, h))
    figures.show_bscan(ax, rgb, pitch_um=res.pitch_um)
    counts = res.counts()
    total = max(int(res.mask.sum()), 1)
    handles = [Patch(color=label_color(c), label=f"{c} ({counts[c] / total:.0%})") for c in res.label_names]
    handles.append(
        Patch(facecolor=MASKED_COLOR, edgecolor="#808080", label=f"masked: background or NaN ({counts['masked']} px)")
    )
    ax.legend(
        handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, title="class (% of classified)"
    )
    ax.set_title(
        f"motion type on mean intensity, model {_model_name(res)}, pool {res.info['pool']}{title_extra}", fontsize=9
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120, bbox_inches="tight")  # the legend beside the image stays whole
    plt.close(fig)


def _model_name(res: Classification) -> str:
    """The model as the figures name it: its spec name and file (``signature-bscan (signature-bscan.onnx)``)."""
    if res.model is None:  # a result assembled by hand (no model file)
        return "not named"
    spec = res.model.metadata.get("spec", {}).get("name") or res.model.path.stem
    return spec if res.model.path.name == f"{spec}.onnx" else f"{spec} ({res.model.path.name})"


def _magnitude_picture(res: Classification, path: str) -> None:
    """``magnitude.png``: the predicted magnitude of the decided pixels on µm axes, the diffusion
    coefficient (µm²/s) where the class is diffusion and the speed (µm/s) where it is ballistic or flow,
    each on a logarithmic colour bar with its unit (cividis, readable with colour-vision deficiencies)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    from torchdoct import figures

    assert res.magnitude is not None  # drawn only for a result with magnitudes (write_classification)
    mag = res.magnitude[0]
    labels = res.labels
    title_extra = ""
    if labels.ndim == 3:
        mid = labels.shape[0] // 2
        mag, labels, title_extra = mag[mid], labels[mid], f", B-scan y = {mid}"
    panels = [
        ("diffusion", ("diffusion",), "D (µm²/s)"),
        ("ballistic or flow", tuple(c for c in ("ballistic", "flow") if c in res.classes), "speed (µm/s)"),
    ]
    extent, _ = figures.image_extent(labels.shape, res.pitch_um)
    h = 4.2
    wdt = h * (extent[1] - extent[0]) / max(extent[2] - extent[3], 1e-9)
    fig, axes = plt.subplots(1, 2, figsize=(2 * (min(max(wdt, 3.0), 10.0) + 1.6), h), constrained_layout=True)
    cmap = plt.get_cmap(figures.MAGNITUDE_CMAP).with_extremes(bad="#d9d9d9")
    for ax, (what, classes, unit) in zip(axes, panels):
        sel = np.isin(labels, [res.classes.index(c) for c in classes if c in res.classes]) & np.isfinite(mag)
        vals = np.where(sel, 10.0 ** np.where(sel, mag, 0.0), np.nan)
        fin = vals[np.isfinite(vals)]
        lo, hi = np.percentile(fin, [1, 99]) if fin.size else (1e-3, 1.0)
        hi = max(hi, lo * 1.0001)
        im = figures.show_bscan(ax, vals, pitch_um=res.pitch_um, cmap=cmap, norm=LogNorm(vmin=lo, vmax=hi))
        fig.colorbar(im, ax=ax, shrink=0.85).set_label(unit)
        ax.set_title(f"{what}: {unit}, {fin.size} px (grey: not this class)", fontsize=8)
    fig.suptitle(
        f"predicted magnitude (median of the model's distribution), model {_model_name(res)}, "
        f"pool {res.info['pool']}{title_extra}",
        fontsize=9,
    )
    fig.savefig(path, dpi=120)
    plt.close(fig)


def check_outputs(out_dir: str | os.PathLike, force: bool) -> dict[str, Path]:
    """The output set of ``doct-classify`` in ``out_dir`` (every file it may hold, :data:`MAGNITUDE_FILES`
    included), checked before the work: ``out_dir`` must not be a file, and no file of the set may
    exist unless ``force``."""
    from torchdoct.files import check_out

    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file; give a directory")
    return {
        name: (check_out(out / name, force, Path(name).suffix, f"--out {out}: {name}") if out.is_dir() else out / name)
        for name in OUTPUT_FILES + MAGNITUDE_FILES
    }


def write_classification(res: Classification, out_dir: str | os.PathLike, *, force: bool = False) -> list[Path]:
    """Write :data:`OUTPUT_FILES` (and ``magnitude.tif`` when the model predicts magnitudes) into
    ``out_dir`` (created if missing), all together or none (:func:`torchdoct.files.output_set`: an error,
    Ctrl-C or SIGTERM leaves the folder as it was); nothing is overwritten without ``force``, and with it
    an earlier run's file this run does not write (``magnitude.tif``/``.png`` of another model) is removed."""
    import tifffile

    from torchdoct.files import atomic_write, output_set

    out = Path(out_dir)
    every = check_outputs(out, force)
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    try:
        with output_set(every.values(), force) as stage:
            written = _write_into(res, {name: stage(p) for name, p in every.items()}, tifffile, atomic_write)
    except BaseException:
        if created and not any(out.iterdir()):  # leave no empty folder behind either
            out.rmdir()
        raise
    return [every[name] for name in written]


def _write_into(res: Classification, paths: dict[str, Path], tifffile, atomic_write) -> list[str]:
    """Write the files of :func:`write_classification` to ``paths`` (staged); returns the names written."""
    names = OUTPUT_FILES + (MAGNITUDE_FILES if res.magnitude is not None else ())
    from torchdoct.measured.imagej import imagej_pages, imagej_write_options

    def imagej(arr, channels, desc, unit=None):  # ImageJ's description (µm scale, channel names), the JSON as Info
        axes = ("C" if len(channels) > 1 or arr.ndim > len(res.axes) else "") + res.axes
        return imagej_write_options(arr.shape, axes, res.pitch_um, channels, description=desc, value_unit=unit)

    def pages(arr, channels):  # a volume's channels fastest, as ImageJ reads a hyperstack
        return imagej_pages(arr, ("C" if len(channels) > 1 or arr.ndim > len(res.axes) else "") + res.axes)

    legend = _legend(res)
    desc_classes = json.dumps({"legend": legend, "source": res.sources})
    desc_probs = json.dumps(
        {"channels": res.classes, "axes": "C" + res.axes, "unit": "probability", "masked": "NaN", "source": res.sources}
    )
    summary = {
        "counts": res.counts(),
        "sources": res.sources,
        "model": res.model.path.name,
        "model_spec": res.model.metadata["spec"]["name"],
        "info": res.info,
    }
    atomic_write(
        paths["classes.tif"],
        lambda t: tifffile.imwrite(t, pages(res.labels, ["class"]), **imagej(res.labels, ["class"], desc_classes)),
    )
    atomic_write(
        paths["probabilities.tif"],
        lambda t: tifffile.imwrite(
            t,
            pages(res.probabilities, list(res.classes)),
            **imagej(res.probabilities, list(res.classes), desc_probs, "probability"),
        ),
    )

    def dump(obj):
        def w(t):
            with open(t, "w", encoding="utf-8") as fh:
                json.dump(obj, fh, indent=1)

        return w

    atomic_write(paths["legend.json"], dump(legend))
    atomic_write(paths["summary.json"], dump(summary))
    atomic_write(paths["overlay.png"], lambda t: _overlay(res, t))
    if res.magnitude is not None:
        desc_mag = json.dumps(
            {
                "channels": list(MAGNITUDE_CHANNELS),
                "axes": "C" + res.axes,
                "unit": "log10(µm^2/s) where the class is diffusion, log10(µm/s) where ballistic or flow",
                "intervals": "68 % = mean ± SD, 95 % = mean ± 1.96 SD of the model's Gaussian predictive distribution",
                "masked": "NaN (also where indeterminate)",
                "source": res.sources,
            }
        )
        atomic_write(
            paths["magnitude.tif"],
            lambda t: tifffile.imwrite(
                t,
                pages(res.magnitude, list(MAGNITUDE_CHANNELS)),
                **imagej(res.magnitude, list(MAGNITUDE_CHANNELS), desc_mag),
            ),
        )
        atomic_write(paths["magnitude.png"], lambda t: _magnitude_picture(res, t))
    return list(names)
