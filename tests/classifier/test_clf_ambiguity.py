"""Where the speckle pattern moved coherently a decision for a direction-symmetric motion is flow; where the physics cannot exclude
flow it is ``ballistic-or-flow`` (classifier.ambiguity): every ballistic decision of a B-scan, a volume's ballistic decisions whose window
has not decorrelated or decorrelated before the shortest lag; a ballistic or diffusion decision is a set with flow where the pattern's
offset moved; what the rules read; on exactly translated speckle beating against static speckle, the offset rule sees the flow that the
moved-peak rule misses and fires more rarely under a direction-symmetric motion; and, on a rendered static-free B-scan of flow crossing the
plane, no flow pixel decided as another class; a single-class decision few of its neighbours share is
indeterminate (rule 6), last, in doct-classify's default only."""

from __future__ import annotations

import numpy as np
import pytest

from classifier.ambiguity import (
    COHERENT_MOVED_MIN,
    COHERENT_PEAK_MIN,
    CONSENSUS_MIN,
    CONSENSUS_WINDOW_MIN,
    DECORRELATED_BELOW,
    FAST_REMAINING_MAX,
    OFFSET_FIRST_MIN,
    OFFSET_GROWTH_MIN,
    OFFSET_HOLD_MIN,
    TRANSLATED_TO_FLOW,
    TRANSLATION_GROWTH_MIN,
    TRANSLATION_HOLD_MIN,
    TRANSLATION_LINEAR_MAX,
    TRANSLATION_WINDOW_MIN,
    OffsetMotion,
    abstain_where_ambiguous,
    coherent_motion,
    fast_decorrelation,
    offset_moved,
    slow_decorrelation,
    translated,
    unshared,
)

NAMES = [
    "diffusion",
    "ballistic",
    "flow",
    "indeterminate",
    "diffusion-or-ballistic",
    "diffusion-or-flow",
    "ballistic-or-flow",
]


def test_every_ballistic_decision_of_a_bscan_becomes_ballistic_or_flow():
    labels = np.array([0, 1, 2, 3, 1, 4, 6, 1])
    out, counts = abstain_where_ambiguous(labels, NAMES, unseen_axis=True, correlation=np.zeros(8))
    assert out.tolist() == [0, 6, 2, 3, 6, 4, 6, 6] and counts == {
        "coherent_motion": 0,
        "translation": 0,
        "doppler_drift": 0,
        "bscan_plane": 3,
        "sheared_flow": 0,
        "slow_decorrelation": 0,
        "fast_decorrelation": 0,
        "offset_moved": 0,
    }
    assert labels.tolist() == [0, 1, 2, 3, 1, 4, 6, 1]  # the input is not modified


def test_a_volume_keeps_ballistic_only_where_the_window_decorrelated():
    labels = np.array([1, 1, 1, 1, 0, 2])
    corr = np.array([DECORRELATED_BELOW - 1e-6, DECORRELATED_BELOW, 0.9, np.nan, 0.9, 0.9])
    out, counts = abstain_where_ambiguous(labels, NAMES, unseen_axis=False, correlation=corr)
    assert out.tolist() == [1, 6, 6, 6, 0, 2] and counts == {
        "coherent_motion": 0,
        "translation": 0,
        "doppler_drift": 0,
        "bscan_plane": 0,
        "sheared_flow": 0,
        "slow_decorrelation": 3,
        "fast_decorrelation": 0,
        "offset_moved": 0,
    }
    same, none = abstain_where_ambiguous(labels, NAMES, unseen_axis=False, correlation=None)
    assert same.tolist() == labels.tolist() and none == {
        "coherent_motion": 0,
        "translation": 0,
        "doppler_drift": 0,
        "bscan_plane": 0,
        "sheared_flow": 0,
        "slow_decorrelation": 0,
        "fast_decorrelation": 0,
        "offset_moved": 0,
    }


def test_coherent_motion_needs_a_kept_peak_mostly_moved_off_centre_at_a_lag_up_to_a_quarter_acquisition():
    p, c = COHERENT_PEAK_MIN, COHERENT_MOVED_MIN
    # per pixel: a moved kept peak; a centred peak; a moved peak below the floor; half moved exactly; NaN
    peak = np.array([0.9, 0.9, p - 1e-6, 0.8, np.nan])
    centre = np.array([0.1, 0.9, 0.0, 0.8 * (1 - c), 0.1])
    ch = {
        "xc_peak_4@original": peak,
        "xc_centre_4@original": centre,
        # lag 16 > 32 // 4: a moved peak there does not count (few frame pairs, lone scatterers)
        "xc_peak_16@original": np.full(5, 0.9),
        "xc_centre_16@original": np.zeros(5),
    }
    seen, used = coherent_motion(ch, n_frames=32)
    assert seen.tolist() == [True, False, False, True, False]
    assert used == ["xc_peak_4@original", "xc_centre_4@original"]
    assert coherent_motion(ch, idx=np.array([1, 0]), n_frames=32)[0].tolist() == [False, True]
    assert coherent_motion({"xc_centre_4@original": centre}) == (None, [])


def test_coherent_motion_turns_every_symmetric_motion_decision_into_flow_before_the_other_rules():
    labels = np.array([1, 6, 0, 4, 5, 3, 2, 1, 1])
    coherent = np.array([True, True, True, True, True, True, True, False, False])
    out, counts = abstain_where_ambiguous(labels, NAMES, unseen_axis=True, correlation=None, coherent=coherent)
    # ballistic, the sets and diffusion become flow; indeterminate and flow stay; the rest of the B-scan's
    # ballistic is a set
    assert out.tolist() == [2, 2, 2, 2, 2, 3, 2, 6, 6]
    assert counts == {
        "coherent_motion": 5,
        "translation": 0,
        "doppler_drift": 0,
        "bscan_plane": 2,
        "sheared_flow": 0,
        "slow_decorrelation": 0,
        "fast_decorrelation": 0,
        "offset_moved": 0,
    }


def test_fast_decorrelation_is_a_decay_over_before_the_shortest_lag():
    f = FAST_REMAINING_MAX
    # per pixel (rho at lags 2 and 16): flat at a static plateau; decaying after lag 2 (fast ballistic);
    # just over a fifth of the decay left; undecayed (rule 2's case, 0 < f of 0); NaN
    first = np.array([0.32, 0.76, 0.3 + f * 0.7 + 1e-9, 1.0, np.nan])
    last = np.array([0.30, 0.31, 0.3, 1.0, 0.3])
    ch = {
        "xc_centre_16@original": last,
        "xc_centre_2@original": first,
        "xc_centre_4@coarse": np.zeros(5),
    }  # another resolution with one lag is not mixed in
    fast, used = fast_decorrelation(ch)
    assert fast.tolist() == [True, False, False, False, False]
    assert used == ["xc_centre_2@original", "xc_centre_16@original"]
    assert fast_decorrelation(ch, idx=np.array([1, 0]))[0].tolist() == [False, True]
    assert fast_decorrelation({"xc_centre_2@original": first}) == (None, [])


def test_fast_decorrelation_makes_a_volume_ballistic_decision_a_set_after_the_slow_rule():
    labels = np.array([1, 1, 1, 2, 0])
    corr = np.array([0.9, 0.1, 0.1, 0.1, 0.1])
    fast = np.array([True, True, False, True, True])
    out, counts = abstain_where_ambiguous(labels, NAMES, unseen_axis=False, correlation=corr, fast=fast)
    assert out.tolist() == [6, 6, 1, 2, 0]  # flow and diffusion decisions stay
    assert counts == {
        "coherent_motion": 0,
        "translation": 0,
        "doppler_drift": 0,
        "bscan_plane": 0,
        "sheared_flow": 0,
        "slow_decorrelation": 1,
        "fast_decorrelation": 1,
        "offset_moved": 0,
    }


def test_labels_without_the_set_name_are_left_alone():
    labels = np.array([1, 1])
    out, counts = abstain_where_ambiguous(
        labels, ["diffusion", "ballistic", "flow", "indeterminate"], unseen_axis=True, correlation=None
    )
    assert out.tolist() == [1, 1] and sum(counts.values()) == 0


def test_the_slow_rule_reads_the_longest_speckle_lag_else_the_pooled_half_acquisition_correlation():
    ch = {"xc_centre_4@original": np.full((2, 3), 0.1), "xc_centre_16@original": np.arange(6.0).reshape(2, 3)}
    vals, src = slow_decorrelation(ch, idx=np.array([5, 0]))
    assert src == "xc_centre_16@original" and vals.tolist() == [5.0, 0.0]
    cols = [
        {"name": "rho_lin_8@a", "metric": "rho_lin_8", "configuration": "a"},
        {"name": "rho_lin_16@b", "metric": "rho_lin_16", "configuration": "b"},
        {"name": "rho_lin_11@a", "metric": "rho_lin_11", "configuration": "a"},
        {"name": "rho_lin_22@a", "metric": "rho_lin_22", "configuration": "a"},
        {"name": "pool_pixels"},
    ]
    pooled = np.array([[0.1, 0.2, 0.3, 0.4, 1.0]])
    vals, src = slow_decorrelation({}, cols, pooled, n_frames=32)  # |11 - 16| < |22 - 16|; b is not first
    assert src == "rho_lin_11@a" and vals.tolist() == [0.3]
    assert slow_decorrelation({}, cols[-1:], pooled[:, -1:]) == (None, None)


def _offsets(shift_um, peak_first, pitch=1.5):
    """Channels of one resolution at lags 2, 4, 8 (and 16, past a quarter of 32 frames: never read)."""
    shift = np.asarray(shift_um, np.float64)
    ch = {f"xc_shift_{m}@original": shift[:, i] for i, m in enumerate((2, 4, 8, 16))}
    ch.update({f"xc_peak_{m}@original": np.full(len(shift), peak_first if m == 2 else 0.3) for m in (2, 4, 8, 16)})
    return offset_moved(ch, pitch, n_frames=32)


def test_offset_rule_fires_on_an_offset_off_centre_or_growing_while_the_pattern_holds():
    p = 1.5
    first = OFFSET_FIRST_MIN * p
    grow = OFFSET_GROWTH_MIN * p
    rows = [
        [first, first, first, 0.0],  # a grid step off at the shortest lag
        [0.9 * first, 0.9 * first, 0.9 * first, 9.0],  # off by less, not growing; lag 16 is not read
        [0.1, 0.1 + grow / 2, 0.1 + 1.01 * grow, 0.0],  # grew at every lag, by the minimum in all
        [0.1, 0.1 + grow, 0.1 + grow, 0.0],  # grew, but not at every lag
        [0.1, 0.1 + grow / 2, 0.1 + 0.99 * grow, 0.0],  # grew at every lag, by less than the minimum
        [np.nan, 1.0, 2.0, 3.0],
    ]  # NaN: not seen
    moved, used = _offsets(rows, OFFSET_HOLD_MIN, p)
    assert moved.off_centre.tolist() == [True, False, False, False, False, False]
    assert moved.grew.tolist() == [False, False, True, False, False, False]
    assert used == ["xc_shift_2@original", "xc_shift_4@original", "xc_shift_8@original", "xc_peak_2@original"]
    held_not, _ = _offsets(rows, 0.99 * OFFSET_HOLD_MIN, p)  # the pattern did not hold: growth is not read
    assert held_not.off_centre.tolist() == moved.off_centre.tolist() and not held_not.grew.any()
    assert offset_moved({"xc_shift_2@original": np.zeros(2)}, p) == (None, [])
    assert _offsets(rows, 1.0, pitch=0.0) == (None, [])


def test_offset_rule_turns_remaining_decisions_into_sets_with_flow_and_only_abstains():
    """Off the centre: ballistic and diffusion; grown: ballistic only (a decaying diffusing pattern lets its
    offset wander); flow, indeterminate and sets are never touched."""
    labels = np.array([0, 1, 2, 3, 4, 0, 1, 0, 1])
    off = np.array([True, True, True, True, True, False, False, False, False])
    grew = np.array([False, False, True, True, True, False, False, True, True])
    moved = OffsetMotion(off, grew)
    out, counts = abstain_where_ambiguous(labels, NAMES, unseen_axis=False, correlation=np.zeros(9), moved=moved)
    assert out.tolist() == [5, 6, 2, 3, 4, 0, 1, 0, 6]
    assert counts["offset_moved"] == 3
    # a B-scan's ballistic decisions are sets already (rule 1); its diffusion decisions still meet rule 4
    out, counts = abstain_where_ambiguous(labels, NAMES, unseen_axis=True, correlation=None, moved=moved)
    assert out.tolist() == [5, 6, 2, 3, 4, 0, 6, 0, 6] and counts["bscan_plane"] == 3
    assert counts["offset_moved"] == 1


def test_every_rule_applies_in_one_call_each_to_the_pixels_the_earlier_rules_left():
    labels = np.array([1, 1, 0, 1, 1, 0])
    coherent = np.array([True, False, False, False, False, False])
    corr = np.array([0.0, 0.9, 0.0, 0.0, 0.0, 0.0])
    fast = np.array([False, False, False, True, False, False])
    moved = OffsetMotion(np.array([True, True, True, True, True, False]), np.zeros(6, bool))
    out, counts = abstain_where_ambiguous(
        labels, NAMES, unseen_axis=False, correlation=corr, coherent=coherent, fast=fast, moved=moved
    )
    assert out.tolist() == [2, 6, 5, 6, 6, 0]
    assert counts == {
        "coherent_motion": 1,
        "translation": 0,
        "doppler_drift": 0,
        "bscan_plane": 0,
        "sheared_flow": 0,
        "slow_decorrelation": 1,
        "fast_decorrelation": 1,
        "offset_moved": 2,
    }


def _path(shift_z, shift_x, peaks, lags=(2, 4, 8, 16)):
    """Channels of one resolution: a signed offset path (µm, one row per pixel) and the peak at every lag (one
    value per pixel for all lags, or one list per pixel)."""
    rows = [list(v) if isinstance(v, (list, tuple)) else [v] * len(lags) for v in peaks]
    ch = {}
    for j, m in enumerate(lags):
        ch[f"xc_peak_{m}@original"] = np.asarray([r[j] for r in rows], float)
        ch[f"xc_shift_z_{m}@original"] = np.asarray([p[j] for p in shift_z], float)
        ch[f"xc_shift_x_{m}@original"] = np.asarray([p[j] for p in shift_x], float)
    return ch


def test_translation_rule_fires_on_a_held_pattern_moving_along_a_line_only():
    """Rule 5 on offset paths (pitch 2 µm): a held pattern (peak 0.9) whose offset moves 0.45 pitch along a
    line in the lag fires; the same path with a pattern that did not hold (peak 0.7), a move short of
    TRANSLATION_GROWTH_MIN, a path that jumps to another grain and stays (off a line), or a still offset at
    the window's own grain position (0.6 pitch from the centre) does not. NaN counts as not moved. A pattern
    that held through the first three lags only (a fast flow leaving the offset grid) is judged on them."""
    p = 2.0
    lags = (2, 4, 8, 16)
    line = [0.3 + 0.45 * p * (m - 2) / 14 for m in lags]  # µm: from an offset of the window's grains
    short = [0.3 + (TRANSLATION_GROWTH_MIN - 0.05) * p * (m - 2) / 14 for m in lags]
    jump = [0.3, 0.3 + 0.5 * p, 0.3 + 0.5 * p, 0.3 + 0.5 * p]  # to a neighbouring grain, then still
    still = [1.2] * 4
    zero = [0.0] * 4
    fast = [0.3 + 0.45 * p * (m - 2) / 6 for m in lags[:3]] + [4.0]  # 0.45 pitch over lags 2-8, then off the grid
    ch = _path(
        [line, line, short, jump, still, [np.nan] * 4, fast, fast, line],
        [zero] * 9,
        [0.9, 0.7, 0.9, 0.9, 0.9, 0.9, [0.95, 0.95, 0.9, 0.4], [0.95, 0.9, 0.4, 0.4], [0.9, 0.9, 0.9, np.nan]],
        lags,
    )
    seen, used = translated(ch, {"z": p, "x": p})
    # the last: NaN at lag 16 counts as not held, and over lags 2-8 the line moved too little
    assert seen.tolist() == [True, False, False, False, False, False, True, False, False]
    assert "xc_peak_16@original" in used and "xc_shift_z_2@original" in used
    assert TRANSLATION_HOLD_MIN > 0.7 and TRANSLATION_LINEAR_MAX > 0
    # the move counts in pitches of each axis: the same path in µm over a coarser x pitch is short of it
    across = _path([zero], [line], [0.9], lags)
    assert translated(across, {"z": p, "x": p})[0].tolist() == [True]
    assert translated(across, {"z": p, "x": 2.5 * p})[0].tolist() == [False]
    # without the signed offsets and peaks at three lags, or the pitches, the rule is not applied
    assert translated({k: v for k, v in ch.items() if "_x_" not in k}, {"z": p, "x": p})[0] is not None
    assert translated(_path([line[:2]], [line[:2]], [0.9], lags[:2]), {"z": p, "x": p}) == (None, [])
    assert translated({k: v for k, v in ch.items() if "peak" not in k}, {"z": p, "x": p}) == (None, [])
    assert translated(ch, None) == (None, [])
    # narrower speckle windows than the one its rates were recorded at: not applied
    assert translated(ch, {"z": p, "x": p}, window_px=TRANSLATION_WINDOW_MIN - 2) == (None, [])
    assert translated(ch, {"z": p, "x": p}, window_px=TRANSLATION_WINDOW_MIN)[0].tolist()[0]


def test_translation_rule_on_maps_needs_the_windows_around_a_pixel_to_have_moved_too():
    """On a map, one window whose held pattern moved along a line (a few scatterers moving alone) is not a
    flow: at least TRANSLATION_SUPPORT_MIN of the valid windows of its speckle window must have moved too.
    A region of moved windows (a flow) keeps every pixel whose neighbourhood is mostly inside it; NaN pixels
    (outside the sample) do not vote; 1-D channels are judged window by window; ``idx`` reads the mask at
    the classified pixels of the map."""
    p, lags = 2.0, (2, 4, 8, 16)
    line = [0.3 + 0.45 * p * (m - 2) / 14 for m in lags]
    zero = [0.0] * 4

    def field(moving: np.ndarray) -> dict:
        flat = moving.reshape(-1)
        ch = _path([line if f else zero for f in flat], [zero] * flat.size, [0.9] * flat.size, lags)
        return {k: v.reshape(moving.shape) for k, v in ch.items()}

    one = np.zeros((15, 15), bool)
    one[7, 7] = True
    assert translated(field(one), {"z": p, "x": p}, window_px=9)[0].sum() == 0
    assert translated({k: v.reshape(-1) for k, v in field(one).items()}, {"z": p, "x": p})[0].sum() == 1
    band = np.zeros((15, 31), bool)
    band[:, 10:21] = True  # an 11-pixel-wide flow band
    seen = translated(field(band), {"z": p, "x": p}, window_px=9)[0].reshape(band.shape)
    assert not seen[~band].any()
    assert seen[:, 11:20].all()  # the neighbourhood of each of these is at least 5/9 inside the band
    # with the band's surroundings outside the sample (NaN), the band's edge columns keep their support
    ch = field(band)
    for k in ch:
        ch[k] = np.where(band, ch[k], np.nan)
    assert translated(ch, {"z": p, "x": p}, window_px=9)[0].reshape(band.shape)[:, 10:21].all()
    idx = np.array([0, 7 * 31 + 15])
    assert translated(field(band), {"z": p, "x": p}, idx, window_px=9)[0].tolist() == [False, True]


def test_translation_rule_gives_the_same_mask_whatever_the_slab_size(monkeypatch):
    """The per-window criterion runs over the map a slab of pixels at a time (bounded memory): slabs of
    7 pixels give the mask of one slab."""
    import classifier.ambiguity as amb

    rng = np.random.default_rng(5)
    p, lags = 1.5, (2, 4, 8, 16)
    ch = {}
    for m in lags:
        ch[f"xc_peak_{m}@original"] = rng.uniform(0.75, 1.0, (12, 17))
        for c in "zx":  # the left columns drift along z (a flow), the right ones jitter
            sd = np.where(np.arange(17) < 9, 0.01, 0.3)
            ch[f"xc_shift_{c}_{m}@original"] = rng.normal(0.0, 1.0, (12, 17)) * sd + 0.06 * m * (c == "z")
    ch["xc_peak_2@original"][3, 4] = np.nan
    whole = translated(ch, {"z": p, "x": p}, window_px=9)[0]
    monkeypatch.setattr(amb, "_CHUNK", 7)
    assert whole.any() and not whole.all()
    assert np.array_equal(translated(ch, {"z": p, "x": p}, window_px=9)[0], whole)


def test_window_share_counts_the_valid_pixels_of_the_box_cut_at_the_edges():
    from classifier.ambiguity import _window_share

    rng = np.random.default_rng(3)
    for shape in ((7, 9), (4, 5, 6)):
        hit = rng.random(shape) < 0.4
        valid = rng.random(shape) < 0.8
        got = _window_share(hit, valid, 3)
        for ix in np.ndindex(*shape):
            box = tuple(slice(max(i - 1, 0), i + 2) for i in ix)
            v = valid[box].sum()
            want = (hit[box] & valid[box]).sum() / v if v else np.nan
            assert np.isclose(got[ix], want, equal_nan=True)


def test_a_single_class_decision_few_of_its_neighbours_share_is_flagged_and_no_set_is():
    """Rule 6: a decision stands where at least CONSENSUS_MIN of the classified pixels of its window hold it:
    a patch of flow keeps its inside and loses the corners it shares with fewer; one flow pixel among
    sets is flagged; a set or indeterminate pixel never; unclassified pixels do not count."""
    assert CONSENSUS_MIN == 0.5 and CONSENSUS_WINDOW_MIN == 3
    flow, ball_set, indet = NAMES.index("flow"), NAMES.index("ballistic-or-flow"), NAMES.index("indeterminate")
    grid = np.full((12, 12), ball_set)
    grid[2:7, 2:7] = flow  # a 5x5 patch
    grid[10, 10] = flow  # a stray decision
    grid[0, 11] = indet
    shape = grid.shape
    valid = np.ones(shape, bool)
    valid[9:12, 0:3] = False  # not classified (background)
    idx = np.flatnonzero(valid)
    got = np.zeros(shape, bool).reshape(-1)
    got[idx] = unshared(grid.reshape(-1)[idx], NAMES, idx, shape, 1)
    got = got.reshape(shape)
    expect = np.zeros(shape, bool)
    expect[10, 10] = True
    for i, j in ((2, 2), (2, 6), (6, 2), (6, 6)):  # corners: 4 of the 9 in their 3x3 box
        expect[i, j] = True
    np.testing.assert_array_equal(got, expect)
    # the pooling window widens the box: at 5x5 the patch's corners keep 9/25 < 1/2, its edges 15/25 ≥ 1/2
    got5 = np.zeros(shape, bool).reshape(-1)
    got5[idx] = unshared(grid.reshape(-1)[idx], NAMES, idx, shape, 5)
    got5 = got5.reshape(shape)
    assert got5[2, 2] and got5[10, 10] and not got5[4, 2] and not got5[4, 4]
    # the box counts only classified pixels: a flow pixel beside the background holds half of the classified pixels of its cut box
    edge = grid.copy()
    edge[8, 0:2] = flow
    got_e = np.zeros(shape, bool).reshape(-1)
    got_e[idx] = unshared(edge.reshape(-1)[idx], NAMES, idx, shape, 1)
    assert not got_e.reshape(shape)[8, 0]  # box rows 7..8 (row 9 unclassified), cols 0..1: 2 of 4 are flow


def test_rule_6_box_is_the_coarsest_psf_footprint_widened_by_the_pooling_window_per_axis():
    """The box spans, per axis, the full width where the coarsest configuration's intensity PSF stays above
    1/e² (the lateral resolution along x and y, √2/√ln2 ≈ 1.70 times the axial FWHM along z) over the
    pitch, rounded up, plus pool − 1 (a pooled pixel averages the footprints of pool pixels), rounded up to
    odd; never narrower than the pooling window or CONSENSUS_WINDOW_MIN; an axis without a pitch keeps the
    pooling window."""
    from classifier.ambiguity import consensus_window

    # x: 18 / 1.5 = 12 → 13; z: 14 · 1.6986 / 1.5 = 15.85 → 16 → 17; y: 18 / 3 = 6 → 7
    assert consensus_window("YZX", {"z": 1.5, "x": 1.5, "y": 3.0}, 1, 18.0, 14.0) == (7, 17, 13)
    # pool 5: z 16 + 4 = 20 → 21, x 12 + 4 = 16 → 17; pool 21: z 36 → 37, x 32 → 33
    assert consensus_window("ZX", {"z": 1.5, "x": 1.5}, 5, 18.0, 14.0) == (21, 17)
    assert consensus_window("ZX", {"z": 1.5, "x": 1.5}, 21, 18.0, 14.0) == (37, 33)
    assert consensus_window("ZX", {"z": 4.0, "x": 10.0}, 1, 18.0, 4.0) == (3, 3)  # footprint under the minimum
    assert consensus_window("ZX", {"x": 1.5}, 5, 18.0, 14.0) == (5, 17)  # no z pitch
    assert consensus_window("ZX", None, 5, 18.0, 14.0) == (5, 5)
    assert consensus_window("YZX", {"z": 1.0, "x": 1.0, "y": 1.0}, 1, 4.0, 2.0, lateral_y_um=10.0) == (11, 5, 5)


def test_rule_7_box_reaches_one_and_a_half_footprints_where_the_coarse_psf_holds_one_percent():
    """Rule 7's box scales the footprint term by FOOTPRINT_REACH = 1.5, where the coarse intensity PSF
    exp(−2d²/r²) has fallen to e^(−4.5) (against e^(−2) at the footprint's edge); the pooling term is
    unchanged; a reach that is not a positive finite number is refused."""
    from classifier import ambiguity
    from classifier.ambiguity import consensus_window

    assert ambiguity.FOOTPRINT_REACH == 1.5
    # x: 1.5 · 18 / 1.5 = 18 → 19; z: 1.5 · 14 · 1.6986 / 1.5 = 23.78 → 24 → 25; pool 5 adds 4 to each
    assert consensus_window("ZX", {"z": 1.5, "x": 1.5}, 1, 18.0, 14.0, reach=1.5) == (25, 19)
    assert consensus_window("ZX", {"z": 1.5, "x": 1.5}, 5, 18.0, 14.0, reach=1.5) == (29, 23)
    assert consensus_window("ZX", {"z": 1.5, "x": 1.5}, 5, 18.0, 14.0, reach=1.0) == (21, 17)
    for bad in (0.0, -1.0, float("nan"), float("inf"), True):
        with pytest.raises(ValueError, match="reach"):
            consensus_window("ZX", {"z": 1.5, "x": 1.5}, 1, 18.0, 14.0, reach=bad)


def test_rule_6_box_per_axis_flags_a_strip_narrower_than_half_of_it():
    """A 3-pixel strip of flow decisions along z among sets stands in a 3×3 box (its centre column holds 3
    of 3) but not in a box 13 pixels wide along x (3 of 13 < 1/2): the coarse PSF mixes it with its
    neighbours. A window with the wrong number of axes is refused."""
    flow, ball_set = NAMES.index("flow"), NAMES.index("ballistic-or-flow")
    grid = np.full((20, 30), ball_set)
    grid[:, 14:17] = flow
    shape, idx = grid.shape, np.arange(grid.size)
    narrow = unshared(grid.reshape(-1), NAMES, idx, shape, (3, 3)).reshape(shape)
    wide = unshared(grid.reshape(-1), NAMES, idx, shape, (3, 13)).reshape(shape)
    assert not narrow[:, 15].any() and wide[:, 14:17].all()
    assert not wide[:, :14].any() and not wide[:, 17:].any()  # sets are never flagged
    with pytest.raises(ValueError, match="2 axes"):
        unshared(grid.reshape(-1), NAMES, idx, shape, (3, 3, 3))


def test_rule_8_flags_a_decision_whose_fine_footprint_holds_one_in_ten_outcomes_that_exclude_it():
    """A diffusion decision in a 5×5 box is contradicted from 3 of 25 pixels (≥ CONTRADICTED_MIN = 1/10) that
    exclude diffusion: a set without it (ballistic-or-flow) or another motion; 2 of 25 are not enough; sets
    that name diffusion and indeterminate pixels never contradict it (indeterminate ones count as classified);
    sets are never flagged themselves."""
    from classifier.ambiguity import CONTRADICTED_MIN, contradicted

    assert CONTRADICTED_MIN == 0.1
    diff, ball_set, diff_set = (
        NAMES.index("diffusion"),
        NAMES.index("ballistic-or-flow"),
        NAMES.index("diffusion-or-flow"),
    )
    ind, flow = NAMES.index("indeterminate"), NAMES.index("flow")

    def at_centre(cells):
        grid = np.full((5, 5), diff)
        for (z, x), v in cells.items():
            grid[z, x] = v
        shape, idx = grid.shape, np.arange(grid.size)
        return contradicted(grid.reshape(-1), NAMES, idx, shape, (5, 5)).reshape(shape)[2, 2]

    assert at_centre({(0, 0): ball_set, (0, 1): ball_set, (0, 2): ball_set})
    assert at_centre({(0, 0): ball_set, (4, 4): flow, (0, 2): ball_set})
    assert not at_centre({(0, 0): ball_set, (0, 1): ball_set})
    assert not at_centre({(0, k): diff_set for k in range(5)} | {(4, k): ind for k in range(5)})
    grid = np.full((5, 5), ball_set)
    grid[2, 2] = diff
    got = contradicted(grid.reshape(-1), NAMES, np.arange(25), (5, 5), (5, 5)).reshape(5, 5)
    assert got[2, 2] and got.sum() == 1  # the sets around it are not flagged


def test_rule_7_flags_an_unfounded_flow_decision_only_where_its_footprint_holds_another_region():
    """A flow strip beside a region of sets, its pattern unmoved: the pixels whose box reaches the sets (flow
    share < FOOTPRINT_FLOW_MIN) are flagged, decorrelated or not, the ones whose box is all flow are kept; a
    pixel whose pattern moved (rule 0 or 5) is never flagged; indeterminate pixels (static tissue) are not
    counted; without a flow label the rule does nothing."""
    from classifier.ambiguity import FOOTPRINT_FLOW_MIN, borrowed_flow

    assert FOOTPRINT_FLOW_MIN == 0.9
    flow, ball_set = NAMES.index("flow"), NAMES.index("ballistic-or-flow")
    grid = np.full((9, 30), ball_set)
    grid[:, 10:30] = flow  # flow from column 10 on
    shape, idx = grid.shape, np.arange(grid.size)
    labels = grid.reshape(-1)
    got = borrowed_flow(labels, NAMES, idx, shape, (3, 5)).reshape(shape)
    # a 5-wide box holds 5 columns: flow share 3/5 at column 10, 4/5 at 11, 5/5 from 12 on
    assert got[:, 10:12].all() and not got[:, 12:].any() and not got[:, :10].any()
    moved = np.zeros(shape, bool)
    moved[4, 11] = True
    got2 = borrowed_flow(labels, NAMES, idx, shape, (3, 5), translation=moved.reshape(-1)).reshape(shape)
    assert not got2[4, 11] and got2[3, 11] and got2[:, 10].all()
    got3 = borrowed_flow(labels, NAMES, idx, shape, (3, 5), coherent=moved.reshape(-1)).reshape(shape)
    assert not got3[4, 11] and got3[3, 11]
    no_flow = np.where(labels == flow, NAMES.index("ballistic"), labels)
    assert not borrowed_flow(no_flow, NAMES, idx, shape, (3, 5)).any()
    # beside indeterminate pixels (static tissue) instead of sets: no other motion's evidence, nothing flagged
    static = np.where(labels == ball_set, NAMES.index("indeterminate"), labels)
    assert not borrowed_flow(static, NAMES, idx, shape, (3, 5)).any()
    mixed = static.reshape(shape).copy()
    mixed[:, 9] = ball_set  # one column of sets next to the flow: flow share 3/4 at column 10, 4/5 at 11
    got4 = borrowed_flow(mixed.reshape(-1), NAMES, idx, shape, (3, 5)).reshape(shape)
    assert got4[:, 10:12].all() and not got4[:, 12:].any()


def test_rule_9_flags_a_flow_decision_where_a_coarser_configuration_decayed_faster_than_the_finest():
    """The excess is, over the coarser configurations, the largest mean over the common lags of
    rho_lin_m@finest − rho_lin_m@coarser; an unmoved flow decision is flagged above MIXED_DECAY_MIN, a coarser
    configuration decaying slower (a flow beside a slower region) never flags, a moved pattern (rule 0 or 5)
    keeps its decision, other labels are never flagged, and without two configurations' rho_lin nothing is."""
    from classifier.ambiguity import MIXED_DECAY_MIN, mixed_footprint

    assert MIXED_DECAY_MIN == 0.3
    cols = [
        {"metric": "rho_lin_1", "configuration": "original"},
        {"metric": "rho_lin_4", "configuration": "original"},
        {"metric": "lin_contrast", "configuration": "original"},
        {"metric": "rho_lin_1", "configuration": "axial=14"},
        {"metric": "rho_lin_4", "configuration": "axial=14"},
        {"metric": "rho_lin_1", "configuration": "lateral=18"},
        {"metric": "rho_lin_8", "configuration": "lateral=18"},  # no common lag beyond 1
        {"metric": "pool_pixels"},
    ]
    #                 fine 1, fine 4, contrast, axial 1, axial 4, lateral 1, lateral 8, pool
    rows = np.array(
        [
            [0.99, 0.90, 1.0, 0.40, 0.20, 0.99, 0.1, 25],  # axial: (0.59 + 0.70) / 2 = 0.645 > 0.3
            [0.99, 0.90, 1.0, 0.80, 0.55, 0.99, 0.1, 25],  # axial: (0.19 + 0.35) / 2 = 0.27 ≤ 0.3
            [0.99, 0.90, 1.0, 0.99, 0.95, 0.60, 0.1, 25],  # lateral at its one common lag: 0.39 > 0.3
            [0.50, 0.20, 1.0, 0.90, 0.80, 0.95, 0.1, 25],  # coarser decays slower: excess < 0
            [0.99, 0.90, 1.0, 0.40, 0.20, 0.99, 0.1, 25],  # as row 0, pattern moved
            [0.99, 0.90, 1.0, 0.40, 0.20, 0.99, 0.1, 25],  # as row 0, a ballistic-or-flow set
        ]
    )
    flow = NAMES.index("flow")
    labels = np.array([flow] * 5 + [NAMES.index("ballistic-or-flow")])
    moved = np.zeros(6, bool)
    moved[4] = True
    got, excess = mixed_footprint(labels, NAMES, cols, rows, "original", translation=moved)
    np.testing.assert_allclose(excess, [0.645, 0.27, 0.39, -0.45, 0.645, 0.645], atol=1e-12)
    assert got.tolist() == [True, False, True, False, False, False]
    got0, _ = mixed_footprint(labels, NAMES, cols, rows, "original", coherent=moved)
    assert got0.tolist() == got.tolist()
    # one configuration only, or no rho_lin of the finest: nothing to compare
    alone, ex = mixed_footprint(labels, NAMES, cols[:3] + cols[-1:], rows[:, [0, 1, 2, 7]], "original")
    assert ex is None and not alone.any()
    none, ex = mixed_footprint(labels, NAMES, cols, rows, "elsewhere")
    assert ex is None and not none.any()


def test_translation_rule_turns_ballistic_decisions_and_sets_into_flow_but_not_diffusion():
    labels = np.array([1, 6, 0, 5, 4, 3, 1])
    seen = np.array([True, True, True, True, True, True, False])
    out, counts = abstain_where_ambiguous(labels, NAMES, unseen_axis=True, correlation=None, translation=seen)
    assert out.tolist() == [2, 2, 0, 5, 4, 3, 6]
    assert counts["translation"] == 2 and counts["bscan_plane"] == 1
    assert TRANSLATED_TO_FLOW == ("ballistic", "ballistic-or-flow")


def test_translation_rule_sees_slow_flow_and_rarely_random_ballistic_motion_in_simulated_patches():
    """Static-free B-scan patches of the patch simulator (1.5-µm pixels, density 0.02 µm⁻³): flow at
    0.335 µm/s at 10° polar (it moves the pattern about half a pitch over the lags; rule 0 sees nothing) and
    random-ballistic motion at 0.0123 µm/s (the grid's slow level: a pattern that holds). The rule fires on
    the flow more often than on the random motion by Z = 3.5 binomial standard errors."""
    from tests.reference.translation_rule import fires

    n = 48
    flow = dict(motion="flow", speed_um_s=0.335, polar_deg=10.0, azimuth_deg=0.0, snr_db=None)
    p_f = fires(flow, n, 11, 1.5)[0].mean()
    p_s = fires(dict(motion="ballistic", speed_um_s=0.0123, snr_db=None), n, 12, 1.5)[0].mean()
    se = np.sqrt(p_f * (1 - p_f) / n + p_s * (1 - p_s) / n)
    assert p_f - p_s > 3.5 * max(se, 1.0 / n), (p_f, p_s)


def _speckle_channels(field, n_frames=32):
    """Default speckle features of each field's centre pixel (1-µm pixels, window 9) as rule channels."""
    from torchdoct.sim.speckle import default_speckle_features, halo_pixels, speckle_motion

    names = default_speckle_features(2, n_frames=n_frames)
    h = halo_pixels() + 1
    c = field.shape[-1] // 2
    crop = field[..., c - h : c + h + 1, c - h : c + h + 1]
    _, f = speckle_motion(crop, {"z": 1.0, "x": 1.0}, 0.2048, names, ndim=2)
    vals = f[..., h, h].numpy()
    return {f"{n}@original": vals[:, i] for i, n in enumerate(names)}


def test_offset_rule_sees_sub_pixel_flow_beating_against_static_speckle_and_rarely_symmetric_motion():
    """Static speckle of the moving part's power shares the PSF (speckle-motion §3 (d)). A flow moves its
    pattern by 0.06 µm per frame in the plane (half a pixel over the 8-frame lag: rule 0 sees no moved peak)
    while its Doppler phase turns by 0.4 rad per frame (the centred correlation beats down). The control is
    random-ballistic motion before transit: the same static speckle plus a moving part of the same power whose
    scatterers keep their place and turn at Doppler rates of random directions (16 sub-patterns, rates
    uniform in ±0.8 rad per frame: the direction cosine is uniform). Rule 4 fires on the flow more often than
    on the control by Z = 3.5 binomial standard errors, and on the flow at least as often as rule 0."""
    import torch
    from _speckle_fields import translated_speckle

    from torchdoct.conventions import amplitude_sigma_axial_um, amplitude_sigma_lateral_um

    n, shape, frames = 64, (32, 32), torch.arange(32, dtype=torch.float64).reshape(1, 32, 1, 1)
    sig = (amplitude_sigma_axial_um(3.8), amplitude_sigma_lateral_um(4.9))
    step = (0.02, 0.06)
    static = translated_speckle(n, shape, sig, lambda i: (0.0, 0.0), seed=21, n_frames=1)
    fwd = translated_speckle(n, shape, sig, lambda i: (step[0] * i, step[1] * i), seed=22)
    flow = _speckle_channels(static + fwd * torch.exp(-0.4j * frames))
    rates = torch.linspace(-0.8, 0.8, 16, dtype=torch.float64)
    moving = (
        sum(
            translated_speckle(n, shape, sig, lambda i: (0.0, 0.0), seed=30 + k, n_frames=1)
            * torch.exp(-1j * float(r) * frames)
            for k, r in enumerate(rates)
        )
        / 4.0
    )
    sym = _speckle_channels(static + moving)
    moved_flow, _ = offset_moved(flow, 1.0, n_frames=32)
    moved_sym, _ = offset_moved(sym, 1.0, n_frames=32)
    p_f = (moved_flow.off_centre | moved_flow.grew).mean()
    p_s = (moved_sym.off_centre | moved_sym.grew).mean()
    se = np.sqrt(p_f * (1 - p_f) / n + p_s * (1 - p_s) / n)
    assert p_f - p_s > 3.5 * max(se, 1.0 / n), (p_f, p_s)
    coherent, _ = coherent_motion(flow, n_frames=32)
    assert coherent.mean() <= p_f


@pytest.fixture(scope="module")
def crossing():
    """One grid cell: a static-free B-scan at 20 dB whose flow band crosses the plane (polar 80°, azimuth
    90°), classified by the default model with and without the rules, at pool 5."""
    from classifier.bench import grid
    from classifier.features import load_spec
    from classifier.infer import load_model

    model = load_model("signature-bscan")
    levels = grid.speed_levels(load_spec("signature-bscan"))
    cell = grid.GridCell("bscan", "none", 20.0, "mid", 80.0, 90.0, seed=3)
    rows = grid.run_cell(cell, model, levels, pools=(5,), threads=1, abstain_ambiguous=(True, False))
    return {r["abstain_ambiguous"]: r for r in rows}


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_flow_across_a_bscan_without_static_tissue_is_never_decided_as_another_class(crossing):
    ruled, model = crossing[True]["per_class"], crossing[False]["per_class"]
    assert ruled["flow"]["wrong_share"] <= 0.10  # issue target: abstaining is right here

    def right(c):
        return round((c["recall"] or 0.0) * c["decided"])

    assert ruled["flow"]["wrong_share"] <= model["flow"]["wrong_share"] and right(ruled["ballistic"]) == 0

    # the rules turn decisions into sets or, where the pattern moved, into flow: the diffusion pixels gain no
    # wrong decision nor a set without diffusion (rule 4 gives some right ones the set diffusion-or-flow), and
    # the flow pixels gain right decisions and lose wrong ones
    def failed(c):
        return c["decided"] - right(c) + round(c["set_miss_share"] * c["pixels"])

    assert failed(ruled["diffusion"]) <= failed(model["diffusion"])
    assert ruled["diffusion"]["decided"] <= model["diffusion"]["decided"]
    assert right(ruled["flow"]) >= right(model["flow"])
    assert ruled["flow"]["decided"] - right(ruled["flow"]) <= model["flow"]["decided"] - right(model["flow"])


def test_classify_maps_applies_rule_6_last_and_decide_ballistic_skips_it(tmp_path, monkeypatch):
    """doct-classify's default ends with rule 6: every pixel it flags becomes indeterminate and is counted
    (a flag-everything stand-in leaves no single-class decision); --decide-ballistic applies no rule."""
    from classifier import ambiguity
    from classifier.bench.classify import _synthetic_maps
    from classifier.infer import classify_maps, load_model

    mdl = load_model("signature")
    path = _synthetic_maps(tmp_path / "maps.npz", mdl.spec, 24, 0)
    kept = classify_maps(path, mdl, pool=5, background_db=None, abstain_ambiguous=False)
    assert kept.info["ambiguity"] is None
    single = [mdl.classes.index(m) for m in ("diffusion", "ballistic", "flow")]
    assert np.isin(kept.labels, single).any()

    base = classify_maps(path, mdl, pool=5, background_db=None)
    amb = base.info["ambiguity"]
    assert amb["rules"][-5:] == ["borrowed_flow", "mixed_footprint", "unshared", "contradicted", "mixed_shape"]
    assert amb["consensus_min"] == CONSENSUS_MIN
    # rule 9 compares every coarser configuration with the one of the smallest footprint
    assert amb["finest_configuration"] == "original" and amb["mixed_decay_min"] == 0.3
    # the box is the coarsest configuration's 1/e² footprint per axis widened by the pooling window (odd)
    pitch = base.pitch_um
    coarse_lat = max(c.lateral_resolution_um for c in mdl.spec.configurations)
    coarse_ax = max(c.axial_resolution_um for c in mdl.spec.configurations)
    for ax, got in amb["consensus_window_px"].items():
        width = coarse_ax * 2 * np.sqrt(2) / (2 * np.sqrt(np.log(2))) if ax == "z" else coarse_lat
        n = int(np.ceil(width / pitch[ax] - 1e-9)) + 5 - 1
        assert got == max(5, n + 1 - n % 2)
        # rule 7's box: the same with the footprint term 1.5 times as far
        n7 = int(np.ceil(1.5 * width / pitch[ax] - 1e-9)) + 5 - 1
        assert amb["footprint_window_px"][ax] == max(5, n7 + 1 - n7 % 2)
        # rule 8's box: the finest configuration's footprint widened by the pooling window
        fine = (
            min(c.axial_resolution_um for c in mdl.spec.configurations) * np.sqrt(2 / np.log(2))
            if ax == "z"
            else min(c.lateral_resolution_um for c in mdl.spec.configurations)
        )
        n8 = int(np.ceil(fine / pitch[ax] - 1e-9)) + 5 - 1
        assert amb["fine_window_px"][ax] == max(5, n8 + 1 - n8 % 2)
    assert amb["footprint_reach"] == 1.5 and amb["rules"][-2] == "contradicted"

    monkeypatch.setattr(ambiguity, "unshared", lambda labels, *a, **k: np.ones(np.shape(labels), bool))
    flagged = classify_maps(path, mdl, pool=5, background_db=None)
    assert not np.isin(flagged.labels, single).any()
    assert flagged.info["ambiguity"]["changed_pixels"]["unshared"] == flagged.info["classified"]
    assert flagged.info["ambiguity"]["changed_pixels"]["contradicted"] == 0  # a pixel counts for rule 6 first
    # rule 8 beside rule 6: every pixel it flags becomes indeterminate and is counted
    monkeypatch.setattr(ambiguity, "unshared", lambda labels, *a, **k: np.zeros(np.shape(labels), bool))
    monkeypatch.setattr(ambiguity, "contradicted", lambda labels, *a, **k: np.ones(np.shape(labels), bool))
    against = classify_maps(path, mdl, pool=5, background_db=None)
    assert not np.isin(against.labels, single).any()
    assert against.info["ambiguity"]["changed_pixels"]["contradicted"] == against.info["classified"]
    # rule 9 before rules 6 and 8: every flow decision it flags becomes indeterminate and is counted
    monkeypatch.undo()
    n_flow = int((base.labels == mdl.classes.index("flow")).sum())
    assert n_flow > 0
    monkeypatch.setattr(
        ambiguity,
        "mixed_footprint",
        lambda labels, names, *a, **k: (np.asarray(labels) == list(names).index("flow"), None),
    )
    mixed = classify_maps(path, mdl, pool=5, background_db=None)
    assert not (mixed.labels == mdl.classes.index("flow")).any()
    assert mixed.info["ambiguity"]["changed_pixels"]["mixed_footprint"] >= n_flow


def test_rule_10_sees_a_doppler_phase_that_keeps_one_sign_over_the_box():
    """The imaginary part of the box's mean Doppler phasor, at the shortest lag the maps hold: a region of one
    phase (a flow) is seen where |sin φ| ≥ DOPPLER_IM_MIN over the box, phases symmetric about 0 or about π (a
    direction-symmetric motion) cancel, a box with less than half its pixels holding a phase sees nothing, the
    box is never narrower than DOPPLER_WINDOW_MIN, and without a Doppler channel the rule is absent."""
    from classifier.ambiguity import DOPPLER_IM_MIN, DOPPLER_WINDOW_MIN, doppler_drift, doppler_imaginary

    assert DOPPLER_IM_MIN == 0.5 and DOPPLER_WINDOW_MIN == 5
    phase = np.zeros((10, 20))
    phase[:, :8] = 0.7  # sin 0.644: one sign, a flow
    phase[:, 8:14] = np.where(np.arange(6) % 2, 1.2, -1.2)[None, :]  # ± in alternate columns: cancels
    phase[:, 14:] = np.where(np.arange(10) % 2, np.pi - 0.3, -np.pi + 0.3)[:, None]  # about π: cancels
    chans = {"doppler_phase_4@original": np.full_like(phase, 1.0), "doppler_phase_1@original": phase}
    seen, names = doppler_drift(chans, None, 1)
    assert names == ["doppler_phase_1@original"]  # the shortest lag
    seen = seen.reshape(phase.shape)
    # a 5-wide box: up to column 5 it holds only 0.7-columns; column 6 holds four and one at −1.2
    im, _ = doppler_imaginary(chans, 1)
    np.testing.assert_allclose(im[4, 0], np.sin(0.7), atol=1e-12)  # cut at the edge: 3 columns, all 0.7
    np.testing.assert_allclose(im[4, 6], (4 * np.sin(0.7) + np.sin(-1.2)) / 5, atol=1e-12)
    assert seen[:, :6].all() and not seen[:, 6:].any()
    # symmetric phases leave only the box's odd one out: one column (row) of five
    np.testing.assert_allclose(im[2:8, 10], -np.sin(1.2) / 5, atol=1e-12)
    np.testing.assert_allclose(np.abs(im[2:8, 17]), np.sin(0.3) / 5, atol=1e-12)
    # every pixel against a brute-force box mean (cut at the edges; NaN skipped; under half valid: 0), at the
    # minimum box and at a pooling window of 9, with holes of no reference
    holed = phase.copy()
    holed[:, :3] = np.nan
    holed[3:6, 12:16] = np.nan

    def brute(ph, w):
        out = np.zeros(ph.shape)
        h = w // 2
        for i in range(ph.shape[0]):
            for j in range(ph.shape[1]):
                box = ph[max(0, i - h) : i + h + 1, max(0, j - h) : j + h + 1]
                ok = np.isfinite(box)
                out[i, j] = np.sin(box[ok]).mean() if 2 * ok.sum() >= box.size else 0.0
        return out

    for ph in (phase, holed):
        for pool, w in ((1, 5), (5, 5), (9, 9)):
            got, _ = doppler_imaginary({"doppler_phase_1@original": ph}, pool)
            ref = brute(ph, w)
            np.testing.assert_allclose(got, ref, atol=1e-12)
            m, _ = doppler_drift({"doppler_phase_1@original": ph}, None, pool)
            assert m.tolist() == (np.abs(ref) >= DOPPLER_IM_MIN).reshape(-1).tolist()
    h, _ = doppler_drift({"doppler_phase_1@original": holed}, None, 1)
    assert not h.reshape(phase.shape)[:, 0].any()  # its box: three columns without a phase
    idx = np.array([0, 25, 199])
    at, _ = doppler_drift(chans, idx, 1)
    assert at.tolist() == seen.reshape(-1)[idx].tolist()
    assert doppler_drift({"xc_centre_2@original": phase}, None, 1) == (None, [])


def test_rule_10_turns_direction_symmetric_outcomes_into_flow_before_rules_1_to_4():
    """Where the Doppler phase drifted, ballistic, diffusion and their sets with flow become flow (counted as
    doppler_drift) before a B-scan's ballistic decisions become sets; flow and indeterminate stay."""
    labels = np.array([0, 1, 2, 3, 4, 5, 6, 1])
    seen = np.array([True] * 7 + [False])
    out, counts = abstain_where_ambiguous(labels, NAMES, unseen_axis=True, correlation=None, doppler=seen)
    flow = NAMES.index("flow")
    assert out.tolist() == [flow, flow, flow, 3, flow, flow, flow, NAMES.index("ballistic-or-flow")]
    assert counts["doppler_drift"] == 5 and counts["bscan_plane"] == 1


def test_rules_7_and_9_leave_a_flow_decision_the_doppler_phase_founds():
    """A flow decision whose Doppler phase drifted is the pixel's own evidence: rule 7 (a box of other outcomes)
    and rule 9 (a coarser configuration decaying faster) flag it only without that evidence."""
    from classifier.ambiguity import borrowed_flow, mixed_footprint

    flow, ball_set = NAMES.index("flow"), NAMES.index("ballistic-or-flow")
    grid = np.full((9, 30), ball_set)
    grid[:, 10:30] = flow
    shape, idx, labels = grid.shape, np.arange(grid.size), grid.reshape(-1)
    dop = np.zeros(shape, bool)
    dop[:, 10] = True
    without = borrowed_flow(labels, NAMES, idx, shape, (3, 5)).reshape(shape)
    with_dop = borrowed_flow(labels, NAMES, idx, shape, (3, 5), doppler=dop.reshape(-1)).reshape(shape)
    assert without[:, 10].all() and not with_dop[:, 10].any() and with_dop[:, 11].all()
    cols = [
        {"metric": "rho_lin_1", "configuration": "original"},
        {"metric": "rho_lin_1", "configuration": "axial=14"},
        {"metric": "pool_pixels"},
    ]
    rows = np.array([[0.99, 0.40, 25], [0.99, 0.40, 25]])
    got, _ = mixed_footprint(np.array([flow, flow]), NAMES, cols, rows, "original", doppler=np.array([True, False]))
    assert got.tolist() == [False, True]


def test_an_axis_is_seen_while_neighbouring_pixels_share_their_speckle():
    """Rule 1's axes: a B-scan never sees y; a volume sees an axis while the speckle correlation of neighbouring
    pixels exp(−p²/(2s²)) is at least 1/e, a pitch of half the lateral 1/e² width, or 1/(2√ln2)·√2 of the axial
    FWHM; an axis without a pitch or a resolution is unseen."""
    from classifier.ambiguity import NEIGHBOUR_CORRELATION_MIN, neighbour_correlation, unseen_axes

    assert neighbour_correlation(2.0, 2.0) == pytest.approx(np.exp(-0.5))
    assert NEIGHBOUR_CORRELATION_MIN == pytest.approx(np.exp(-1.0))
    lat, ax = 4.9, 3.8
    half_lateral, axial_edge = lat / 2, ax * np.sqrt(2.0) / (2.0 * np.sqrt(np.log(2.0)))
    fine = {"x": 2.0, "y": 2.0, "z": 2.0}
    assert unseen_axes("ZX", fine, lat, ax) == ["y"]
    assert unseen_axes("YZX", fine, lat, ax) == []
    assert unseen_axes("YZX", {**fine, "y": half_lateral}, lat, ax) == []
    assert unseen_axes("YZX", {**fine, "y": half_lateral * 1.01}, lat, ax) == ["y"]
    assert unseen_axes("YZX", {**fine, "z": axial_edge}, lat, ax) == []
    assert unseen_axes("YZX", {**fine, "z": axial_edge * 1.01}, lat, ax) == ["z"]
    assert unseen_axes("YZX", {**fine, "y": 4.0}, lat, ax, lateral_y_um=9.0) == []  # a wider PSF along y
    assert unseen_axes("YZX", {"x": 2.0, "z": 2.0}, lat, ax) == ["y"]  # no y pitch
    assert unseen_axes("YZX", fine, None, None) == ["x", "y", "z"]  # no speckle channels: nothing is seen
    assert unseen_axes("YZX", {**fine, "y": float("nan")}, lat, ax) == ["y"]


def test_rules_0_and_5_read_the_dynamic_field_s_channels_beside_the_field_s():
    """Inside static tissue the field's peak stays centred while the dynamic field's moves (speckle-motion §3 (f)):
    rule 0 reads the family it is given, and the pixels either family shows are coherent motion."""
    ch = {
        "xc_peak_4@original": np.array([0.9, 0.9, 0.9]),
        "xc_centre_4@original": np.array([0.9, 0.1, 0.9]),
        "xcd_peak_4@original": np.array([0.9, 0.9, 0.9]),
        "xcd_centre_4@original": np.array([0.1, 0.9, 0.9]),
    }
    field, used_f = coherent_motion(ch, n_frames=32)
    dyn, used_d = coherent_motion(ch, n_frames=32, family="xcd")
    assert field.tolist() == [False, True, False] and dyn.tolist() == [True, False, False]
    assert used_f == ["xc_peak_4@original", "xc_centre_4@original"]
    assert used_d == ["xcd_peak_4@original", "xcd_centre_4@original"]
    # rule 5: the same path read from either family
    p, lags = 2.0, (2, 4, 8, 16)
    line = [0.3 + 0.45 * p * (m - 2) / 14 for m in lags]
    path = _path([line], [[0.0] * 4], [0.9], lags)
    dyn_path = {k.replace("xc_", "xcd_", 1): v for k, v in path.items()}
    assert translated(dyn_path, {"z": p, "x": p}, family="xcd")[0].tolist() == [True]
    assert translated(dyn_path, {"z": p, "x": p}) == (None, [])


def test_classify_maps_counts_coherent_motion_that_only_the_dynamic_field_shows(tmp_path):
    """Maps whose field's speckle peak is centred everywhere and whose dynamic field's peak moved: every
    direction-symmetric decision becomes flow by rule 0, read from the xcd channels; without them, none."""
    import dataclasses

    from classifier.bench.classify import _synthetic_maps
    from classifier.infer import classify_maps, load_model
    from torchdoct.measured.mapsfile import read_maps, write_maps

    mdl = load_model("signature")
    base = read_maps(_synthetic_maps(tmp_path / "maps.npz", mdl.spec, 24, 0))
    shape = base.maps.shape[1:]
    extra = {"xc_peak_4": 0.9, "xc_centre_4": 0.9, "xcd_peak_4": 0.9, "xcd_centre_4": 0.1}
    rec0 = base.meta["channels"][0]
    recs = [{**rec0, "name": f"{k}@{rec0['resolution']}", "metric": k, "unit": "1"} for k in extra]

    def with_channels(keys):
        chans = [r for r in recs if r["metric"] in keys]
        arrays = np.stack([np.full(shape, extra[r["metric"]], np.float32) for r in chans])
        meta = {**base.meta, "channels": base.meta["channels"] + chans}
        m = dataclasses.replace(
            base,
            maps=np.concatenate([base.maps, arrays]),
            channels=base.channels + tuple(r["name"] for r in chans),
            meta=meta,
        )
        return write_maps(tmp_path / f"m{len(keys)}.npz", m)

    field_only = classify_maps(with_channels(list(extra)[:2]), mdl, pool=1, background_db=None)
    both = classify_maps(with_channels(list(extra)), mdl, pool=1, background_db=None)
    assert field_only.info["ambiguity"]["changed_pixels"]["coherent_motion"] == 0
    changed = both.info["ambiguity"]["changed_pixels"]["coherent_motion"]
    assert changed > 0 and "xcd_peak_4@original" in both.info["ambiguity"]["coherent_channels"]
    sym = [mdl.classes.index(m) for m in ("diffusion", "ballistic")]
    assert not np.isin(both.labels, sym).any()
