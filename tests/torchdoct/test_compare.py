"""Per-sample means and the paper's tests (torchdoct.measured.compare) and ``torchdoct compare``."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from _maps_data import make_maps
from scipy import stats

from torchdoct.cli import main
from torchdoct.measured.compare import compare_samples, parse_config, plot_comparison, region_mask, sample_means
from torchdoct.measured.io import write_maps


def test_sample_means_and_regions():
    rng = np.random.default_rng(0)
    m = make_maps(rng, ["original", "axial=14"], nan_at=(2, 3))
    everything = region_mask(m)
    assert everything.all()
    means = sample_means(m, everything)
    cfgs = list(means)
    assert [c.resolution for c in cfgs] == ["original", "axial=14"]
    liv = m["liv@original"]
    assert means[cfgs[0]]["liv"][0] == pytest.approx(np.nanmean(liv.astype(np.float64)), rel=1e-12)
    assert means[cfgs[0]]["liv"][1] == liv.size - 1  # the NaN pixel is left out
    bright = region_mask(m, threshold_db=10.0)
    assert not bright[0].any() and bright[1:].all()  # mean_db of row 0 is 0 dB
    assert sample_means(m, bright)[cfgs[1]]["ocds"][0] == pytest.approx(
        m["ocds@axial=14"][1:].astype(np.float64).mean(), rel=1e-12
    )
    mask = np.zeros((6, 7), dtype=int)
    mask[2:4, 1:3] = 1
    assert region_mask(m, mask=mask).sum() == 4
    with pytest.raises(ValueError, match="spatial shape"):
        region_mask(m, mask=np.ones((7, 6), bool))
    with pytest.raises(ValueError, match="not both"):
        region_mask(m, mask=mask, threshold_db=1.0)
    with pytest.raises(ValueError, match="0/1"):
        region_mask(m, mask=mask * 2)


def test_paired_t_test_between_two_configurations():
    rng = np.random.default_rng(1)
    samples = {f"s{i}": [(make_maps(rng, ["original", "axial=14"], shift={"axial=14": 2.0}), None)] for i in range(5)}
    samples = {k: [(m, region_mask(m))] for k, [(m, _)] in samples.items()}
    res = compare_samples(samples)
    assert res.configs == ["original", "axial=14"] and len(res.tests) == 2
    for metric in ("liv", "ocds"):
        v = res.values(metric)
        ref = stats.ttest_rel(v[:, 0], v[:, 1])
        row = res.tests[res.tests["metric"] == metric].iloc[0]
        assert row["test"] == "paired t-test"
        assert row["statistic"] == pytest.approx(ref.statistic, rel=1e-12)
        assert row["p_value"] == pytest.approx(ref.pvalue, rel=1e-12)
        assert row["mean_diff_b_minus_a"] == pytest.approx(v[:, 1].mean() - v[:, 0].mean(), rel=1e-12)
        assert row["sd_a"] == pytest.approx(np.std(v[:, 0], ddof=1), rel=1e-12)
    assert res.tests[res.tests["metric"] == "liv"].iloc[0]["p_value"] < 1e-3  # a 2 dB² shift is obvious
    flipped = compare_samples(samples, configs=["axial=14", "original"])
    a, b = flipped.tests.iloc[0], res.tests.iloc[0]
    assert a["statistic"] == pytest.approx(-b["statistic"]) and a["p_value"] == pytest.approx(b["p_value"])


def test_kruskal_then_pairwise():
    rng = np.random.default_rng(2)
    resolutions = ["original", "axial=7.6", "axial=11.4", "axial=14"]
    samples = {}
    for i in range(4):
        m = make_maps(rng, resolutions, shift={"axial=14": 3.0})
        samples[f"s{i}"] = [(m, region_mask(m))]
    res = compare_samples(samples, metrics=["liv"])
    kw = res.tests[res.tests["test"] == "Kruskal-Wallis"].iloc[0]
    v = res.values("liv")
    ref = stats.kruskal(*v.T)
    assert kw["statistic"] == pytest.approx(ref.statistic) and kw["p_value"] == pytest.approx(ref.pvalue)
    pairs = res.tests[res.tests["test"] == "paired t-test"]
    assert len(pairs) == 6 and set(pairs["posthoc"]) == {bool(ref.pvalue < 0.05)}
    for _, r in pairs.iterrows():
        i, j = res.configs.index(r["config_a"]), res.configs.index(r["config_b"])
        assert r["p_value"] == pytest.approx(stats.ttest_rel(v[:, i], v[:, j]).pvalue, rel=1e-12)
    assert "Kruskal-Wallis" in res.format()


def test_wavelength_pairs_across_maps_files(tmp_path, capsys):
    """840 nm reduced to 18/14 µm vs 1310 nm original: one sample = two maps files, matched by optics."""
    rng = np.random.default_rng(3)
    args, masks = [], []
    for i in range(4):
        m840 = make_maps(rng, ["original", "axial=14,lateral=18"], shift={"axial=14,lateral=18": 4.0})
        m1310 = make_maps(rng, ["original"], wavelength=1.31, shape=(5, 5))
        for tag, m in (("840", m840), ("1310", m1310)):
            p = write_maps(tmp_path / f"s{i}_{tag}.npz", m)
            args.append(f"spheroid{i}={p}")
            mask = np.ones(m.maps.shape[1:], bool)
            mask[-1] = False
            np.save(tmp_path / f"mask{i}_{tag}.npy", mask)
            masks += ["--mask", str(tmp_path / f"mask{i}_{tag}.npy")]
    out, per, plot = tmp_path / "t.csv", tmp_path / "p.csv", tmp_path / "f.png"
    argv = [
        "compare",
        *args,
        *masks,
        "--config",
        "0.84:axial=14,lateral=18",
        "--config",
        "1.31:original",
        "--out",
        str(out),
        "--per-sample",
        str(per),
        "--plot",
        str(plot),
    ]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "840nm axial=14,lateral=18" in text and "1310nm original" in text
    table = pd.read_csv(out)
    assert list(table["test"]) == ["paired t-test", "paired t-test"]
    per_sample = pd.read_csv(per)
    assert sorted(set(per_sample["sample"])) == [f"spheroid{i}" for i in range(4)]
    assert set(per_sample["n_pixels"]) == {5 * 7, 4 * 5}  # masks drop the last row
    assert plot.stat().st_size > 0
    assert main(argv) == 2 and "exists" in capsys.readouterr().err
    # without --config: the configurations common to all samples (840 original, 840 reduced, 1310 original)
    assert main(["compare", *args, "--json"]) == 0
    assert "Kruskal-Wallis" in capsys.readouterr().out
    assert main(["compare", *args, "--config", "original"]) == 2
    assert "add the wavelength" in capsys.readouterr().err


def test_errors_and_plot(tmp_path):
    rng = np.random.default_rng(4)
    m = make_maps(rng, ["original", "axial=14"])
    m2 = make_maps(rng, ["original"])
    with pytest.raises(ValueError, match="at least 2 configurations"):
        compare_samples({"a": [(m, region_mask(m))], "b": [(m2, region_mask(m2))]})
    with pytest.raises(ValueError, match="has no channels"):
        compare_samples({"a": [(m, region_mask(m))], "b": [(m2, region_mask(m2))]}, configs=["original", "axial=14"])
    with pytest.raises(ValueError, match="not a wavelength"):
        parse_config("nm:original")
    res = compare_samples(
        {"a": [(m, region_mask(m))], "b": [(make_maps(rng, ["original", "axial=14"]), np.ones((6, 7), bool))]}
    )
    p = plot_comparison(res, tmp_path / "f.svg")
    assert p.read_text().startswith("<?xml")
    with pytest.raises(ValueError, match="exists"):
        plot_comparison(res, p)
    assert math.isfinite(res.tests.iloc[0]["p_value"])


def _render(rng, *, nz=36, nx=36, pz=1.5, px=2.0, frames=8, dt=0.2048, d_um2_per_s=0.005, density=0.03):
    """Sum of Gaussian PSFs (4.9/3.8 µm, 840 nm, phase exp(i2kz_j)) of Poisson scatterers, half of them
    diffusing: complex [frames, nz, nx] on a pixel grid at y = 0."""
    from torchdoct.conventions import amplitude_sigma_axial_um, amplitude_sigma_lateral_um, wavenumber_per_um

    sx, sz, k = amplitude_sigma_lateral_um(4.9), amplitude_sigma_axial_um(3.8), wavenumber_per_um(0.84)
    z_um, x_um = np.arange(nz) * pz, np.arange(nx) * px
    lo = np.array([-6 * sx, -6 * sx, -6 * sz])
    hi = np.array([x_um[-1] + 6 * sx, 6 * sx, z_um[-1] + 6 * sz])
    n = rng.poisson(density * np.prod(hi - lo))
    p = lo + (hi - lo) * rng.random((n, 3))
    moving = rng.random(n) < 0.5
    out = np.empty((frames, nz, nx), np.complex64)
    for t in range(frames):
        c = np.exp(-(p[:, 1] ** 2) / (2 * sx * sx) + 2j * k * p[:, 2])
        hz = np.exp(-((z_um[:, None] - p[None, :, 2]) ** 2) / (2 * sz * sz))
        hx = np.exp(-((p[:, None, 0] - x_um[None, :]) ** 2) / (2 * sx * sx))
        out[t] = (hz * c[None, :]) @ hx
        p = p + rng.normal(0, math.sqrt(2 * d_um2_per_s * dt), p.shape) * moving[:, None]
    return out


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under five minutes
def test_whole_path_from_sequence_files_to_the_statistics_table(tmp_path, capsys):
    """Simulated sequences → ``torchdoct maps`` (3 resolutions) → ``torchdoct compare`` (Kruskal-Wallis)."""
    from torchdoct.measured.io import write_sequence

    rng = np.random.default_rng(5)
    maps_args = []
    for i in range(3):
        seq = write_sequence(
            tmp_path / f"sample{i}.h5",
            _render(rng),
            {
                "axes": "TZX",
                "pitch_um": {"z": 1.5, "x": 2.0},
                "frame_times_s": [0.2048 * t for t in range(8)],
                "system": {
                    "name": "840nm",
                    "wavelength_um": 0.84,
                    "lateral_resolution_um": 4.9,
                    "axial_resolution_um": 3.8,
                    "refractive_index": 1.0,
                },
            },
        )
        out = tmp_path / f"sample{i}_maps.tif"
        assert (
            main(
                [
                    "maps",
                    str(seq),
                    "--resolution",
                    "original",
                    "--resolution",
                    "axial=14",
                    "--resolution",
                    "lateral=18",
                    "--ocds-delay-range-s",
                    "0.2048",
                    "0.6144",
                    "--out",
                    str(out),
                    "--png",
                    "--no-progress",
                ]
            )
            == 0
        )
        maps_args.append(str(out))
    table = tmp_path / "stats.csv"
    assert (
        main(
            ["compare", *maps_args, "--threshold-db", "-30", "--out", str(table), "--plot", str(tmp_path / "stats.png")]
        )
        == 0
    )
    t = pd.read_csv(table)
    assert list(t["test"]) == ["Kruskal-Wallis"] + ["paired t-test"] * 3 + ["Kruskal-Wallis"] + ["paired t-test"] * 3
    assert t["p_value"].between(0, 1).all() and (tmp_path / "stats.png").exists()
    assert "sample0_maps_liv_axial14.png" in {p.name for p in tmp_path.glob("*.png")}


def test_one_sample_gives_the_summary_without_tests(tmp_path, capsys):
    rng = np.random.default_rng(6)
    m = make_maps(rng, ["original", "axial=14"], shift={"axial=14": 2.0})
    res = compare_samples({"only": [(m, region_mask(m))]})
    assert len(res.tests) == 0 and list(res.tests.columns)[:3] == ["metric", "test", "config_a"]
    np.testing.assert_allclose(
        res.values("liv")[0], [np.nanmean(m["liv@original"]), np.nanmean(m["liv@axial=14"])], rtol=1e-6
    )
    text = res.format()
    assert "1 sample" in text and "no tests" in text and "at least 2 samples" in text
    path = tmp_path / "only.npz"
    write_maps(path, m)
    assert (
        main(["compare", str(path), "--per-sample", str(tmp_path / "per.csv"), "--plot", str(tmp_path / "p.png")]) == 0
    )
    out = capsys.readouterr().out
    assert "no tests" in out and (tmp_path / "per.csv").exists() and (tmp_path / "p.png").exists()
    assert len(pd.read_csv(tmp_path / "per.csv")) == 2 * 2  # 2 configurations × 2 metrics
    # a tests table cannot be written from one sample: the error says why and how
    assert main(["compare", str(path), "--out", str(tmp_path / "t.csv")]) == 2
    err = capsys.readouterr().err
    assert "at least 2 samples" in err and not (tmp_path / "t.csv").exists()


def test_maps_without_optics_are_refused_naming_the_fix(tmp_path, capsys):
    rng = np.random.default_rng(7)
    m = make_maps(rng, ["original", "axial=14"], source="cog.tif")
    for c in m.meta["channels"]:
        c["wavelength_um"] = c["lateral_resolution_um"] = c["axial_resolution_um"] = None
    with pytest.raises(ValueError, match="cog.tif.*liv@original.*--wavelength-um"):
        sample_means(m, region_mask(m))
    write_maps(tmp_path / "a.npz", m)
    assert main(["compare", str(tmp_path / "a.npz")]) == 2
    assert "--wavelength-um" in capsys.readouterr().err


def test_truncated_tif_mask_is_refused_quietly(tmp_path, capfd):
    import tifffile

    from torchdoct.cli.data import _load_mask

    good = tmp_path / "m.tif"
    tifffile.imwrite(good, np.ones((8, 64, 64), np.uint8))
    bad = tmp_path / "cut.tif"
    bad.write_bytes(good.read_bytes()[: good.stat().st_size // 3])
    with pytest.raises(ValueError, match="mask cut.tif: not a readable TIFF, truncated or corrupt"):
        _load_mask(str(bad))
    assert capfd.readouterr().err == ""
