"""What accuracy costs in time: measured trade-off curves of the motion-type classifier.

Four knobs are turned one at a time away from the shipped single-acquisition model's settings
(:data:`DEFAULTS`: 270 training draws, spec ``single-acquisition``, hidden layers (64, 64),
``doct-classify --pool 1``); every point is evaluated on the same held-out test split (seed 0, split
``test``, the shipped model's test draws, never seen in training):

* **training draws**: networks trained on prefixes of one cached training split. Draws are
  stratified by motion type and magnitude and a draw does not depend on how many are made
  (:mod:`classifier.dataset`), so a prefix of ``n`` draws is bit-identical to a split simulated with
  ``n`` draws. Time = simulation of those draws (the split's recorded seconds per draw × ``n``) +
  simulation of the validation split + network training ("build time");
* **feature spec**: ``one-configuration`` (840 nm at 4.9/3.8 µm only: LIV and OCDS at the original
  resolution, :func:`one_configuration_spec`), ``single-acquisition``, ``two-wavelength``. The
  one-configuration features are the matching columns of the single-acquisition dataset: every
  configuration of a scene sees the same scatterers and its own independent noise, so these columns
  have exactly the distribution a one-system simulation would give; its ground truth is recomputed
  with its single configuration (:func:`classifier.truth.identifiability`), which makes more
  draws indeterminate. Its simulation cost per draw is the single-acquisition one scaled by the ratio
  of the two measured on the same draws. Build time as above;
* **model size**: hidden widths and depth; time = inference per sample (onnxruntime, the classify
  path) and training;
* **pooling**: the *shipped* ONNX model at ``n`` = 1, 4, 9, 25 independent pixels (the test split's
  pooled samples, as in its report); time = classify-path inference per map pixel: the N × N box
  mean of :func:`classifier.infer.pool_features` with N = √n (independent pixels on the grid),
  onnxruntime and the rule, timed on a synthetic map of test features. What pooling really costs is
  spatial resolution: ``n`` pixels share one decision, so this axis has a second front against
  pixels per decision.

Error = 1 − balanced accuracy over the identifiable test samples that the indeterminate rule decides
(:func:`classifier.report.evaluate`); coverage (decided share of the identifiable ones) and the strict
accuracy on the draws identifiable under the single-acquisition truth (undecided counts as wrong: a
common denominator across specs) stand beside it. Standard errors come from a bootstrap over test
*draws*, the independent unit, with the resamples of :func:`classifier.report.bootstrap_se`; every
point uses the same resamples, so the difference of two points has a paired standard error.

Pareto front (per axis, time key and pool): the points no other point beats in both time and error
(:func:`torchdoct.bench.tradeoffs.pareto_front`), among the settings that decide at least
``TradeoffPlan.min_coverage`` (0.1) of the identifiable samples (a balanced accuracy over a handful
of decisions says nothing). The defaults are *on the front* when no point is both faster and more
accurate, and *significantly dominated* when such a point is better by more than two paired standard
errors. Recommendation (one-standard-error rule): the cheapest setting whose error exceeds the lowest
error by at most one paired standard error and whose coverage is at most one paired standard error
below that setting's.

Modules, in import order: :mod:`.plan` (what is measured), :mod:`.data` (datasets of the axes),
:mod:`.evaluate` (fit, time and score one setting), :mod:`.pareto` (fronts and recommendations),
:mod:`.run` (the measurement); :mod:`.report` (tables and figure) reads only the result.
"""

from __future__ import annotations

from .data import derive_dataset, one_configuration_spec, prefix_dataset
from .evaluate import _bootstrap_weights, _Evaluator, _fit
from .pareto import _pareto
from .plan import DEFAULTS, ONE_CONFIGURATION, QUICK_PLAN, TradeoffPlan
from .report import format_table, plot_tradeoffs
from .run import classifier_tradeoffs, run_tradeoffs

__all__ = [
    "DEFAULTS",
    "TradeoffPlan",
    "QUICK_PLAN",
    "one_configuration_spec",
    "derive_dataset",
    "prefix_dataset",
    "classifier_tradeoffs",
    "run_tradeoffs",
    "format_table",
    "plot_tradeoffs",
]
