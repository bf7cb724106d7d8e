"""End to end: phantom → ``torchdoct render`` → ``torchdoct maps`` → ``doct-classify`` (shipped model) → accuracy.

The four-slab phantom and its chain are in ``tests/classifier/_slabs.py``: diffusion, random-ballistic motion
and flow slabs over a static one, B-scan and volume, ``--pool 5`` with the model's own argmax decisions
(``--decision rule --decide-ballistic``; the default's conformal and ballistic-or-flow sets are tested in
``test_conformal`` and ``test_clf_ambiguity``).

Floors: ``mean − z·SD`` of the balanced accuracy, the mean coverage of the motion slabs and the static
slab's indeterminate share over the recorded renderings of ``tests/floors/slabs.json`` (z and the command
that records them, ``python -m tests.reference.floors slabs``, are in the file). The test runs the
phantom's own seed once; the spread over renderings is the standard error of that one run. Every motion
type must also be recalled better than chance.
"""

from __future__ import annotations

import pytest

pytest.importorskip("torchdoct")
from tests.classifier._slabs import FLOORED, GEOMETRIES, run_chain, score
from tests.reference.floors import floor, load

RECORDED = load("slabs")


def _check(geometry: str, s: dict) -> None:
    runs, z = RECORDED["runs"][geometry], RECORDED["z"]
    for key in FLOORED:
        assert s[key] >= floor(runs[key], z), (key, s[key], floor(runs[key], z), s)
    assert min(s["recall"]) > 1 / 3, s  # every motion type better than chance


def test_bscan_phantom_end_to_end(tmp_path):
    grid, z_axis = GEOMETRIES["bscan"]
    truth, decided, summary = run_chain(tmp_path, grid)
    # B-scan maps (lateral reduction along x only) take the LIV/OCDS model trained on that PSF: no note
    assert summary["model_spec"] == "single-acquisition-bscan" and summary["info"]["notes"] == []
    _check("bscan", score(truth, decided, z_axis))


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under five minutes
def test_volume_phantom_end_to_end(tmp_path):
    grid, z_axis = GEOMETRIES["volume"]
    truth, decided, summary = run_chain(tmp_path, grid)
    assert summary["info"]["notes"] == []  # volumes are reduced isotropically
    _check("volume", score(truth, decided, z_axis))
