"""Your own system, end to end as a user runs it (slow): a rendered phantom of another OCT system →
``torchdoct maps`` → ``doct-train --like --quick`` → ``doct-classify --model DIR --pool 5``, scored against the
rendered ground truth (``research.systems``).

The three systems of issue "your own system": ``system-1310nm`` (1310 nm, lateral 10 µm, axial 8 µm),
``system-fast`` (64 frames 12.8 ms apart), ``system-tissue-volume`` (a volume in tissue, n = 1.38). The
``--quick`` models are rough; the full ``--like`` models are in ``research/results/systems-validation.md``.
Floors: ``mean − z·SD`` of the quick model's pool-5 balanced accuracy and coverage over the recorded renderings
(and the ceiling ``mean + z·SD`` of the worst wrong share over the grid's probes with the rules, pools 1 and 5)
of ``tests/floors/systems-quick.json`` (z and the command that records them are in the file;
``tests/reference/floors.py``). The test runs the shipped seed; the spread over renderings is the standard
error of that one run. The volume system, the longest of the three (a few minutes), carries the ``extended``
marker: ``.ci/run`` runs the two B-scan systems, ``python -m pytest -m extended`` the volume too.
"""

from __future__ import annotations

import pytest

pytestmark = pytest.mark.slow

from tests.reference.floors import SYSTEMS, floor, load, probes_wrong_share_max  # noqa: E402

RECORDED = load("systems-quick")


@pytest.mark.parametrize(
    "system",
    [pytest.param(s, marks=pytest.mark.extended) if s == "system-tissue-volume" else s for s in SYSTEMS],
)
def test_like_quick_model_classifies_its_system(system, tmp_path):
    from research.systems import evaluate

    r = evaluate(tmp_path, system, [2026], quick=True)
    s = r["scores"]["5"][0]["overall"]
    runs = RECORDED["runs"][system]["5"]
    acc, cov = (floor(runs[k], RECORDED["z"]) for k in ("balanced_accuracy", "coverage"))
    assert s["balanced_accuracy"] >= acc and s["coverage"] >= cov, (system, s, acc, cov)
    # off its own phantom: the grid's probes of its geometry (regions that touch, every motion at the model's
    # prior's mid or slow level) with doct-classify's rules; the worst wrong share stays under its ceiling
    for pool in ("1", "5"):
        worst = probes_wrong_share_max(r["probes"], pool)
        ceiling = floor(RECORDED["runs"][system][pool]["probes_wrong_share_max"], RECORDED["z"], error=True)
        assert worst <= ceiling, (system, pool, worst, ceiling)
    assert r["spec"]["protocol"]["n_frames"] == (64 if system == "system-fast" else 32)
    assert r["training_s"] is not None
