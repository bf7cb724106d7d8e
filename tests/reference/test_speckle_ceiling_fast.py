"""The pieces of tests/reference/speckle_ceiling.py on a few patches (the full run is a research command)."""

from __future__ import annotations

import numpy as np
import speckle_ceiling as sc

from torchdoct.sim.speckle import default_speckle_features


def test_draws_cycle_through_the_classes_with_their_own_parameters():
    motions = [sc.draw_params(k, 0)["motion"] for k in range(6)]
    assert motions == ["diffusion", "ballistic", "flow"] * 2
    assert sc.draw_params(2, 0) != sc.draw_params(5, 0)
    assert sc.draw_params(2, 0) == sc.draw_params(2, 0)
    lo, hi = sc.FLOW_UM_S
    assert lo <= sc.draw_params(2, 0)["speed_um_s"] <= hi


def test_every_feature_set_of_a_patch_is_finite_and_complete():
    row = sc.features(1, 0, window=9, snr_db=None)
    assert row["speckle"].shape == (len(default_speckle_features(2)),)
    assert row["pixel"].shape == row["pooled"].shape
    for key in ("pixel", "pooled", "speckle"):
        assert np.isfinite(row[key]).all(), key
    assert row["patch_seconds"] > 0
