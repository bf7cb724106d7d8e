"""The classifier's part of ``torchdoct bench tradeoffs`` (entry point ``torchdoct.tradeoffs``/``classifier``,
:mod:`torchdoct.cli.extensions`): accuracy against time of the classifier's settings."""

from __future__ import annotations

from typing import Any

from .report import format_table, plot_tradeoffs
from .run import classifier_tradeoffs

__all__ = ["compute", "format_table", "plot"]


def compute(*, quick: bool = False, progress: bool = False) -> dict[str, Any]:
    """:func:`classifier.bench.tradeoffs.run.classifier_tradeoffs` (the quick plan when ``quick``)."""
    return classifier_tradeoffs(quick=quick, progress=progress)


def plot(result: dict[str, Any], path) -> None:
    """:func:`classifier.bench.tradeoffs.report.plot_tradeoffs`."""
    plot_tradeoffs(result, path)
