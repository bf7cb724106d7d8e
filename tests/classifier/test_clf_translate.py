"""``torchdoct translate``: the per-pixel mixture, the target file, the codes of what cannot be translated,
and the chain on a rendered phantom seen by two systems (slow)."""

from __future__ import annotations

import numpy as np
import pytest

from classifier.translate import STATUS, load_target, mixture_quantiles


def test_one_grid_point_gives_its_own_quantiles():
    rng = np.random.default_rng(0)
    values = rng.normal(3.0, 2.0, size=(1, 4000))
    q = mixture_quantiles(np.array([0.0]), np.array([0.1]), np.array([0.0]), values)
    np.testing.assert_allclose(q[:, 0], np.quantile(values[0], [0.5, 0.158655, 0.841345]), atol=0.02)


def test_a_sharp_posterior_selects_its_grid_point_and_a_broad_one_mixes():
    grid = np.linspace(-2.0, 2.0, 25)
    values = np.repeat((10.0 * grid)[:, None], 50, axis=1) + np.linspace(-0.1, 0.1, 50)[None, :]  # point k ≈ 10·grid[k]
    sharp = mixture_quantiles(np.array([0.5, -1.0]), np.array([1e-3, 1e-3]), grid, values)
    np.testing.assert_allclose(sharp[0], [5.0, -10.0], atol=0.2)
    # a Gaussian posterior of SD s in log10 magnitude, through a linear table: median = 10·mu, 68 % = ±10·s
    broad = mixture_quantiles(np.array([0.0]), np.array([0.5]), grid, values)
    np.testing.assert_allclose(broad[:, 0], [0.0, -5.0, 5.0], atol=0.4)
    # monotone in mu for a monotone table
    many = mixture_quantiles(np.linspace(-1.5, 1.5, 31), np.full(31, 0.3), grid, values)
    assert np.all(np.diff(many[0]) > 0)


def test_target_file_errors_name_the_file_and_the_fix(tmp_path):
    with pytest.raises(FileNotFoundError, match="--to"):
        load_target(tmp_path / "none.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "x"\n[protocol]\nn_frames = 32\nframe_interval_s = 0.2048\n')
    with pytest.raises(ValueError, match=r"\[\[system\]\]"):
        load_target(bad)
    t = load_target("motion-types-two-systems", "1310nm-10um")
    assert [s.name for s in t.systems] == ["1310nm-10um"] and t.scene.noise.snr_db == 30.0
    with pytest.raises(ValueError, match="--to-system"):
        load_target("motion-types-two-systems", "nope")
    assert set(STATUS) == {0, 1, 2, 3}


@pytest.fixture(scope="module")
def two_systems(tmp_path_factory):
    """The motion-types phantom rendered on both systems, with the 840-nm signature maps."""
    from torchdoct.cli import main

    d = tmp_path_factory.mktemp("tr")
    assert (
        main(
            [
                "render",
                "motion-types-two-systems",
                "--out",
                str(d / "mt2.npz"),
                "--no-preview",
                "--no-progress",
                "--threads",
                "1",
            ]
        )
        == 0
    )
    assert (
        main(
            [
                "maps",
                str(d / "mt2-840nm-high.npz"),
                "--resolution",
                "original",
                "--resolution",
                "axial=14",
                "--resolution",
                "lateral=18",
                "--signature",
                "--out",
                str(d / "src.npz"),
                "--no-progress",
                "--threads",
                "1",
            ]
        )
        == 0
    )
    return d


@pytest.mark.slow  # an end-to-end command run; the default suite covers its parts
def test_translate_command_writes_values_intervals_and_codes(two_systems, capsys):
    from torchdoct.cli import main
    from torchdoct.measured.mapsfile import read_maps

    d = two_systems
    out = d / "tr.npz"
    assert (
        main(
            [
                "translate",
                str(d / "src.npz"),
                "--to",
                "motion-types-two-systems",
                "--to-system",
                "1310nm-10um",
                "--out",
                str(out),
                "--trials",
                "16",
                "--no-progress",
            ]
        )
        == 0
    )
    m = read_maps(out)
    code = m["translation@1310nm-10um"]
    liv, lo, hi = (m[f"liv{s}@1310nm-10um"] for s in ("", "_lower_68", "_upper_68"))
    ok = code == 0
    assert ok.any() and (code == 2).any()  # the static tissue is indeterminate
    assert np.all(np.isfinite(liv[ok])) and np.all(np.isnan(liv[~ok]))
    assert np.all(lo[ok] <= liv[ok] + 1e-6) and np.all(liv[ok] <= hi[ok] + 1e-6)
    assert m.meta["system"]["wavelength_um"] == 1.31 and len(m.meta["frame_times_s"]) == 32
    # the same command again: refused without --force, nothing changed; an LIV/OCDS model is refused
    before = out.read_bytes()
    assert main(["translate", str(d / "src.npz"), "--to", "motion-types-two-systems", "--out", str(out)]) == 2
    assert out.read_bytes() == before
    assert (
        main(
            [
                "translate",
                str(d / "src.npz"),
                "--to",
                "motion-types-two-systems",
                "--model",
                "single-acquisition-bscan",
                "--out",
                str(d / "liv.npz"),
            ]
        )
        == 2
    )
    assert "magnitude" in capsys.readouterr().err and not (d / "liv.npz").exists()


@pytest.mark.slow
def test_translated_maps_match_the_directly_rendered_ones(tmp_path):
    """840 nm → 1310 nm on one rendering: per motion type the median over its three regions of
    |median translated − median direct| / SD(direct) ≤ 1/2 and the 68 % intervals cover 0.58-0.78 of the
    direct pixels. Tolerances: a region's inner pixels (~160) hold ~27 independent speckle grains
    (~6 pixels each), so a region median's SE is ≈ 1.25/√27 ≈ 0.24 SD: the goal 1/3 + one SE of the
    median of three; a coverage over the ~1200 translated pixels of all regions (~200 grains) has SE
    ≈ 0.033: 0.68 ± 3 SE."""
    from research.translation import chain, score, summarize

    s = summarize(score(chain(tmp_path, 2026, 128)))
    for motion in ("diffusion", "ballistic", "flow"):
        for m in ("liv", "ocds"):
            assert s[motion][m]["median_abs_bias_over_sd"] <= 0.5, (motion, m, s[motion][m])
    for m in ("liv", "ocds"):
        assert 0.58 <= s["all"][m]["coverage_68"] <= 0.78, (m, s["all"][m])
