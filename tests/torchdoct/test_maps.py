"""DOCT maps (torchdoct.measured.maps) and the ``torchdoct maps`` / ``torchdoct bench maps`` commands."""

from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest
import tifffile
import torch
from scipy import ndimage, optimize

from torchdoct.cli import main
from torchdoct.measured.io import BlockRaster, SequenceData, read_maps, read_sequence, validate_meta, write_sequence
from torchdoct.measured.maps import (
    FLAG_RGB,
    box_smooth_zx,
    compute_maps,
    fit_saturation,
    liv_curve,
    ocds_map,
    png_name,
    pseudo_color,
)
from torchdoct.measured.resolution import reduce_resolution
from torchdoct.sim import metrics

SYSTEM = {
    "name": "840nm",
    "wavelength_um": 0.84,
    "lateral_resolution_um": 4.9,
    "axial_resolution_um": 3.8,
    "refractive_index": 1.0,
}
DT = 0.2048


def speckle(shape, *, corr=0.8, seed=0, dtype=np.complex64) -> np.ndarray:
    """Complex Gaussian frames [T, ...] with lag-1 field correlation ``corr`` (AR(1) in time)."""
    rng = np.random.default_rng(seed)

    def noise():
        return rng.standard_normal(shape[1:]) + 1j * rng.standard_normal(shape[1:])

    e = noise()
    out = []
    for _ in range(shape[0]):
        e = corr * e + math.sqrt(1 - corr * corr) * noise()
        out.append(e)
    return np.array(out).astype(dtype)


def make_seq(data, *, volume=False, raster=None, times=None) -> SequenceData:
    t = times if times is not None else [DT * i for i in range(data.shape[0])]
    meta = {
        "axes": "TYZX" if volume else "TZX",
        "pitch_um": {"z": 1.5, "x": 2.0, **({"y": 3.0} if volume else {})},
        "frame_times_s": t,
        "system": SYSTEM,
    }
    if raster is not None:
        meta["block_raster"] = raster.to_dict()
    return SequenceData(data=data, meta=validate_meta(meta, data.shape), source="test.npy")


# ----------------------------------------------------------------------------------------------------------
# per-pixel metrics agree with torchdoct.sim.metrics
# ----------------------------------------------------------------------------------------------------------
def test_liv_ocds_mean_db_match_metrics():
    data = speckle((12, 9, 11), dtype=np.complex128)
    data[:, 0, 0] = 1.0 + 1.0j  # constant pixel: LIV 0, OCDS 0 (rho = 1 at every lag)
    seq = make_seq(data)
    m = compute_maps(seq, ["original"], ocds_delay_range_s=(0.2048, 0.8192))
    i = torch.from_numpy(np.abs(data) ** 2).movedim(0, -1)
    np.testing.assert_allclose(m["liv@original"], metrics.liv(i).numpy(), rtol=1e-5, atol=1e-5)
    ref = metrics.ocds(i, seq.frame_times_s, delay_range_s=(0.2048, 0.8192)).numpy()
    np.testing.assert_allclose(m["ocds@original"], ref, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(m["mean_db@original"], 10 * np.log10((np.abs(data) ** 2).mean(0)), rtol=1e-5)
    assert m["liv@original"][0, 0] == 0 and m["ocds@original"][0, 0] == 0
    assert m.maps.dtype == np.float32 and m.meta["axes"] == "CZX"


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("scale,estimator", [("db", "pearson"), ("linear", "pearson"), ("db", "biased")])
def test_ocds_of_the_lags_in_range_equals_the_slope_of_every_lag(scale, estimator, dtype):
    """The one OCDS (maps and simulator) correlates only the lags in the delay range; the slope over
    every lag's correlation (lag_correlations → ocds_from_correlations) is the same number, bit for bit."""
    g = torch.Generator().manual_seed(5)
    i = (torch.rand(300, 16, generator=g, dtype=torch.float64) + 0.01).to(dtype)
    i[:3] = 1.0  # constant
    times = [DT * k for k in range(16)]
    got = ocds_map(i, times, delay_range_s=(0.2048, 1.2288), scale=scale, estimator=estimator)
    s = metrics.to_db(i) if scale == "db" else i
    delays, rho = metrics.lag_correlations(s, times, estimator=estimator)
    ref = metrics.ocds_from_correlations(rho, delays, (0.2048, 1.2288))
    assert torch.equal(got, ref)
    assert torch.equal(metrics.ocds(i, times, scale=scale, estimator=estimator), got)  # the maps' OCDS is this one
    nonuniform = [0.0, 0.1, 0.3, 0.4, 0.6, 0.7, 0.9, 1.0, 1.2, 1.3, 1.5, 1.6, 1.8, 1.9, 2.1, 2.2]
    d, r = metrics.lag_correlations(metrics.to_db(i), nonuniform)
    assert torch.equal(
        ocds_map(i, nonuniform, delay_range_s=(0.1, 0.6)), metrics.ocds_from_correlations(r, d, (0.1, 0.6))
    )
    with pytest.raises(ValueError, match="fewer than 2 delays"):
        ocds_map(i, times, delay_range_s=(0.3, 0.35))


def test_zero_intensity_pixels_are_nan():
    data = speckle((8, 4, 5))
    data[3, 1, 1] = 0  # one empty frame
    data[:, 2, 2] = 0  # always empty
    m = compute_maps(
        make_seq(data),
        ["original"],
        metrics=["liv", "ocds", "mean_db", "aliv", "swiftness"],
        ocds_delay_range_s=(0.2048, 0.6144),
    )
    for name in ("liv", "ocds", "aliv", "swiftness"):
        assert np.isnan(m[f"{name}@original"][1, 1]) and np.isnan(m[f"{name}@original"][2, 2])
    assert np.isfinite(m["mean_db@original"][1, 1]) and np.isnan(m["mean_db@original"][2, 2])
    assert np.isfinite(m.maps[:, 0, 0]).all()


# ----------------------------------------------------------------------------------------------------------
# LIV curve, smoothing and the saturation fit (aLIV, Swiftness)
# ----------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("times", [[DT * k for k in range(10)], [0.0, 0.1, 0.3, 0.4, 0.6, 0.7, 0.9, 1.0]])
def test_liv_curve_brute_force(times):
    g = torch.Generator().manual_seed(1)
    i = torch.rand(7, len(times), generator=g, dtype=torch.float64) + 0.05
    w, c = liv_curve(i, times)
    db = 10 * np.log10(i.numpy())
    t = np.asarray(times) - times[0]
    spans = sorted({round(t[b] - t[a], 9) for a in range(len(t)) for b in range(a + 1, len(t))})
    np.testing.assert_allclose(w.numpy(), spans, atol=1e-9)
    for k, span in enumerate(spans):
        runs = [(a, b) for a in range(len(t)) for b in range(a + 1, len(t)) if abs(t[b] - t[a] - span) < 1e-9]
        ref = np.mean([np.var(db[:, a : b + 1], axis=1) for a, b in runs], axis=0)
        np.testing.assert_allclose(c[:, k].numpy(), ref, rtol=1e-9, atol=1e-9)
    w2, c2 = liv_curve(i, times, max_window_s=0.45)
    assert float(w2.max()) <= 0.45 and c2.shape[-1] == int((w <= 0.45 + 1e-12).sum())


def test_box_smoothing_is_cv2_blur():
    x = torch.rand(2, 6, 7, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    ref = ndimage.uniform_filter(x.numpy(), size=(1, 3, 3, 1), mode="mirror")  # mirror = reflect-101
    np.testing.assert_allclose(box_smooth_zx(x).numpy(), ref, rtol=1e-12, atol=1e-12)


def _curve_fit(t, y):
    def model(x, a, tau):
        return a * (1 - np.exp(-x / tau))

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        p, _ = optimize.curve_fit(
            model,
            t,
            y,
            p0=(20.0, 1.0),
            bounds=([0, 0], [np.inf, np.inf]),
            ftol=1e-14,
            xtol=1e-14,
            gtol=1e-14,
            max_nfev=10000,
        )
    return p


def test_fit_matches_scipy_curve_fit():
    rng = np.random.default_rng(4)
    t = DT * np.arange(1, 32)
    curves = []
    for a, tau in [(25.0, 0.4), (8.0, 2.0), (30.0, 0.1), (3.0, 6.0), (15.0, 1.0)]:
        curves.append(a * (1 - np.exp(-t / tau)) + rng.normal(0, 0.3, t.size))
    # noise-free sample-size "saturation" of independent frames: σ²·m/(m+1) (physics.md §3 note i)
    curves.append(31.03 * np.arange(1, 32) / np.arange(2, 33))
    y = torch.tensor(np.array(curves))
    a, tau = fit_saturation(torch.tensor(t), y)
    for k in range(len(curves)):
        pa, ptau = _curve_fit(t, curves[k])
        assert float(a[k]) == pytest.approx(pa, rel=1e-4)
        assert float(tau[k]) == pytest.approx(ptau, rel=1e-4)
    assert float(a[-1]) == pytest.approx(29.1, abs=0.05) and 1 / float(tau[-1]) == pytest.approx(2.8, abs=0.05)


def test_fit_on_map_pixels_matches_curve_fit():
    data = speckle((16, 6, 7), corr=0.85, seed=3, dtype=np.complex128)
    m = compute_maps(make_seq(data), ["original"], metrics=["aliv", "swiftness"], aliv_smoothing=False)
    i = torch.from_numpy(np.abs(data) ** 2).movedim(0, -1)
    w, c = liv_curve(i, [DT * k for k in range(16)])
    for z, x in [(0, 0), (2, 3), (5, 6), (4, 1)]:
        pa, ptau = _curve_fit(w.numpy(), c[z, x].numpy())
        assert m["aliv@original"][z, x] == pytest.approx(pa, rel=1e-4)
        assert m["swiftness@original"][z, x] == pytest.approx(1 / ptau, rel=1e-4)
    flat = fit_saturation(w, torch.zeros(2, w.numel(), dtype=torch.float64))[0]
    assert torch.equal(flat, torch.zeros(2, dtype=torch.float64))


# ----------------------------------------------------------------------------------------------------------
# compute_maps: resolutions, slabs, volumes, block raster, intensity input
# ----------------------------------------------------------------------------------------------------------
@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_maps_at_reduced_resolution_and_slab_invariance():
    data = speckle((10, 60, 20), seed=6, dtype=np.complex128)
    seq = make_seq(data)
    kw = dict(metrics=["liv", "ocds", "mean_db", "aliv", "swiftness"], ocds_delay_range_s=(0.2048, 0.6144))
    big = compute_maps(seq, ["original", "axial=14", "lateral=18", "axial=14,lateral=18"], **kw)
    small = compute_maps(
        seq,
        ["original", "axial=14", "lateral=18", "axial=14,lateral=18"],
        slab_elements=10 * 20 * 7,
        chunk_pixels=37,
        **kw,
    )
    # slabs see the axial window truncated at 5σ' (tail e^-12.5 ≈ 4e-6 of the field); dB metrics of dark
    # pixels amplify that a little
    np.testing.assert_allclose(small.maps, big.maps, rtol=1e-4, atol=1e-4)
    np.testing.assert_array_equal(small.maps[:3], big.maps[:3])  # no reduction: LIV, OCDS, mean dB exact
    np.testing.assert_allclose(small.maps[3:5], big.maps[3:5], rtol=1e-5)  # fit: rounding of chunked sums
    red = reduce_resolution(data, pitch_um=seq.pitch_um, system=SYSTEM, axial_resolution_um=14.0)
    i = torch.from_numpy(np.abs(red) ** 2).movedim(0, -1)
    np.testing.assert_allclose(big["liv@axial=14"], metrics.liv(i).numpy(), rtol=1e-5, atol=1e-5)
    infos = {c["name"]: c for c in big.meta["channels"]}
    assert infos["ocds@axial=14,lateral=18"]["lateral_resolution_um"] == 18.0
    assert infos["ocds@axial=14,lateral=18"]["axial_resolution_um"] == 14.0
    assert infos["liv@lateral=18"]["axial_resolution_um"] == 3.8 and infos["liv@original"]["unit"] == "dB^2"
    assert infos["swiftness@original"]["unit"] == "1/s" and infos["mean_db@original"]["unit"] == "dB"
    assert big.channels[0] == "liv@original" and len(big.channels) == 24  # 5 metrics + aliv_fit, 4 resolutions
    assert big.meta["reduction"]["lateral_axes"] == "X" and big.meta["source"] == "test.npy"


def test_volume_with_block_raster_drops_boundary_bscans():
    raster = BlockRaster(n_blocks=2, n_repeats=8, bscans_per_block=4, drop_boundary=1)
    nz = 10  # 10 × 1.5 µm = 15 µm deep: the field of view holds the axial=14 target below
    data = speckle((8, 8, nz, 6), seed=7)
    seq = make_seq(data, volume=True, raster=raster)
    m = compute_maps(seq, ["original", "lateral=9.8"], ocds_delay_range_s=(0.2048, 0.6144))
    assert m.maps.shape == (6, 6, nz, 6) and m.meta["axes"] == "CYZX"
    assert m.meta["y_indices"] == [0, 1, 2, 5, 6, 7] and m.meta["reduction"]["lateral_axes"] == "YX"
    full = compute_maps(seq, ["original", "lateral=9.8"], ocds_delay_range_s=(0.2048, 0.6144), drop_boundary=False)
    np.testing.assert_array_equal(m.maps, full.maps[:, [0, 1, 2, 5, 6, 7]])
    # chunking over B-scans (axial only) or depth slabs (axial + lateral) does not change the maps
    res = ["axial=14", "axial=14,lateral=9.8"]
    kw = dict(ocds_delay_range_s=(0.2048, 0.6144), metrics=["liv", "ocds", "mean_db", "aliv"])
    one = compute_maps(seq, res, **kw)
    chunked = compute_maps(seq, res, slab_elements=8 * 2 * nz * 6, **kw)
    np.testing.assert_allclose(chunked.maps, one.maps, rtol=1e-4, atol=1e-4)
    # the original resolution with the aLIV smoothing is cut into whole B-scans: the same maps up to the
    # float32 rounding of the per-pixel sums (torch orders a reduction by the batch's shape)
    orig = compute_maps(seq, ["original"], **kw)
    for size in (8 * 1 * nz * 6, 8 * 3 * nz * 6):
        np.testing.assert_allclose(
            compute_maps(seq, ["original"], slab_elements=size, **kw).maps, orig.maps, rtol=1e-5, atol=1e-5
        )


def test_slab_cut_follows_what_the_stages_need():
    """The slab loop cuts the axis its stages need least; halos of stages in sequence add up."""
    from torchdoct.measured.bulkphase import CORRECTION_AXIS_NEEDS
    from torchdoct.measured.mapmetrics import SMOOTHING_AXIS_NEEDS
    from torchdoct.measured.resolution import reduction_axis_needs
    from torchdoct.measured.slabs import slab_cut

    axial = reduction_axis_needs("TYZX", lateral=False, axial_sigma_px=2.0)
    lateral = reduction_axis_needs("TYZX", lateral=True, axial_sigma_px=0.0)
    both = reduction_axis_needs("TZX", lateral=True, axial_sigma_px=2.0)
    assert axial == {"Z": 11} and lateral == {"Y": None, "X": None} and both == {"Z": 11, "X": None}
    assert reduction_axis_needs("TZX", lateral=False, axial_sigma_px=2.0, edge_mode="wrap") == {"Z": None}
    assert slab_cut("TZX", []) == ("Z", 0, 0)  # per-pixel work: depth slabs
    assert slab_cut("TYZX", [CORRECTION_AXIS_NEEDS]) == ("Z", 0, 0)  # the correction cuts anywhere
    assert slab_cut("TYZX", [axial]) == ("Y", 0, 0)  # an axial window in a volume: whole B-scans, no halo
    assert slab_cut("TYZX", [lateral]) == ("Z", 0, 0)
    assert slab_cut("TYZX", [lateral], [SMOOTHING_AXIS_NEEDS]) == ("Z", 1, 1)
    assert slab_cut("TZX", [both], [SMOOTHING_AXIS_NEEDS]) == ("Z", 12, 1)  # the window's halo + the smoothing's
    assert slab_cut("TYZX", [], [SMOOTHING_AXIS_NEEDS]) == ("Y", 0, 0)  # smoothing is per B-scan
    wrap = reduction_axis_needs("TZX", lateral=True, axial_sigma_px=2.0, edge_mode="wrap")
    assert slab_cut("TZX", [wrap]) == ("Z", None, 0)  # nothing may be cut: one slab


def test_intensity_input_allows_only_original(tmp_path):
    inten = np.abs(speckle((8, 10, 6), seed=8)) ** 2  # 10 × 1.5 µm deep: holds the axial=14 target
    tifffile.imwrite(tmp_path / "cog.tif", inten.astype(np.float32))
    seq = read_sequence(tmp_path / "cog.tif", pitch_um="z=1.5,x=2", frame_interval_s=DT, system=SYSTEM)
    m = compute_maps(seq, ["original"], ocds_delay_range_s=(0.2048, 0.6144))
    i = torch.from_numpy(inten.astype(np.float32)).movedim(0, -1)
    np.testing.assert_allclose(m["liv@original"], metrics.liv(i).numpy(), rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="intensity only.*needs the complex field"):
        compute_maps(seq, ["original", "axial=14"])


def test_bad_requests():
    seq = make_seq(speckle((8, 5, 6)))
    with pytest.raises(ValueError, match="unknown metrics"):
        compute_maps(seq, metrics=["liv", "speed"])
    with pytest.raises(ValueError, match="finer than the original"):
        compute_maps(seq, ["axial=2"])
    with pytest.raises(ValueError, match="requested twice"):
        compute_maps(seq, ["original", "original"])
    with pytest.raises(ValueError, match="fewer than 2 delays"):
        compute_maps(seq, ["original"], ocds_delay_range_s=(0.2048, 0.25))
    bare = SequenceData(data=seq.data, meta={k: v for k, v in seq.meta.items() if k != "system"})
    with pytest.raises(ValueError, match="--wavelength-um"):
        compute_maps(bare, ["original", "axial=14"])
    assert (
        compute_maps(bare, metrics=["liv"]).channel_info("liv@original")["wavelength_um"] is None
    )  # original: optics not needed


# ----------------------------------------------------------------------------------------------------------
# pseudo colour
# ----------------------------------------------------------------------------------------------------------
def test_pseudo_color_takes_the_perceptual_map_scaled_by_brightness():
    import matplotlib

    from torchdoct.figures import CONTINUOUS_CMAP

    cm = matplotlib.colormaps[CONTINUOUS_CMAP]
    ends = [tuple(int(round(c * 255)) for c in cm(x)[:3]) for x in (0.0, 1.0)]
    v = np.array([[0.0, 10.0, 5.0, np.nan]])
    db = np.array([[40.0, 40.0, 20.0, 40.0]])
    rgb = pseudo_color(v, db, value_range=(0, 10), db_range=(20, 40))
    assert rgb.dtype == np.uint8 and rgb.shape == (1, 4, 3)
    assert tuple(rgb[0, 0]) == ends[0]  # low value: the map's low end, full brightness
    assert tuple(rgb[0, 1]) == ends[1]  # high value: the map's high end
    assert tuple(rgb[0, 2]) == (0, 0, 0)  # at the dB floor: black
    assert tuple(rgb[0, 3]) == (153, 153, 153)  # NaN: grey
    assert tuple(pseudo_color(np.array([[20.0]]), None, value_range=(0, 10))[0, 0]) == ends[1]  # clipped
    with pytest.raises(ValueError, match="hi > lo"):
        pseudo_color(v, db, value_range=(1, 1), db_range=(0, 1))
    assert png_name("out/maps.tif", "liv@axial=14,lateral=9.8").name == "maps_liv_axial14-lateral9p8.png"


# ----------------------------------------------------------------------------------------------------------
# command line
# ----------------------------------------------------------------------------------------------------------
@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under five minutes
def test_cli_maps_end_to_end(tmp_path, capsys):
    data = speckle((10, 24, 16), seed=9)
    seq_path = write_sequence(
        tmp_path / "seq.npz",
        data,
        {
            "axes": "TZX",
            "pitch_um": {"z": 1.5, "x": 2.0},
            "frame_times_s": [DT * k for k in range(10)],
            "system": SYSTEM,
        },
    )
    out_tif, out_npz = tmp_path / "maps.tif", tmp_path / "maps.npz"
    argv = [
        "maps",
        str(seq_path),
        "--resolution",
        "original",
        "--resolution",
        "axial=14",
        "--resolution",
        "lateral=18",
        "--aliv",
        "--ocds-delay-range-s",
        "0.2048",
        "0.6144",
        "--out",
        str(out_tif),
        "--out",
        str(out_npz),
        "--png",
        "--range",
        "liv=0,30",
        "--no-progress",
    ]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "swiftness@lateral=18" in text and f"wrote {out_npz}" in text
    assert "aLIV fit on a τ bound at axial=14:" in text
    a, b = read_maps(out_tif), read_maps(out_npz)
    np.testing.assert_array_equal(a.maps, b.maps)
    assert a.maps.shape == (18, 24, 16) and a.meta == b.meta  # 5 metrics + the aLIV fit flags, 3 resolutions
    assert a.meta["source"] == "seq.npz" and a.meta["system"]["wavelength_um"] == 0.84
    assert a.meta["frame_times_s"] == pytest.approx([DT * k for k in range(10)])
    assert a.meta["ocds_delay_range_s"] == [0.2048, 0.6144]
    pngs = sorted(p.name for p in tmp_path.glob("*.png"))
    assert len(pngs) == 15 and "maps_ocds_axial14.png" in pngs
    direct = compute_maps(
        read_sequence(seq_path),
        ["original", "axial=14", "lateral=18"],
        metrics=["liv", "ocds", "mean_db", "aliv", "swiftness"],
        ocds_delay_range_s=(0.2048, 0.6144),
    )
    np.testing.assert_array_equal(a.maps, direct.maps)
    # never overwrites without --force, and checks before working
    assert main(argv) == 2
    assert "exists; pass --force" in capsys.readouterr().err
    assert main(argv + ["--force"]) == 0


def test_cli_maps_errors(tmp_path, capsys):
    np.save(tmp_path / "raw.npy", speckle((8, 5, 6)))
    assert main(["maps", str(tmp_path / "raw.npy"), "--out", str(tmp_path / "m.npz"), "--no-progress"]) == 2
    assert "--axes" in capsys.readouterr().err
    argv = [
        "maps",
        str(tmp_path / "raw.npy"),
        "--axes",
        "TZX",
        "--pitch-um",
        "z=1.5,x=2",
        "--frame-interval-s",
        "0.2048",
        "--out",
        str(tmp_path / "m.npz"),
        "--no-progress",
        "--ocds-delay-range-s",
        "0.2048",
        "0.6144",
    ]
    assert main(argv + ["--resolution", "axial=14"]) == 2
    assert "--wavelength-um" in capsys.readouterr().err
    sys_args = ["--wavelength-um", "0.84", "--lateral-resolution-um", "4.9", "--axial-resolution-um", "3.8"]
    assert main(argv + sys_args + ["--resolution", "axial=3"]) == 2
    assert "finer than the original" in capsys.readouterr().err
    assert main(argv + sys_args) == 0
    assert read_maps(tmp_path / "m.npz").meta["system"]["lateral_resolution_um"] == 4.9
    inten = np.abs(speckle((8, 5, 10))) ** 2  # 10 × 2 µm wide: holds the lateral=18 target
    tifffile.imwrite(tmp_path / "i.tif", inten.astype(np.float32))
    assert (
        main(
            [
                "maps",
                str(tmp_path / "i.tif"),
                "--pitch-um",
                "z=1.5,x=2",
                "--frame-interval-s",
                "0.2048",
                "--resolution",
                "lateral=18",
                "--out",
                str(tmp_path / "i.npz"),
                "--no-progress",
            ]
            + sys_args
        )
        == 2
    )
    assert "intensity only" in capsys.readouterr().err
    # without the optics the intensity-only refusal comes first, not a request for optics that cannot help
    assert (
        main(
            [
                "maps",
                str(tmp_path / "i.tif"),
                "--frame-interval-s",
                "0.2048",
                "--resolution",
                "lateral=18",
                "--out",
                str(tmp_path / "i.npz"),
                "--no-progress",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "i.tif holds intensity only" in err and "--wavelength-um" not in err and "pitch" not in err
    assert not (tmp_path / "i.npz").exists()


def test_cli_block_raster_volume(tmp_path, capsys):
    raster = BlockRaster(n_blocks=2, n_repeats=8, bscans_per_block=4)
    vol = speckle((8, 8, 4, 5), seed=10)
    flat = np.concatenate([vol[:, 4 * b : 4 * (b + 1)].reshape(-1, 4, 5) for b in range(2)])  # acquisition order
    np.save(tmp_path / "flat.npy", flat)
    assert (
        main(
            [
                "maps",
                str(tmp_path / "flat.npy"),
                "--axes",
                "TZX",
                "--pitch-um",
                "z=1.5,x=2,y=8",
                "--frame-interval-s",
                "0.2048",
                "--block-raster",
                "2:8:4",
                "--wavelength-um",
                "0.84",
                "--lateral-resolution-um",
                "4.9",
                "--axial-resolution-um",
                "3.8",
                "--ocds-delay-range-s",
                "0.2048",
                "0.6144",
                "--out",
                str(tmp_path / "v.npz"),
                "--no-progress",
                "--png",
            ]
        )
        == 0
    )
    m = read_maps(tmp_path / "v.npz")
    assert m.maps.shape == (3, 6, 4, 5) and m.meta["block_raster"] == raster.to_dict()
    direct = compute_maps(make_seq(vol, volume=True, raster=raster), ["original"], ocds_delay_range_s=(0.2048, 0.6144))
    np.testing.assert_allclose(m.maps, direct.maps, rtol=1e-6)


def test_cli_bench_maps_runs(tmp_path, capsys):
    out = tmp_path / "bench.json"
    assert main(["bench", "maps", "--frames", "12", "--size", "16", "12", "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["shape"] == [12, 16, 12] and set(res["seconds_per_resolution"]) == {"original", "axial=14", "lateral=18"}
    assert main(["bench", "maps", "--frames", "12", "--size", "16", "12", "--out", str(out)]) == 2


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_cli_bench_maps_channels_compares_every_channel_set_to_the_signature_maps(tmp_path):
    """One run times every channel set (idle and beside a busy process) and divides by the signature set's."""
    out = tmp_path / "channels.json"
    argv = ["bench", "maps-channels", "--frames", "12", "--size", "20", "16", "--repeats", "1", "--load"]
    assert main(argv + ["--out", str(out), "--no-progress"]) == 0
    res = json.loads(out.read_text())
    assert res["shape"] == [12, 20, 16] and res["modes"] == ["idle", "loaded"]
    assert list(res["sets"]) == [
        "plain",
        "signature",
        "signature+speckle",
        "signature+speckle+doppler",
        "signature+speckle+doppler+dynamic",
    ]
    for mode in res["modes"]:
        base = res["sets"]["signature"][f"seconds_{mode}"]
        assert res["sets"]["signature"][f"ratio_to_signature_{mode}"] == 1.0
        for rec in res["sets"].values():
            assert rec[f"seconds_{mode}"] > 0
            assert rec[f"ratio_to_signature_{mode}"] == rec[f"seconds_{mode}"] / base
            assert set(rec[f"seconds_per_resolution_{mode}"]) == {"original", "axial=14", "lateral=18"}
    assert main(argv + ["--out", str(out), "--no-progress"]) == 2  # nothing overwritten unasked


# ----------------------------------------------------------------------------------------------------------
# edge cases (issue 15): undefined neighbours, fits on a τ bound, reduction leakage, figures, bad inputs
# ----------------------------------------------------------------------------------------------------------
def _mean_over_defined(c: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """3×3 mean (border reflect-101, as cv2.blur) of curves ``c [Z, X, W]`` over the defined pixels only."""
    w = valid.astype(np.float64)
    num = ndimage.uniform_filter(c * w[..., None], size=(3, 3, 1), mode="mirror")
    den = ndimage.uniform_filter(w, size=3, mode="mirror")
    with np.errstate(invalid="ignore", divide="ignore"):  # no defined neighbour: NaN
        return num / den[..., None]


def test_undefined_pixels_do_not_enter_the_aliv_smoothing():
    """Zeroing a patch leaves its neighbours' aLIV/Swiftness equal to the 3×3 mean over defined neighbours."""
    data = speckle((12, 14, 13), corr=0.85, seed=11, dtype=np.complex128)
    valid = np.ones((14, 13), bool)
    valid[4:9, 5:10] = False
    zeroed = data.copy()
    zeroed[:, ~valid] = 0
    m = compute_maps(make_seq(zeroed), ["original"], metrics=["aliv", "swiftness"])
    i = torch.from_numpy(np.abs(data) ** 2).movedim(0, -1)
    w, c = liv_curve(i, [DT * k for k in range(12)])
    a, tau = fit_saturation(w, torch.from_numpy(_mean_over_defined(c.numpy(), valid)))
    np.testing.assert_allclose(m["aliv@original"][valid], a.numpy()[valid], rtol=2e-5)
    np.testing.assert_allclose(m["swiftness@original"][valid], 1 / tau.numpy()[valid], rtol=2e-5)
    assert np.isnan(m["aliv@original"][~valid]).all() and np.isnan(m["swiftness@original"][~valid]).all()
    # the pixels away from the patch do not change at all
    far = ndimage.binary_dilation(~valid, structure=np.ones((3, 3), bool))
    ref = compute_maps(make_seq(data), ["original"], metrics=["aliv", "swiftness"])
    np.testing.assert_array_equal(m.maps[:2][:, ~far], ref.maps[:2][:, ~far])


def test_fits_on_a_tau_bound_are_flagged():
    t = np.arange(16)
    data = speckle((16, 4, 5), corr=0.85, seed=12, dtype=np.complex128)
    data[:, 0, 0] = np.sqrt(10 ** (0.3 * t / 10))  # dB ramp: LIV curve grows as T_w², τ → upper bound
    data[:, 0, 1] = np.sqrt(10 ** (np.where(t % 2 == 0, 1.0, -1.0) / 10))  # alternating: flat curve, τ → lower bound
    data[:, 3, 4] = 0  # undefined
    m = compute_maps(make_seq(data), ["original"], metrics=["aliv", "swiftness"], aliv_smoothing=False)
    assert m.channels == ("aliv@original", "swiftness@original", "aliv_fit@original")
    code = m["aliv_fit@original"]
    assert code[0, 0] == 2 and code[0, 1] == 1 and np.isnan(code[3, 4])
    inside = np.ones((4, 5), bool)
    inside[0, :2] = inside[3, 4] = False
    assert (code[inside] == 0).all()
    assert m.meta["aliv"]["flagged_pixels"] == {"original": {"tau_at_lower_bound": 1, "tau_at_upper_bound": 1}}
    assert "bound" in m.meta["aliv"]["flag"] and m.channel_info("aliv_fit@original")["unit"] == "code"
    # flagged pixels are shown in their own colour, distinct from every hue of the scale and from NaN grey
    rgb = pseudo_color(m["aliv@original"], None, value_range=(0, 30), flagged=code > 0)
    assert tuple(rgb[0, 0]) == tuple(rgb[0, 1]) == FLAG_RGB
    assert all(tuple(rgb[z, x]) != FLAG_RGB for z, x in zip(*np.nonzero(inside)))


def test_empty_pixels_stay_undefined_after_an_axial_reduction():
    """FFT leakage into exactly empty rows is masked by the documented floor; real blur is kept."""
    data = speckle((8, 120, 6), seed=13)
    data[:, 20:] = 0  # rows 20… exactly empty (a 150 µm empty region below the sample)
    m = compute_maps(make_seq(data), ["original", "axial=14"], ocds_delay_range_s=(0.2048, 0.6144))
    for metric in ("liv", "ocds", "mean_db"):
        assert np.isnan(m[f"{metric}@original"][20:]).all()
        v = m[f"{metric}@axial=14"]
        assert np.isfinite(v[:24]).all(), metric  # the reduced PSF reaches a few rows into the empty region
        assert np.isnan(v[70:]).all(), metric  # > 9 σ'_z away: only round-off remains
    rule = m.meta["empty_rule"]
    assert rule["floor_relative_db"] == pytest.approx(10 * np.log10((64 * np.finfo(np.float32).eps) ** 2))
    assert "max" in rule["rule"] and "I = 0" in rule["rule"]


def test_map_figure_axes_colour_bar_and_title(tmp_path):
    from torchdoct import figures
    from torchdoct.measured.maps import map_figure

    data = speckle((8, 12, 10), seed=14)
    m = compute_maps(make_seq(data), ["original", "axial=14"], ocds_delay_range_s=(0.2048, 0.6144))
    fig = map_figure(m, "liv@axial=14", value_range=(0.0, 30.0), db_range=(-10.0, 10.0))
    img_ax = fig.axes[0]
    assert img_ax.get_xlabel() == figures.X_LABEL == "x (µm)" and img_ax.get_ylabel() == figures.Z_LABEL
    assert img_ax.images[0].get_extent() == pytest.approx([0.0, 10 * 2.0, 12 * 1.5, 0.0])
    title = img_ax.get_title()
    assert "LIV" in title and "axial=14" in title and "lateral 4.9 µm" in title and "axial 14 µm" in title
    cbar_label = fig.axes[1].get_ylabel()
    assert "dB²" in cbar_label and "0" in cbar_label and "30" in cbar_label
    import matplotlib.pyplot as plt

    plt.close(fig)
    paths = write_pngs_for(m, tmp_path)
    h, w = matplotlib_image_shape(paths[0])
    assert w > 400 and h > 250  # a figure with axes, not the bare 12×10 map


def write_pngs_for(m, tmp_path):
    from torchdoct.measured.maps import write_pngs

    return write_pngs(m, tmp_path / "maps.npz")


def matplotlib_image_shape(path):
    import matplotlib.image

    return matplotlib.image.imread(path).shape[:2]


def test_one_axes_convention_for_render_preview_maps_and_overlay(tmp_path, monkeypatch):
    import matplotlib.figure

    from torchdoct import figures
    from torchdoct.image.phantom import load_phantom
    from torchdoct.image.render import preview_figure, render

    res = render(load_phantom("spheroid", grid={"n_z": 24, "n_x": 20, "pitch_x_um": 2.0, "pitch_z_um": 2.0}), seed=1)
    fig = preview_figure(res, 0)
    images = [ax for ax in fig.axes if ax.images]
    assert len(images) == 3
    for ax in images:
        assert ax.get_xlabel() == figures.X_LABEL and ax.get_ylabel() == figures.Z_LABEL
        x0, x1, z1, z0 = ax.images[0].get_extent()
        assert (x1 - x0, z1 - z0) == pytest.approx((20 * 2.0, 24 * 2.0))  # pixel edges: n·pitch
    import matplotlib.pyplot as plt

    plt.close(fig)
    # the classifier overlay draws with the same helper
    from classifier import infer, outputs

    seen = []
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", lambda self, *a, **k: seen.append(self))
    cls = infer.Classification(
        labels=np.zeros((6, 5), np.uint8),
        probabilities=np.zeros((1, 6, 5), np.float32),
        classes=["diffusion"],
        mask=np.ones((6, 5), bool),
        background=np.zeros((6, 5), bool),
        intensity_db=np.zeros((6, 5)),
        model=None,
        sources=["m.npz"],
        axes="CZX",
        pitch_um={"z": 1.5, "x": 2.0},
        info={"pool": 1},
    )
    outputs._overlay(cls, str(tmp_path / "o.png"))
    ax = seen[0].axes[0]
    assert ax.get_xlabel() == figures.X_LABEL and ax.get_ylabel() == figures.Z_LABEL
    assert ax.images[0].get_extent() == pytest.approx([0.0, 5 * 2.0, 6 * 1.5, 0.0])


def test_intensity_tiff_at_original_resolution_needs_no_optics(tmp_path, capsys):
    inten = (np.abs(speckle((8, 5, 6), seed=15)) ** 2).astype(np.float32)
    tifffile.imwrite(tmp_path / "cog.tif", inten)
    out = tmp_path / "m.npz"
    assert (
        main(
            [
                "maps",
                str(tmp_path / "cog.tif"),
                "--frame-interval-s",
                "0.2048",
                "--ocds-delay-range-s",
                "0.2048",
                "0.6144",
                "--aliv",
                "--out",
                str(out),
                "--png",
                "--no-progress",
            ]
        )
        == 0
    )
    m = read_maps(out)
    i = torch.from_numpy(inten).movedim(0, -1)
    np.testing.assert_allclose(m["liv@original"], metrics.liv(i).numpy(), rtol=1e-5, atol=1e-5)
    assert m.channel_info("liv@original")["wavelength_um"] is None and m.meta["pitch_um"] is None
    assert (tmp_path / "m_liv_original.png").exists()
    capsys.readouterr()
    # a resolution change still needs them, and says which
    np.save(tmp_path / "raw.npy", speckle((8, 5, 6)))
    argv = [
        "maps",
        str(tmp_path / "raw.npy"),
        "--axes",
        "TZX",
        "--frame-interval-s",
        "0.2048",
        "--ocds-delay-range-s",
        "0.2048",
        "0.6144",
        "--out",
        str(tmp_path / "r.npz"),
        "--no-progress",
    ]
    assert main(argv) == 0
    assert main(argv + ["--resolution", "axial=14", "--force"]) == 2
    err = capsys.readouterr().err
    assert "--pitch-um" in err or "--wavelength-um" in err


def test_biased_ocds_computes_only_the_lags_in_the_range(monkeypatch):
    g = torch.Generator().manual_seed(16)
    i = torch.rand(50, 24, generator=g, dtype=torch.float64) + 0.01
    times = [DT * k for k in range(24)]
    delays, rho = metrics.lag_correlations(metrics.to_db(i), times, estimator="biased")
    ref = metrics.ocds_from_correlations(rho, delays, (0.2048, 0.6144))

    def every_lag(*a, **k):
        raise AssertionError("all lags computed")

    monkeypatch.setattr(metrics, "lag_correlations", every_lag)
    got = ocds_map(i, times, delay_range_s=(0.2048, 0.6144), estimator="biased")
    torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-12)


def test_all_nan_or_empty_input_is_refused(tmp_path, capsys):
    for name, fill in (("nan", np.nan), ("zero", 0.0)):
        data = np.full((12, 5, 6), fill, np.complex64)  # 12 frames: every default OCDS delay has 6+ pairs
        path = write_sequence(
            tmp_path / f"{name}.npz",
            data,
            {
                "axes": "TZX",
                "pitch_um": {"z": 1.5, "x": 2.0},
                "frame_times_s": [DT * k for k in range(12)],
                "system": SYSTEM,
            },
        )
        with pytest.raises(ValueError, match=f"{name}.npz.*no (finite|nonzero)"):
            compute_maps(read_sequence(path), ["original"])
        out = tmp_path / f"{name}-maps.npz"
        assert main(["maps", str(path), "--out", str(out), "--no-progress"]) == 2
        assert f"{name}.npz" in capsys.readouterr().err and not out.exists()


def test_one_frame_input_is_refused_naming_the_file(tmp_path, capsys):
    path = write_sequence(
        tmp_path / "one.npy",
        speckle((1, 5, 6)),
        {"axes": "TZX", "pitch_um": {"z": 1.5, "x": 2.0}, "frame_times_s": [0.0], "system": SYSTEM},
    )
    with pytest.raises(ValueError, match="one.npy.*1 frame.*at least 2"):
        compute_maps(read_sequence(path), ["original"], metrics=["liv"])
    assert main(["maps", str(path), "--out", str(tmp_path / "m.npz"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "one.npy" in err and "max()" not in err


def test_big_endian_npy_is_read(tmp_path, capsys):
    data = speckle((8, 10, 6), seed=17)  # 10 × 1.5 µm deep: holds the axial=14 target
    meta = {
        "axes": "TZX",
        "pitch_um": {"z": 1.5, "x": 2.0},
        "frame_times_s": [DT * k for k in range(8)],
        "system": SYSTEM,
    }
    write_sequence(tmp_path / "le.npy", data, meta)
    np.save(tmp_path / "be.npy", data.astype(">c8"))
    (tmp_path / "be.json").write_text(json.dumps(meta))
    outs = []
    for stem in ("le", "be"):
        outs.append(tmp_path / f"{stem}-maps.npz")
        assert (
            main(
                [
                    "maps",
                    str(tmp_path / f"{stem}.npy"),
                    "--resolution",
                    "original",
                    "--resolution",
                    "axial=14",
                    "--ocds-delay-range-s",
                    "0.2048",
                    "0.6144",
                    "--aliv",
                    "--out",
                    str(outs[-1]),
                    "--no-progress",
                ]
            )
            == 0
        )
    np.testing.assert_array_equal(read_maps(outs[0]).maps, read_maps(outs[1]).maps)


def test_bulk_phase_correction_is_the_corrected_sequence_for_every_channel():
    """One corrected field per slab: with ``bulk_phase`` the reduced channels and the signature channels are
    those of :func:`corrected_sequence` bit for bit, while the intensity channels at the original resolution
    (which read no phase) are those of the uncorrected field."""
    from torchdoct.measured.bulkphase import corrected_sequence, estimate_bulk_phase

    data = speckle((12, 16, 10), seed=31, corr=0.95)
    rng = np.random.default_rng(31)
    phi = rng.uniform(-math.pi, math.pi, (12, 1, 10))  # one phase per frame and A-line, common to its depths
    seq = make_seq((data * np.exp(1j * phi)).astype(np.complex64))
    bp = estimate_bulk_phase(seq, "weighted-mean")
    res = ["original", "axial=14", "lateral=18"]
    kw = dict(ocds_delay_range_s=(0.2048, 0.6144), signature=True, slab_elements=12 * 10 * 5)
    got = compute_maps(seq, res, bulk_phase=bp, **kw)
    corrected = compute_maps(corrected_sequence(seq, bp), res, **kw)
    plain = compute_maps(seq, res, **kw)
    assert got.channels == corrected.channels == plain.channels
    for i, name in enumerate(got.channels):
        metric, _, r = name.partition("@")
        doct_original = r == "original" and metric in ("liv", "ocds", "mean_db")
        np.testing.assert_array_equal(got.maps[i], (plain if doct_original else corrected).maps[i], err_msg=name)
    # the correction matters for the field features: the corrected field is more coherent than the recorded one
    assert np.median(got["g1_1@original"]) > np.median(plain["g1_1@original"]) + 0.3


# ----------------------------------------------------------------------------------------------------------
# speckle-motion channels (compute_maps(..., speckle=...)): the numbers of torchdoct.sim.speckle on the whole
# field whatever the slabs, the other channels unchanged bit for bit, the window in the metadata, the
# torch-free reader, refusals before any work
# ----------------------------------------------------------------------------------------------------------


def _speckle_reference(data: np.ndarray, pitch: dict, window: int, ndim: int) -> np.ndarray:
    from torchdoct.sim.speckle import map_speckle_features, speckle_motion

    return speckle_motion(
        torch.from_numpy(data),
        pitch,
        DT,
        window=window,
        ndim=ndim,
        names=map_speckle_features(ndim, n_frames=data.shape[0]),
    )[1].numpy()


@pytest.mark.parametrize("volume", [False, True])
def test_speckle_channels_match_the_feature_module_across_slabs(volume):
    shape = (12, 4, 20, 9) if volume else (12, 24, 13)
    data = speckle(shape, corr=0.9, seed=3, dtype=np.complex128)
    seq = make_seq(data, volume=volume)
    from torchdoct.sim.speckle import map_speckle_features

    names = map_speckle_features(3 if volume else 2, n_frames=shape[0])
    whole = compute_maps(seq, ["original", "axial=14"], speckle=True, speckle_window=5)
    slabs = compute_maps(
        seq,
        ["original", "axial=14"],
        speckle=True,
        speckle_window=5,
        slab_elements=12 * 4 * 9 * (4 if volume else 1) if volume else 12 * 13 * 4,
    )
    ref = _speckle_reference(data, seq.pitch_um, 5, 3 if volume else 2)
    got = np.stack([whole[f"{n}@original"] for n in names])
    np.testing.assert_allclose(got, ref.astype(np.float32), rtol=1e-5, atol=1e-6, equal_nan=True)
    np.testing.assert_allclose(
        np.stack([slabs[f"{n}@original"] for n in names]), got, rtol=1e-5, atol=1e-6, equal_nan=True
    )
    plain = compute_maps(seq, ["original", "axial=14"])
    for c in plain.channels:  # every other channel unchanged bit for bit
        assert np.array_equal(whole[c], plain[c], equal_nan=True), c
    assert whole.meta["speckle"]["window_px"] == 5 and whole.meta["speckle"]["resolution"] == "original"
    rec = {c["name"]: c for c in whole.meta["channels"]}
    assert rec["xc_speed@original"]["unit"] == "um/s" and rec["xc_speed@original"]["lateral_resolution_um"] == 4.9


def test_speckle_channels_survive_the_torch_free_reader(tmp_path):
    from torchdoct.measured.mapsfile import write_maps
    from torchdoct.sim.speckle import speckle_feature_unit

    data = speckle((10, 16, 12), corr=0.9, seed=4)
    m = compute_maps(make_seq(data), ["original"], speckle=True)
    for suffix in (".npz", ".tif"):
        path = write_maps(tmp_path / f"m{suffix}", m)
        back = read_maps(path)
        assert back.channels == m.channels
        np.testing.assert_array_equal(back["xc_shift_2@original"], m["xc_shift_2@original"])
        units = {c["name"]: c["unit"] for c in back.meta["channels"]}
        assert units["xc_shift_2@original"] == speckle_feature_unit("xc_shift_2") == "um"
        assert back.meta["speckle"]["window_px"] == m.meta["speckle"]["window_px"]


def test_speckle_channels_are_refused_without_a_pitch_or_an_original_resolution():
    data = speckle((10, 16, 12), seed=5)
    seq = make_seq(data)
    with pytest.raises(ValueError, match="original resolution"):
        compute_maps(seq, ["axial=14"], speckle=True)
    with pytest.raises(ValueError, match="odd"):
        compute_maps(seq, ["original"], speckle=True, speckle_window=4)
    bare = SequenceData(
        data=data,
        meta=validate_meta({"axes": "TZX", "frame_times_s": [DT * i for i in range(10)], "system": SYSTEM}, data.shape),
        source="bare.npy",
    )
    with pytest.raises(ValueError, match="pitch"):
        compute_maps(bare, ["original"], speckle=True)


def test_speckle_dynamic_adds_the_dynamic_field_s_channels_across_slabs_and_leaves_the_others(tmp_path, capsys):
    """``torchdoct maps --speckle-dynamic``: the channels of the dynamic field are those of
    torchdoct.sim.speckle on the whole field (whatever the slabs: the temporal mean is per pixel), read back by
    the torch-free reader; every other channel is bit for bit that of ``--speckle``; an intensity sequence is
    refused, naming the file and the flag, before any work."""
    from torchdoct.measured.mapsfile import write_maps
    from torchdoct.sim.speckle import dynamic_speckle_features, map_speckle_features, speckle_motion

    shape = (12, 4, 20, 9)
    data = speckle(shape, corr=0.9, seed=21, dtype=np.complex128)
    data += 2.0 * speckle((1, *shape[1:]), seed=22, dtype=np.complex128)  # static tissue sharing the PSF
    seq = make_seq(data, volume=True)
    dyn = dynamic_speckle_features(3, n_frames=12)
    names = map_speckle_features(3, n_frames=12) + dyn
    whole = compute_maps(seq, ["original"], speckle=names, speckle_window=5)
    slabs = compute_maps(seq, ["original"], speckle=names, speckle_window=5, slab_elements=12 * 9 * 20 * 2)
    ref = speckle_motion(torch.from_numpy(data), seq.pitch_um, DT, dyn, window=5, ndim=3)[1].numpy()
    got = np.stack([whole[f"{n}@original"] for n in dyn])
    np.testing.assert_allclose(got, ref.astype(np.float32), rtol=1e-5, atol=1e-6, equal_nan=True)
    np.testing.assert_allclose(
        np.stack([slabs[f"{n}@original"] for n in dyn]), got, rtol=1e-5, atol=1e-6, equal_nan=True
    )
    plain = compute_maps(seq, ["original"], speckle=True, speckle_window=5)
    for c in plain.channels:
        assert np.array_equal(whole[c], plain[c], equal_nan=True), c
    back = read_maps(write_maps(tmp_path / "m.npz", whole))
    assert (
        back.channels == whole.channels
        and {c["name"]: c["unit"] for c in back.meta["channels"]}["xcd_shift_y_2@original"] == "um"
    )
    # the command line: one flag, and intensity data refused
    np.save(tmp_path / "raw.npy", data)
    meta = {"axes": "TYZX", "pitch_um": {"z": 1.5, "x": 2.0, "y": 3.0}, "frame_times_s": [DT * i for i in range(12)]}
    (tmp_path / "raw.json").write_text(json.dumps({**meta, "system": SYSTEM}))
    assert main(["maps", str(tmp_path / "raw.npy"), "--speckle-dynamic", "--out", str(tmp_path / "cli.npz")]) == 0
    assert {f"{n}@original" for n in dyn} <= set(read_maps(tmp_path / "cli.npz").channels)
    np.save(tmp_path / "inten.npy", (np.abs(data) ** 2).astype(np.float32))
    (tmp_path / "inten.json").write_text(json.dumps({**meta, "system": SYSTEM}))
    capsys.readouterr()
    code = main(["maps", str(tmp_path / "inten.npy"), "--speckle-dynamic", "--out", str(tmp_path / "no.npz")])
    err = capsys.readouterr().err
    assert code != 0 and "inten.npy" in err and "--speckle-dynamic" in err and "complex" in err
    assert not (tmp_path / "no.npz").exists()
