"""What accuracy costs in acquisition time (classifier.bench.protocol): the variants, the decision from the
rules of classifier.ambiguity on known channel values, the scores on known label arrays, the matched
speed pair, the results files of a tiny run and the refusals."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

pytest.importorskip("torchdoct")

from classifier.bench import protocol as P
from classifier.bench.protocol import Variant

B, F, U = P.CODES["ballistic"], P.CODES["flow"], P.UNDECIDED


def test_full_variants_are_every_combination_and_quick_one_axis_at_a_time():
    full = P.full_variants()
    assert len(full) == len(P.FRAMES) * len(P.INTERVAL_FACTORS) * len(P.WINDOWS) == len(set(full))
    assert {v.n_frames for v in full} == set(P.FRAMES) and {v.window for v in full} == set(P.WINDOWS)
    quick = P.quick_variants()
    assert len(quick) == len(set(quick)) == 7
    centre = Variant(32, 1.0, 9)
    assert centre in quick and set(quick) <= set(full)
    for v in quick:  # every quick variant differs from the centre along one axis at most
        assert sum((v.n_frames != 32, v.interval_factor != 1.0, v.window != 9)) <= 1
    assert {v.n_frames for v in quick} == set(P.FRAMES)
    assert {v.interval_factor for v in quick} == set(P.INTERVAL_FACTORS)
    assert {v.window for v in quick} == set(P.WINDOWS)
    assert Variant(64, 0.5, 13).key == "T64-dt0.5x-w13"


@pytest.mark.parametrize(
    "frames,factors,windows",
    [
        ((4,), (1.0,), (9,)),
        ((32,), (0.0,), (9,)),
        ((32,), (1.0,), (8,)),
        ((32, 32), (1.0,), (9,)),
        ((), (1.0,), (9,)),
        ((32,), (float("nan"),), (9,)),
    ],
)
def test_bad_axes_are_refused(frames, factors, windows):
    with pytest.raises(ValueError):
        P.full_variants(frames, factors, windows)


def _channels(pixels, lags=(2, 4, 8, 16)):
    """Speckle channels of one resolution from per-pixel dicts {lag: (centre, peak, shift_um)}."""
    ch = {}
    for m in lags:
        for k, name in enumerate(("centre", "peak", "shift")):
            ch[f"xc_{name}_{m}@original"] = np.array([p[m][k] for p in pixels], np.float64)
    return ch


def _pixel(centre, peak=None, shift=None):
    """{lag: (centre, peak, shift)} with per-lag lists (lags 2, 4, 8, 16)."""
    peak = centre if peak is None else peak
    shift = [0.0] * 4 if shift is None else shift
    return {m: (centre[i], peak[i], shift[i]) for i, m in enumerate((2, 4, 8, 16))}


def test_decision_follows_the_rules_of_classifier_ambiguity():
    pitch = 1.5
    pixels = [
        # 0: the pattern moved coherently at lag 2 (peak kept, centre lost): rule 0 -> flow in both
        _pixel([0.3, 0.2, 0.2, 0.1], peak=[0.9, 0.8, 0.7, 0.6], shift=[1.5, 3.0, 4.5, 6.0]),
        # 1: decorrelated gradually, centred: ballistic in both
        _pixel([0.9, 0.7, 0.5, 0.2]),
        # 2: decorrelated, the offset starts a pitch off the centre: rule 4 -> undecided / flow
        _pixel([0.9, 0.7, 0.5, 0.2], shift=[1.0, 1.0, 1.0, 1.0]),
        # 3: not decorrelated at the longest lag (rule 2): undecided in both
        _pixel([0.95, 0.9, 0.85, 0.8]),
        # 4: decorrelated before the first lag (rule 3): undecided in both
        _pixel([0.21, 0.2, 0.2, 0.2]),
        # 5: coherent and moved: rule 0 comes first -> flow in both
        _pixel([0.3, 0.2, 0.2, 0.1], peak=[0.9, 0.8, 0.7, 0.6], shift=[1.0, 1.0, 1.0, 1.0]),
        # 6: the offset grew by a third of a pitch while the pattern held: rule 4
        _pixel([0.9, 0.7, 0.5, 0.2], peak=[0.9, 0.7, 0.5, 0.2], shift=[0.1, 0.3, 0.6, 0.6]),
    ]
    d = P.decide(_channels(pixels), 32, pitch)
    assert d["rules"].tolist() == [F, B, U, U, U, F, U]
    assert d["offset-as-flow"].tolist() == [F, B, F, U, U, F, F]
    assert d["coherent"].tolist() == [True, False, False, False, False, True, False]
    assert d["moved"].tolist() == [True, False, True, False, False, True, True]
    assert d["decorrelated"].tolist() == [True, True, True, False, True, True, True]
    assert d["fast"].tolist() == [False, False, False, False, True, False, False]
    with pytest.raises(ValueError, match="speckle channels"):
        P.decide({"mean_db@original": np.zeros(3)}, 32, pitch)


def test_scores_are_exact_on_known_label_arrays():
    truth = np.zeros((1, 24), np.int64)
    truth[0, 2:12] = B
    truth[0, 12:22] = F
    masks = {"ballistic": truth[0] == B, "flow": truth[0] == F}
    out = np.full(24, U)
    out[2:7] = B  # ballistic: 5 right, 5 undecided
    out[12:18] = F  # flow: 6 right,
    out[18:20] = B  # 2 decided ballistic, 2 undecided
    c = P.count_outcome(out, truth, masks, {"coherent": out == F})
    assert c["ballistic"] == {"pixels": 10, "decided": 5, "right": 5, "wrong": 0, "coherent": 0}
    assert c["flow"] == {"pixels": 10, "decided": 8, "right": 6, "wrong": 2, "coherent": 6}
    s = P.score_outcome(c)
    assert s["per_band"]["ballistic"]["coverage"] == 0.5 and s["per_band"]["ballistic"]["accuracy"] == 1.0
    assert s["per_band"]["flow"]["coverage"] == 0.8 and s["per_band"]["flow"]["accuracy"] == 0.75
    assert s["per_band"]["flow"]["wrong_share"] == 0.2 and s["per_band"]["flow"]["rules"]["coherent"] == 0.6
    assert s["coverage"] == 13 / 20 and s["balanced_accuracy"] == pytest.approx(0.875)
    assert s["wrong_share_max"] == 0.2 and s["pixels"] == 20
    none = P.score_outcome(P.count_outcome(np.full(24, U), truth, masks))
    assert none["coverage"] == 0.0 and none["balanced_accuracy"] is None and none["wrong_share_max"] == 0.0
    assert none["per_band"]["flow"]["accuracy"] is None


def test_scored_pixels_keep_their_box_inside_the_band_and_the_image():
    truth = np.zeros((9, 20), np.int64)
    truth[:, 2:9] = B  # 7 columns
    truth[:, 9:20] = F  # 11 columns, touching the image's right edge
    mb = P.scored_mask(truth, B, 2)
    assert mb.sum() == 5 * 3 and mb[2:7, 4:7].all()  # rows 2..6 (image edge), columns 4..6
    mf = P.scored_mask(truth, F, 2)
    assert mf.sum() == 5 * 7 and mf[2:7, 11:18].all()
    assert (P.scored_mask(truth, F, 0) == (truth == F)).all()


def test_matched_ballistic_speed_gives_the_flows_single_pixel_correlation():
    from classifier.features import load_spec

    spec = load_spec("signature-bscan")
    v = P.matched_ballistic_speed(spec)
    tau, dens = P.match_lag_s(spec), P._density()
    flow = P._rho_intensity("flow", P.FLOW_SPEED, tau, spec, dens, P.FLOW_POLAR_DEG, P.FLOW_AZIMUTH_DEG)
    assert P._rho_intensity("ballistic", v, tau, spec, dens) == pytest.approx(flow, abs=5e-3)
    assert (
        P._rho_intensity("ballistic", 2 * v, tau, spec, dens)
        < flow
        < P._rho_intensity("ballistic", v / 2, tau, spec, dens)
    )
    with pytest.raises(ValueError, match="--ballistic-speed"):  # a flow that has not moved: nothing matches
        P.matched_ballistic_speed(spec, flow_speed=1e-9)


TINY = ["--frames", "16", "--intervals", "1,2", "--windows", "3", "--seeds", "1", "--threads", "1", "--no-progress"]


def test_a_tiny_run_writes_four_self_describing_files_and_refuses_to_overwrite(tmp_path, capsys):
    assert P.main(["--out", str(tmp_path), *TINY, "--ballistic-speed", "0.05"]) == 0
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["protocol.csv", "protocol.json", "protocol.md", "protocol.png"]
    res = json.loads((tmp_path / "protocol.json").read_text(encoding="utf-8"))
    assert res["schema_version"] == P.SCHEMA_VERSION and res["benchmark"] == "protocol"
    assert set(res["definitions"]) == {"phantom", "variants", "decision", "scores"}
    assert (
        res["command"].startswith("python -m classifier.bench.protocol") and "--ballistic-speed 0.05" in res["command"]
    )
    assert {"cpu_count", "torch"} <= set(res["machine"])
    assert res["motions"]["ballistic"] == {
        "speed_um_per_s": 0.05,
        "directions": "isotropic",
        "matched": False,
        "matched_at_s": None,
    }
    assert len(res["rows"]) == 2 * len(P.DECISIONS)
    for r in res["rows"]:
        assert r["acquisition_s"] == pytest.approx(r["n_frames"] * r["interval_s"])
        assert r["lags_frames"] == [1, 2, 4, 8] and r["decision"] in P.DECISIONS
        assert r["pixels"] > 0 and 0.0 <= r["coverage"] <= 1.0 and r["seconds"]["total"] > 0
        assert set(r["per_band"]) == set(P.BANDS) and len(r["per_seed"]) == 1
    rows = list(csv.DictReader((tmp_path / "protocol.csv").read_text(encoding="utf-8").splitlines()))
    assert len(rows) == len(res["rows"]) and list(rows[0]) == list(P._COLUMNS)
    md = (tmp_path / "protocol.md").read_text(encoding="utf-8")
    assert "## Decision `rules`" in md and "## Decision `offset-as-flow`" in md and "| frames |" in md
    before = (tmp_path / "protocol.json").read_bytes()
    capsys.readouterr()
    assert P.main(["--out", str(tmp_path), *TINY]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and "--force" in err[0]
    assert (tmp_path / "protocol.json").read_bytes() == before


@pytest.mark.parametrize(
    "extra",
    [
        ["--windows", "4"],
        ["--frames", "4"],
        ["--intervals", "0"],
        ["--intervals", "x"],
        ["--seeds", "0"],
        ["--flow-speed", "-1"],
        ["--polar", "200"],
        ["--stem", "a/b"],
        ["--threads", "0"],
        ["--spec", "no-such-spec"],
    ],
)
def test_bad_arguments_exit_2_with_one_error_line_and_write_nothing(tmp_path, capsys, extra):
    out = tmp_path / "out"
    assert P.main(["--out", str(out), "--no-progress", *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:")
    assert not out.exists() or not any(out.iterdir())


def test_an_output_that_is_a_file_and_both_system_sources_are_refused(tmp_path, capsys):
    f = tmp_path / "file"
    f.write_text("x")
    assert P.main(["--out", str(f), "--quick"]) == 2
    assert capsys.readouterr().err.startswith("error:")
    with pytest.raises(SystemExit) as e:
        P.main(["--out", str(tmp_path), "--spec", "signature", "--like", "m.npz"])
    assert e.value.code == 2


def test_torchdoct_protocol_is_the_same_command(tmp_path, capsys):
    """``torchdoct protocol`` (the entry point of the classifier's commands) parses the same options and
    runs the same checks: an output that is a file exits 2 with one error line, nothing written."""
    from torchdoct.cli import main

    f = tmp_path / "file"
    f.write_text("x")
    assert main(["protocol", "--out", str(f), "--quick", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and f.read_text() == "x"
    with pytest.raises(SystemExit) as e:
        main(["protocol", "--help"])
    assert e.value.code == 0 and "--frames" in capsys.readouterr().out
