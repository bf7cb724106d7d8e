"""research.decayed_in_place: the candidate's criterion per pixel and its command line (the rendering is what the
grid benchmark's tests check)."""

import numpy as np
import pytest

from classifier.ambiguity import DECORRELATED_BELOW
from research import decayed_in_place as D

LAGS = (2, 4, 8, 16)


def _channels(field_last, peaks, centres):
    """One pixel per column: the field's centred correlation at the longest lag, the dynamic field's peak and
    centred correlation per lag (rows)."""
    ch = {f"xc_centre_{LAGS[-1]}@original": np.asarray(field_last, float)}
    for j, m in enumerate(LAGS):
        ch[f"xcd_peak_{m}@original"] = np.asarray([p[j] for p in peaks], float)
        ch[f"xcd_centre_{m}@original"] = np.asarray([c[j] for c in centres], float)
    return ch


def test_a_pattern_that_decays_in_place_after_it_held_is_the_candidate_s_and_a_moving_one_is_not():
    in_place = ([0.9, 0.7, 0.4, 0.3], [0.9, 0.7, 0.4, 0.3])  # peak = centre: nothing moved
    moving = ([0.9, 0.85, 0.8, 0.7], [0.9, 0.6, 0.3, 0.1])  # the peak keeps its height off the centre
    too_fast = ([0.4, 0.3, 0.3, 0.3], [0.4, 0.3, 0.3, 0.3])  # decayed before the first lag: no lag held it
    never = ([0.9, 0.9, 0.8, 0.8], [0.9, 0.9, 0.8, 0.8])  # never decayed to 1/2
    rows = [in_place, moving, too_fast, never, in_place]
    field = [0.3, 0.3, 0.3, 0.3, DECORRELATED_BELOW]  # the last: the field itself did not decorrelate
    got = D.decayed_in_place(_channels(field, [r[0] for r in rows], [r[1] for r in rows]), LAGS)
    assert got.tolist() == [True, False, False, False, False]


def test_a_small_move_at_either_lag_and_nan_are_not_in_place():
    a = D.MOVED_MAX
    peaks = [[0.9, 0.7, 0.4, 0.3], [0.9, 0.7, 0.4, 0.3], [0.9, np.nan, 0.4, 0.3]]
    centres = [
        [0.9, 0.7 * (1 - a - 0.01), 0.4, 0.3],  # moved at the lag before
        [0.9, 0.7, 0.4 * (1 - a - 0.01), 0.3],  # moved at the decayed lag
        [0.9, np.nan, 0.4, 0.3],
    ]
    assert D.decayed_in_place(_channels([0.3] * 3, peaks, centres), LAGS).tolist() == [False, False, False]


@pytest.mark.parametrize("parts", ["volume-none", "volume-edge,volume-edge", ""])
def test_unknown_or_repeated_parts_are_refused(tmp_path, parts):
    with pytest.raises(SystemExit):
        D.main(["--out", str(tmp_path), "--parts", parts])
    assert not (tmp_path / "decayed-in-place.json").exists()
