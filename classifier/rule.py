"""The ``indeterminate`` outcome: its physical definition and the rule that applies it (numpy only).

Physics (physics.md §5.3-5.4): LIV and OCDS are functionals of the intensity autocorrelation of a
pixel. Motion types differ in *how* it decays with the delay, the wavelength and the resolution.
When the scatterers' speckle does not decorrelate at all over the acquisition, LIV and OCDS are
those of a static sample (zero, or the noise's) for every motion type; when it decorrelates
completely within one frame interval, every frame is an independent speckle pattern and LIV/OCDS
are those of independent speckle (LIV at its N_eff-dependent plateau, OCDS at the estimator's
floor) for every motion type. In both regimes no method can tell the motion types apart.

Ground truth (:func:`classifier.truth.identifiability`): a sample is indeterminate when its moving
scatterers do not decorrelate over the acquisition (intensity correlation coefficient
``ρ_I(T) ≥ 1 − ε`` at every configuration, ``T`` the first-to-last frame delay; "static") or when
their field decorrelates completely within one frame interval (``|g1(Δt)|² ≤ ε`` at every
configuration; "decorrelated": each frame is a new speckle phase pattern and only the incoherent
transit term ``j/N_eff`` of physics.md §5.4 is left, the same in kind for diffusion and
random-ballistic motion), with ``ε = 0.05``. The same holds for signature models: a transit term
that still decays after the field has decorrelated was measured not to tell diffusion from
random-ballistic motion per pixel (``python -m research.ablation --indeterminate``).

Model: the network has an explicit class ``indeterminate`` trained on that ground truth. The rule
(stored in the model's metadata, applied by ``doct-classify`` and by the report) is

    indeterminate  if  argmax p = "indeterminate"  or  max p < min_probability

i.e. the pixel is also left undecided when no class is more likely than ``min_probability``
(0.5: more likely than all the others together).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = ["INDETERMINATE", "DEFAULT_MIN_PROBABILITY", "make_rule", "apply_rule", "REASONS"]

INDETERMINATE = "indeterminate"
DEFAULT_MIN_PROBABILITY = 0.5
#: Reason codes returned by :func:`apply_rule`.
REASONS = ("decided", "indeterminate class", "low probability")

_DEFINITION = (
    "indeterminate if argmax p is the class 'indeterminate' or max p < min_probability. The class "
    "'indeterminate' is trained on samples whose moving scatterers do not decorrelate over the "
    "acquisition (intensity correlation coefficient rho_I(T) >= 1 - epsilon at every configuration, "
    "T = first-to-last frame delay; rho_I = (|g1|^2 + j/N_eff)/(1 + 1/N_eff)) or whose field decorrelates "
    "completely within one frame interval (|g1(frame interval)|^2 <= epsilon at every configuration) "
    "(physics.md 5.3-5.4)."
)


def make_rule(epsilon: float, min_probability: float = DEFAULT_MIN_PROBABILITY) -> dict[str, Any]:
    """The rule as stored in model metadata (JSON-able)."""
    if not 0.0 <= float(min_probability) < 1.0:
        raise ValueError(f"min_probability must be in [0, 1); got {min_probability!r}")
    return {
        "kind": "class-or-threshold",
        "indeterminate_class": INDETERMINATE,
        "min_probability": float(min_probability),
        "epsilon": float(epsilon),
        "definition": _DEFINITION,
    }


def apply_rule(
    probabilities: np.ndarray, class_names: Sequence[str], rule: dict[str, Any], min_probability: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Decide each row of ``probabilities [N, C]``.

    Returns ``(labels [N] int, reasons [N] int)``: labels index ``class_names`` (indeterminate rows
    get the index of ``"indeterminate"``); reasons index :data:`REASONS`. ``min_probability``
    overrides the rule's threshold.
    """
    p = np.asarray(probabilities)
    if p.ndim != 2 or p.shape[1] != len(class_names):
        raise ValueError(f"probabilities must be [N, {len(class_names)}]; got {p.shape}")
    if rule.get("kind") != "class-or-threshold":
        raise ValueError(
            f"unknown indeterminate rule kind {rule.get('kind')!r} (this version knows "
            "'class-or-threshold'); update the classifier package"
        )
    name = rule["indeterminate_class"]
    if name not in class_names:
        raise ValueError(f"rule names class {name!r}, which is not among the model's classes {list(class_names)}")
    ind = list(class_names).index(name)
    thr = float(rule["min_probability"] if min_probability is None else min_probability)
    labels = p.argmax(axis=1)
    top = p.max(axis=1) if p.shape[0] else np.zeros(0, p.dtype)
    reasons = np.zeros(p.shape[0], np.int64)
    reasons[labels == ind] = 1
    low = (labels != ind) & (top < thr)
    reasons[low] = 2
    labels = np.where(low, ind, labels)
    return labels.astype(np.int64), reasons
