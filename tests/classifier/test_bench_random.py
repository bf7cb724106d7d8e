"""The random phantoms (classifier.bench.random_phantoms): the prior is what the module states, a draw is a pure
function of its seed, geometry and index, the summary counts what it says, and the command writes its files
together and keeps what exists."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from classifier.bench import random_phantoms as R

ROOT = Path(__file__).resolve().parents[2]
RECORDED = ROOT / "docs" / "benchmarks" / "random-phantoms.json"


def test_a_draw_is_a_pure_function_of_its_seed_geometry_and_index():
    assert R.draw("bscan", 3) == R.draw("bscan", 3)
    assert R.draw("bscan", 3) != R.draw("bscan", 4)
    assert R.draw("bscan", 3) != R.draw("bscan", 3, seed=R.SEED + 1)
    assert R.draw("bscan", 3)[1]["motions"] != R.draw("volume", 3)[1]["motions"]  # the geometry seeds it too
    for bad in (-1, 1.5, True, "3"):
        with pytest.raises(ValueError, match="draw index"):
            R.draw("bscan", bad)
    with pytest.raises(ValueError, match="geometry 'aline'"):
        R.draw("aline", 0)


@pytest.mark.parametrize("geometry", R.GEOMETRIES)
def test_every_draw_is_a_valid_phantom_inside_the_stated_prior(geometry):
    from torchdoct.image.phantom import phantom_from_dict

    fov = R.N_PX * R.PITCH_UM
    for index in range(60):
        phantoms, d = R.draw(geometry, index)
        for p in phantoms:
            phantom_from_dict(p)  # the renderer's own validation
        main = phantoms[0]
        assert main["grid"]["kind"] == geometry and main["grid"]["n_x"] == main["grid"]["n_z"] == R.N_PX
        assert (main["grid"].get("n_y") == R.VOLUME_NY) == (geometry == "volume")
        assert d["structure"] in R.STRUCTURES and d["context"] in R.CONTEXTS and d["snr_db"] in R.SNR_CHOICES
        assert main.get("noise", {}).get("snr_db") == d["snr_db"]
        assert R.DENSITY_RANGE[0] <= d["density_per_um3"] <= R.DENSITY_RANGE[1]
        m = d["motions"]
        assert R.DIFFUSION_RANGE[0] <= m["diffusion"]["diffusion_um2_per_s"] <= R.DIFFUSION_RANGE[1]
        assert R.BALLISTIC_RANGE[0] <= m["ballistic"]["speed_um_per_s"] <= R.BALLISTIC_RANGE[1]
        assert R.FLOW_RANGE[0] <= m["flow"]["speed_um_per_s"] <= R.FLOW_RANGE[1]
        regions = {r["name"]: r for r in main["region"]}
        assert {r["motion"][0]["kind"] for r in main["region"] if r["motion"]} == set(R.MOTIONS)
        if d["structure"] == "layers":
            slabs = [regions[k] for k in R.MOTIONS]
            depths = [s["z_max_um"] - s["z_min_um"] for s in slabs]
            assert min(depths) >= R.LAYER_MIN_UM - 1e-9 and sum(depths) == pytest.approx(fov)
        else:
            vessel = regions["flow"]
            f = m["flow"]
            p, a = math.radians(f["polar_angle_deg"]), math.radians(f["azimuth_deg"])
            # the flow runs along the vessel's axis
            assert vessel["axis"] == pytest.approx([math.sin(p) * math.cos(a), math.sin(p) * math.sin(a), math.cos(p)])
            assert R.VESSEL_RADIUS_RANGE[0] <= vessel["radius_um"] <= R.VESSEL_RADIUS_RANGE[1]
            assert vessel["center_um"][1] == 0.0  # it crosses the plane y = 0, the B-scan's
        if d["context"] == "half":  # the static circle's edge passes through x = 0 on the B-scan's plane
            st = regions["static-tissue"]
            assert st["motion"] == [] and st["center_um"][0] + st["radius_um"] == pytest.approx(0.0)
            assert main["region"][-1] is st  # painted over the motions
        assert (len(phantoms) == 2) == (d["context"] == "under")
        if d["context"] == "under":
            assert phantoms[1]["background"][0]["density_per_um3"] == d["density_per_um3"]
            assert "noise" not in phantoms[1] and "region" not in phantoms[1]


def test_the_prior_draws_flow_directions_uniformly_on_the_sphere_and_speeds_log_uniformly():
    """Over 3000 draws the flow's cos(polar) has mean 0 and variance 1/3 (uniform on [−1, 1]) and the log of
    each range's value is uniform over the log of its range (mean at the middle, variance (ln(hi/lo))²/12):
    each mean within 4 standard errors."""
    n = 3000
    draws = [R.draw("bscan", i)[1]["motions"] for i in range(n)]
    cos_polar = np.cos(np.radians([d["flow"]["polar_angle_deg"] for d in draws]))
    assert abs(cos_polar.mean()) < 4 * math.sqrt(1 / 3 / n)
    assert abs((cos_polar**2).mean() - 1 / 3) < 4 * math.sqrt((1 / 5 - 1 / 9) / n)
    azimuth = np.radians([d["flow"]["azimuth_deg"] for d in draws])
    assert abs(np.cos(azimuth).mean()) < 4 * math.sqrt(0.5 / n) and abs(np.sin(azimuth).mean()) < 4 * math.sqrt(0.5 / n)
    for key, field, (lo, hi) in (
        ("diffusion", "diffusion_um2_per_s", R.DIFFUSION_RANGE),
        ("ballistic", "speed_um_per_s", R.BALLISTIC_RANGE),
        ("flow", "speed_um_per_s", R.FLOW_RANGE),
    ):
        logs = np.log([d[key][field] for d in draws])
        width = math.log(hi / lo)
        assert abs(logs.mean() - math.log(lo * hi) / 2) < 4 * width / math.sqrt(12 * n), key


def _row(pool, rules, wrong, pixels=100, coverage=0.5):
    return {
        "pool": pool,
        "rules": rules,
        "per_class": {m: {"pixels": pixels, "coverage": coverage, "wrong_share": w} for m, w in zip(R.MOTIONS, wrong)},
        "coverage": coverage,
        "wrong_share_max": max(wrong),
        "seconds": 0.0,
    }


def test_the_summary_counts_the_draws_over_each_bound_and_pools_the_pixels():
    draws = [
        {"geometry": "bscan", "index": 0, "rows": [_row(1, True, (0.0, 0.0, 0.2))]},
        {"geometry": "bscan", "index": 1, "rows": [_row(1, True, (0.07, 0.0, 0.0), pixels=300, coverage=0.9)]},
        {"geometry": "bscan", "index": 2, "rows": [_row(1, True, (0.0, 0.05, 0.0))]},  # at a bound: not over it
        {"geometry": "bscan", "index": 3, "rows": [_row(1, True, (0.0, 0.0, 0.0))]},
    ]
    (s,) = R.summarize(draws)
    assert (s["geometry"], s["pool"], s["rules"], s["draws"]) == ("bscan", 1, True, 4)
    assert s["over_bound"] == {"0.05": 0.5, "0.1": 0.25}
    assert s["median_coverage"] == 0.5
    assert s["per_class"]["diffusion"]["wrong_share"] == pytest.approx(0.07 * 300 / 600)
    assert s["per_class"]["flow"]["wrong_share"] == pytest.approx(0.2 * 100 / 600)
    assert s["per_class"]["diffusion"]["coverage"] == pytest.approx((0.5 * 300 + 0.9 * 300) / 600)
    assert [(w["index"], w["motion"]) for w in s["worst"]] == [(0, "flow"), (1, "diffusion"), (2, "ballistic")]

    # a motion painted over (no pixels: no coverage, no wrong share) counts in no pool of that motion
    gone = _row(1, True, (0.0, 0.0, 0.0))
    gone["per_class"]["flow"] = {"pixels": 0, "coverage": None, "wrong_share": None}
    (s2,) = R.summarize(draws + [{"geometry": "bscan", "index": 4, "rows": [gone]}])
    assert s2["per_class"]["flow"]["pixels"] == 600 and s2["per_class"]["flow"]["wrong_share"] == pytest.approx(0.2 / 6)
    assert s2["draws"] == 5 and s2["over_bound"] == {"0.05": 0.4, "0.1": 0.2}


def test_the_command_writes_its_files_together_keeps_them_and_writes_a_draw_to_render(tmp_path, capsys):
    from torchdoct.image.phantom import load_phantom, phantom_from_dict

    out = tmp_path / "random"
    args = ["--out", str(out), "--bscans", "1", "--volumes", "0", "--no-progress", "--threads", "1"]
    assert R.main(args) == 0
    res = json.loads((out / "random-phantoms.json").read_text(encoding="utf-8"))
    assert (
        res["command"] == f"python -m classifier.bench.random_phantoms --bscans 1 --volumes 0 --seed {R.SEED} --out DIR"
    )
    (d,) = res["draws"]
    assert {(r["pool"], r["rules"]) for r in d["rows"]} == {(p, b) for p in R.POOLS for b in (True, False)}
    assert d["motions"] == R.draw("bscan", 0)[1]["motions"]
    assert "| bscan | 5 | rules (default) | 1 |" in (out / "random-phantoms.md").read_text(encoding="utf-8")
    assert (out / "random-phantoms.png").stat().st_size > 0
    before = (out / "random-phantoms.json").read_bytes()
    assert R.main(args) == 2
    assert "random-phantoms.json exists; give --force" in capsys.readouterr().err
    assert (out / "random-phantoms.json").read_bytes() == before
    assert R.main(["--out", str(tmp_path / "none"), "--bscans", "0", "--volumes", "0"]) == 2
    assert "nothing to draw" in capsys.readouterr().err and not (tmp_path / "none").exists()
    assert R.main(["--out", str(tmp_path / "none"), "--bscans", "-2"]) == 2
    assert "--bscans -2: give a whole number" in capsys.readouterr().err

    drawn = tmp_path / "draw"
    index = next(i for i in range(50) if R.draw("volume", i)[1]["context"] == "under")  # two files: moving, static
    assert R.main(["--out", str(drawn), "--draw", f"volume:{index}"]) == 0
    written = sorted(drawn.iterdir())
    assert [p.name for p in written] == [f"random-volume-{index}-static.toml", f"random-volume-{index}.toml"]
    phantoms, _ = R.draw("volume", index)
    for p, d in zip(written[::-1], phantoms):  # the files render's TOML reader reads are the draw's phantoms
        assert load_phantom(p).to_dict() == phantom_from_dict(d).to_dict()
    assert R.main(["--out", str(drawn), "--draw", f"volume:{index}"]) == 2  # kept without --force
    assert "pass --force to overwrite" in capsys.readouterr().err
    assert R.main(["--out", str(drawn), "--draw", "aline:1"]) == 2
    assert "give GEOMETRY:INDEX" in capsys.readouterr().err


def test_every_drawn_phantom_round_trips_through_its_toml_file():
    import tomllib

    from torchdoct.image.phantom import phantom_from_dict

    for geometry in R.GEOMETRIES:
        for index in range(40):
            for d in R.draw(geometry, index)[0]:
                again = tomllib.loads(R.phantom_toml(d, "a header\nof two lines"))
                assert phantom_from_dict(again).to_dict() == phantom_from_dict(d).to_dict(), (geometry, index)


def test_the_recorded_run_holds_every_draw_of_its_prior():
    res = json.loads(RECORDED.read_text(encoding="utf-8"))
    n = {g: sum(d["geometry"] == g for d in res["draws"]) for g in R.GEOMETRIES}
    assert n == {"bscan": R.N_BSCANS, "volume": R.N_VOLUMES}
    assert res["command"] == (
        f"python -m classifier.bench.random_phantoms --bscans {R.N_BSCANS} --volumes {R.N_VOLUMES} --seed {R.SEED} "
        "--out DIR"
    )
    for d in res["draws"][:: max(1, len(res["draws"]) // 12)]:  # a sample: their descriptions are the draws'
        assert {k: d[k] for k in ("structure", "context", "snr_db", "motions")} == {
            k: R.draw(d["geometry"], d["index"], res["seed"])[1][k]
            for k in ("structure", "context", "snr_db", "motions")
        }
    assert R.summarize(res["draws"]) == res["summary"]


@pytest.mark.slow  # two B-scans and a volume rendered, mapped and classified four times (about 40 s)
def test_draws_run_again_give_the_recorded_scores():
    """The recorded file is what the code gives: the same draws, rendered, mapped and classified again, decide
    the same pixels (to within two pixels of a motion: a pixel at a decision threshold may flip with the
    floating-point rounding of another machine)."""
    res = json.loads(RECORDED.read_text(encoding="utf-8"))
    recorded = {(d["geometry"], d["index"]): d for d in res["draws"]}
    for key in (("bscan", 0), ("bscan", 1), ("volume", 0)):
        again = R.run_draw(*key, res["seed"], threads=1)
        for r0, r1 in zip(recorded[key]["rows"], again["rows"]):
            assert (r0["pool"], r0["rules"]) == (r1["pool"], r1["rules"])
            for m in R.MOTIONS:
                a, b = r0["per_class"][m], r1["per_class"][m]
                assert a["pixels"] == b["pixels"], (key, m)
                tol = 2 / max(a["pixels"], 1)
                assert b["coverage"] == pytest.approx(a["coverage"], abs=tol), (key, r0["pool"], r0["rules"], m)
                assert b["wrong_share"] == pytest.approx(a["wrong_share"], abs=tol), (key, r0["pool"], r0["rules"], m)
