"""Split-conformal prediction sets over the motion classes: decide only where the evidence separates them
(numpy only: the classify path).

**Score** (least ambiguous set-valued classifier, LAC): ``s(x, y) = 1 − p_y(x)``, the network's probability
of the true class ``y`` (the model's classes, ``indeterminate`` included: its ground truth is
:func:`classifier.truth.identifiability`).

**Calibration** (:mod:`classifier.calibrate`): ``n`` exchangeable samples drawn like the data (one per
simulated parameter group, so that the samples are independent) give scores ``s_1 … s_n``; the threshold
at error level ``α`` is the ``k``-th smallest, ``k = ⌈(n + 1)(1 − α)⌉`` (:func:`conformal_quantile`;
``+∞`` when ``k > n``). The set of a new pixel is ``C(x) = {y : 1 − p_y(x) ≤ q̂}``.

**Class-conditional (Mondrian) thresholds** (the default, ``mode = "class-conditional"``): the quantile is
taken per true class, over the ``n_k`` calibration samples of class ``k``, giving ``q̂_k``; the set is
``C(x) = {k : 1 − p_k(x) ≤ q̂_k}``. ``mode = "marginal"``: one threshold over all samples.

**Guarantee** (the split-conformal theorem, applied within each class for Mondrian thresholds): for a new
pixel exchangeable with the calibration samples, ``P(y ∈ C(x) | y = k) ≥ 1 − α`` for every class ``k``
(marginal mode: ``P(y ∈ C(x)) ≥ 1 − α``), and at most ``1 − α + 1/(n_k + 1)`` when the scores have no
ties. So on such data at most a share ``α`` of each class's pixels gets a set without its class, which
bounds the share decided as another class. It holds on average over pixels drawn like the calibration
data (the model's training prior at one pool size), not per phantom, per speed, per direction or per
pixel; data unlike the calibration set (another prior, a system the model was not trained for,
correlated neighbouring pixels, motion outside the prior) carry no guarantee.

**Labels** (:func:`set_labels`): ``indeterminate`` in a set means "not identifiable" and never contradicts a
motion type, so the label is made of the motion classes in the set: one motion class is a decision
(``flow``), two are a set label (``ballistic-or-flow``), three or none are ``indeterminate``.

**Pools**: the threshold depends on how many independent pixels were averaged (the model's ``pool_pixels``
input): calibrated at a few pool sizes, a pixel takes the threshold of the largest calibrated size not
above its own ``pool_pixels`` (:func:`thresholds_for`).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = [
    "SCHEMA_VERSION",
    "conformal_quantile",
    "scores_lac",
    "prediction_sets",
    "set_label_names",
    "set_labels",
    "pool_thresholds",
    "thresholds_for",
    "decide",
    "check_calibration",
    "MODES",
]

SCHEMA_VERSION = 1
INDETERMINATE = "indeterminate"
#: ``doct-classify``'s default error level α of the prediction sets.
DEFAULT_ALPHA = 0.1


def conformal_quantile(scores: np.ndarray, alpha: float) -> float:
    """The split-conformal threshold: the ``⌈(n + 1)(1 − α)⌉``-th smallest score (``+∞`` beyond ``n``)."""
    s = np.sort(np.asarray(scores, np.float64).ravel())
    if not 0.0 < float(alpha) < 1.0:
        raise ValueError(f"alpha must be in (0, 1); got {alpha!r}")
    if s.size == 0 or not np.all(np.isfinite(s)):
        raise ValueError("conformal scores must be a non-empty array of finite numbers")
    k = int(math.ceil((s.size + 1) * (1.0 - float(alpha))))
    return math.inf if k > s.size else float(s[k - 1])


def scores_lac(probabilities: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """``1 − p_y``: the LAC score of each row of ``probabilities [N, C]`` at its true class ``truth [N]``."""
    p = np.asarray(probabilities, np.float64)
    return 1.0 - p[np.arange(p.shape[0]), np.asarray(truth, np.int64)]


def prediction_sets(probabilities: np.ndarray, threshold: np.ndarray | float) -> np.ndarray:
    """Membership ``[N, C]`` (bool) of the sets ``{y : 1 − p_y ≤ q̂_y}``; ``threshold`` a number, ``[C]`` or ``[N, C]``."""
    p = np.asarray(probabilities, np.float64)
    q = np.asarray(threshold, np.float64)
    return (1.0 - p) <= q  # a number, one per class [C] or per row and class [N, C]


def set_label_names(classes: Sequence[str]) -> list[str]:
    """The set labels of two motion classes (``a-or-b``, in class order), after the model's classes."""
    motions = [c for c in classes if c != INDETERMINATE]
    return [f"{a}-or-{b}" for a, b in itertools.combinations(motions, 2)]


def set_labels(members: np.ndarray, classes: Sequence[str]) -> np.ndarray:
    """Label index per row of ``members [N, C]`` (module docstring): a motion class, ``indeterminate``, or
    ``len(classes) + j`` for the ``j``-th name of :func:`set_label_names`."""
    classes = list(classes)
    ind = classes.index(INDETERMINATE)
    motion_idx = [i for i, c in enumerate(classes) if c != INDETERMINATE]
    m = np.asarray(members, bool)[:, motion_idx]
    n = m.sum(axis=1)
    out = np.full(m.shape[0], ind, np.int64)
    one = n == 1
    out[one] = np.asarray(motion_idx)[m[one].argmax(axis=1)]
    for j, (a, b) in enumerate(itertools.combinations(range(len(motion_idx)), 2)):
        out[(n == 2) & m[:, a] & m[:, b]] = len(classes) + j
    return out


def check_calibration(cal: dict[str, Any], classes: Sequence[str], where: str) -> None:
    """A ``ValueError`` naming ``where`` and the field when a calibration record is not one this version reads."""
    if not isinstance(cal, dict) or cal.get("schema_version") != SCHEMA_VERSION:
        raise ValueError(
            f"{where}: calibration schema_version {cal.get('schema_version') if isinstance(cal, dict) else None!r} "
            f"is not {SCHEMA_VERSION}; calibrate the model again (python -m classifier.calibrate)"
        )
    if cal.get("mode", MODES[0]) not in MODES:
        raise ValueError(
            f"{where}: calibration mode {cal.get('mode')!r} is not one of {', '.join(MODES)}; calibrate the model again"
        )
    if cal.get("score") != "lac" or list(cal.get("classes", [])) != list(classes):
        raise ValueError(
            f"{where}: calibration of classes {cal.get('classes')!r} with score {cal.get('score')!r}; "
            f"the model's classes are {list(classes)} (score 'lac'): calibrate this model again"
        )
    pools = cal.get("pools")
    if not isinstance(pools, list) or not pools:
        raise ValueError(f"{where}: calibration has no 'pools' list; calibrate the model again")
    for p in pools:
        sc = p.get("scores") if isinstance(p, dict) else None
        tr = p.get("truth") if isinstance(p, dict) else None
        if (
            not isinstance(sc, list)
            or not sc
            or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in sc)
            or not isinstance(tr, list)
            or len(tr) != len(sc)
            or not all(isinstance(v, int) and 0 <= v < len(classes) for v in tr)
            or not isinstance(p.get("pool_pixels"), (int, float))
        ):
            raise ValueError(
                f"{where}: calibration pool {p.get('pool_pixels') if isinstance(p, dict) else p!r} lacks "
                "'pool_pixels', finite 'scores' or a class index per score in 'truth'; calibrate the model again"
            )


MODES = ("class-conditional", "marginal")


def pool_thresholds(pool: dict[str, Any], n_classes: int, alpha: float, mode: str = MODES[0]) -> np.ndarray:
    """Thresholds ``[C]`` of one calibrated pool: per class (Mondrian) or one for all (marginal)."""
    scores = np.asarray(pool["scores"], np.float64)
    if mode == "marginal":
        return np.full(n_classes, conformal_quantile(scores, alpha))
    if mode != "class-conditional":
        raise ValueError(f"mode must be one of {', '.join(MODES)}; got {mode!r}")
    truth = np.asarray(pool["truth"], np.int64)
    out = np.empty(n_classes)
    for k in range(n_classes):
        sk = scores[truth == k]
        out[k] = conformal_quantile(sk, alpha) if sk.size else math.inf
    return out


def thresholds_for(cal: dict[str, Any], pool_pixels: np.ndarray, alpha: float, mode: str = MODES[0]) -> np.ndarray:
    """The thresholds ``[N, C]`` of every row: those of the largest calibrated pool size ≤ its ``pool_pixels``
    (the smallest calibrated size below all of them)."""
    pools = sorted(cal["pools"], key=lambda p: p["pool_pixels"])
    sizes = np.array([float(p["pool_pixels"]) for p in pools])
    qs = np.stack([pool_thresholds(p, len(cal["classes"]), alpha, mode) for p in pools])
    k = np.clip(np.searchsorted(sizes, np.asarray(pool_pixels, np.float64), side="right") - 1, 0, sizes.size - 1)
    return qs[k]


def decide(
    probabilities: np.ndarray,
    pool_pixels: np.ndarray,
    classes: Sequence[str],
    cal: dict[str, Any],
    alpha: float,
    mode: str = MODES[0],
) -> tuple[np.ndarray, np.ndarray]:
    """``(labels [N], set_size [N])``: the label of every row's prediction set (:func:`set_labels`) and
    the number of model classes in it."""
    q = thresholds_for(cal, pool_pixels, alpha, mode)
    members = prediction_sets(probabilities, q)
    return set_labels(members, classes), members.sum(axis=1)
