"""Doppler phase against a static-tissue reference (torchdoct.measured.doppler, ``torchdoct maps --doppler``;
docs/concepts/doppler-reference.md).

The fields are point scatterers under the Gaussian PSF of physics.md §5.1 (840 nm, 4.9/3.8 µm, n = 1), one
column of scatterers per A-line, layered in depth: static tissue, an axial flow layer (every scatterer
moves deeper at ``v_z``), a random-ballistic layer (isotropic directions), in white noise; a random bulk
phase per frame (and per A-line) multiplies the whole field where a test asks for it. The truth of the
flow layer is ``−2kn·v_z·Δt`` per lag; its mean over A-lines (each A-line's mean over the layer's inner
rows, A-lines independent) must recover it within 3.5 standard errors.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from torchdoct.cli import main
from torchdoct.measured.doppler import min_reference_snr, min_whiteness, phase_tolerance
from torchdoct.measured.io import SequenceData, read_maps, validate_meta
from torchdoct.measured.maps import compute_maps

WL, LAT, AX = 0.84, 4.9, 3.8
SYSTEM = {
    "name": "840nm",
    "wavelength_um": WL,
    "lateral_resolution_um": LAT,
    "axial_resolution_um": AX,
    "refractive_index": 1.0,
}
K = 2 * math.pi / WL
SX = LAT / (2 * math.sqrt(2))
SZ = AX / (2 * math.sqrt(math.log(2)))
DZ, DT, T = 1.5, 0.05, 32
Z_SE = 3.5
NAME = "doppler_phase_1@original"


def layered_field(n_lines, layers, *, snr_db=30.0, seed=0, density=0.05):
    """``[T, Z, X]`` complex128 field of A-lines through ``layers``: a list of ``(rows, motion, speed)`` with
    ``motion`` one of ``static``, ``flow`` (axial, deeper, speed µm/s), ``ballistic`` (speed µm/s) or
    ``diffusion`` (speed: D in µm²/s, a Gaussian step of variance 2DΔt per axis and frame); white noise
    ``snr_db`` below the mean intensity."""
    rng = np.random.default_rng(seed)
    n_z = sum(r for r, _, _ in layers)
    zpix = np.arange(n_z) * DZ
    half = 3 * SX
    top, bottom = -3 * SZ, n_z * DZ + 3 * SZ
    n_j = int(density * (2 * half) ** 2 * (bottom - top))
    x0 = rng.uniform(-half, half, (n_lines, n_j))
    y0 = rng.uniform(-half, half, (n_lines, n_j))
    z0 = rng.uniform(top, bottom, (n_lines, n_j))
    bounds = np.cumsum([r for r, _, _ in layers]) * DZ
    layer = np.minimum(np.searchsorted(bounds, z0, side="right"), len(layers) - 1)
    vel = np.zeros((n_lines, n_j, 3))
    diff = np.zeros((n_lines, n_j))  # D per scatterer
    for i, (_, motion, speed) in enumerate(layers):
        here = layer == i
        if motion == "diffusion":
            diff[here] = speed
        elif motion == "flow":
            vel[here] = [0.0, 0.0, speed]
        elif motion == "ballistic":
            u = rng.standard_normal((int(here.sum()), 3))
            vel[here] = speed * u / np.linalg.norm(u, axis=1, keepdims=True)
    e = np.empty((T, n_lines, n_z), dtype=np.complex128)
    walk = np.zeros((3, n_lines, n_j))
    for t in range(T):
        if t and diff.any():
            walk += rng.standard_normal(walk.shape) * np.sqrt(2 * diff * DT)
        x, y, z = (c + vel[..., i] * t * DT + walk[i] for i, c in enumerate((x0, y0, z0)))
        amp = np.exp(-(x * x + y * y) / (2 * SX * SX) + 2j * K * z)
        e[t] = np.einsum("lj,ljz->lz", amp, np.exp(-((z[..., None] - zpix) ** 2) / (2 * SZ * SZ)))
    p = float(np.mean(np.abs(e) ** 2))
    e += (rng.standard_normal(e.shape) + 1j * rng.standard_normal(e.shape)) * math.sqrt(p * 10 ** (-snr_db / 10) / 2)
    return np.ascontiguousarray(e.transpose(0, 2, 1))  # [T, Z, X]


def _meta():
    return {
        "axes": "TZX",
        "pitch_um": {"z": DZ, "x": 2.0},
        "frame_times_s": [DT * i for i in range(T)],
        "system": SYSTEM,
    }


def seq_of(data):
    return SequenceData(data=data, meta=validate_meta(_meta(), data.shape), source="test.npy")


def save_sequence(path, data):
    """``data`` as ``path`` (.npy) with its JSON sidecar: what ``torchdoct maps`` reads."""
    np.save(path, data)
    path.with_suffix(".json").write_text(json.dumps(_meta()))


def with_bulk(e, seed, per_aline=False):
    rng = np.random.default_rng(seed)
    phi = rng.uniform(-math.pi, math.pi, (T, 1, e.shape[2] if per_aline else 1))
    return e * np.exp(1j * phi)


def layer_mean(ch, rows):
    """Mean and standard error over A-lines of each A-line's mean over ``rows`` (its finite values)."""
    block = ch[rows]
    block = block[:, np.isfinite(block).any(axis=0)]  # A-lines without a reference are NaN throughout
    a = np.nanmean(block, axis=0)
    return float(a.mean()), float(a.std(ddof=1) / math.sqrt(a.size))


V_FLOW = 0.8  # µm/s: a Doppler step of 0.6 rad per frame, 1.2 µm of travel over the sequence
LAYERS = [(16, "static", 0.0), (16, "flow", V_FLOW), (16, "ballistic", 0.3)]
# the layers' inner rows: more than 2 s_z (4.6 µm, 3 rows) from a boundary, so the PSF does not mix them
STATIC, FLOW, BALLISTIC = slice(0, 12), slice(20, 28), slice(36, 48)


@pytest.fixture(scope="module")
def field():
    return layered_field(96, LAYERS, seed=3)


@pytest.fixture(scope="module")
def maps_with_bulk(field):
    return compute_maps(seq_of(with_bulk(field, 11)), metrics=("liv", "mean_db"), doppler=True)


def test_flow_velocity_is_recovered_under_a_random_bulk_phase(maps_with_bulk):
    m = maps_with_bulk
    assert m.channels[-1] == NAME
    ch = m.maps[m.index(NAME)].astype(np.float64)
    info = m.meta["doppler"]["per_lag"]["1"]
    mean, se = layer_mean(ch, FLOW)
    vz = mean * info["vz_um_per_s_per_rad"]
    assert abs(mean - (-2 * K * V_FLOW * DT)) <= Z_SE * se, (mean, se, vz)
    assert abs(vz - V_FLOW) <= Z_SE * se * abs(info["vz_um_per_s_per_rad"])
    s_mean, s_se = layer_mean(ch, STATIC)  # the static tissue sits at 0
    assert abs(s_mean) <= Z_SE * s_se, (s_mean, s_se)
    # the reference is the static layer: its share, and no flow pixel in it
    assert info["alines_own_reference"] + info["alines_bscan_reference"] == 96
    assert 0.1 < info["reference_share"] < 1.0 / 3 + 0.01


def test_random_ballistic_layer_has_zero_mean_phase(maps_with_bulk):
    ch = maps_with_bulk.maps[maps_with_bulk.index(NAME)].astype(np.float64)
    mean, se = layer_mean(ch, BALLISTIC)
    assert abs(mean) <= Z_SE * se, (mean, se)


def test_diffusing_layer_has_zero_mean_phase_beside_the_flow():
    """D = 0.05 µm²/s: g1 at one frame is exp(−4k²nD·Δt) ≈ 0.6, real and positive (physics.md §5.3 (a))."""
    layers = [(16, "static", 0.0), (16, "flow", V_FLOW), (16, "diffusion", 0.05)]
    m = compute_maps(seq_of(with_bulk(layered_field(64, layers, seed=8), 37)), metrics=("mean_db",), doppler=True)
    ch = m.maps[m.index(NAME)].astype(np.float64)
    mean, se = layer_mean(ch, BALLISTIC)  # the third layer's inner rows
    assert abs(mean) <= Z_SE * se, (mean, se)
    mean, se = layer_mean(ch, FLOW)
    assert abs(mean - (-2 * K * V_FLOW * DT)) <= Z_SE * se, (mean, se)


def test_bulk_phase_does_not_change_the_channel(field, maps_with_bulk):
    """None, another random phase per frame: the same channel to rounding. A random phase per frame and A-line:
    the same wherever the A-line has its own reference (the B-scan fallback assumes a phase common to the
    B-scan, so an A-line that needs it may lose it)."""
    ref = maps_with_bulk.maps[maps_with_bulk.index(NAME)]
    for seed, per_aline in ((None, False), (12, False), (12, True)):
        data = field if seed is None else with_bulk(field, seed, per_aline=per_aline)
        m = compute_maps(seq_of(data), metrics=("liv", "mean_db"), doppler=True)
        got = m.maps[m.index(NAME)]
        both = np.isfinite(got) & np.isfinite(ref)
        if not per_aline:
            np.testing.assert_array_equal(np.isnan(got), np.isnan(ref))
        else:
            assert both.mean() > 0.9 and m.meta["doppler"]["per_lag"]["1"]["alines_own_reference"] > 0.9 * 96
        np.testing.assert_allclose(got[both], ref[both], atol=1e-4)


def test_other_channels_are_bit_identical(field, maps_with_bulk):
    data = with_bulk(field, 11)
    plain = compute_maps(seq_of(data), metrics=("liv", "mean_db"))
    assert maps_with_bulk.channels[:-1] == plain.channels
    np.testing.assert_array_equal(maps_with_bulk.maps[:-1], plain.maps)
    assert "doppler" not in plain.meta


@pytest.mark.parametrize(
    "layers",
    [
        [(16, "flow", V_FLOW), (16, "ballistic", 0.3)],  # flow beside ballistic
        [(40, "flow", V_FLOW), (8, "ballistic", 0.3)],
    ],
)  # a thick flow layer
def test_without_static_tissue_the_channel_is_absent(layers):
    """The slow flow's speckle moves 1.2 µm over the sequence (half the axial PSF's s_z): many of its pixels pass
    the steadiness test, some the whiteness test too, and they share one Doppler phase; as a population they
    drift, so no A-line and no B-scan takes them for static tissue."""
    e = with_bulk(layered_field(48, layers, seed=5), 13)
    m = compute_maps(seq_of(e), metrics=("mean_db",), doppler=True)
    assert not any(c.startswith("doppler_phase") for c in m.channels)
    d = m.meta["doppler"]
    assert d["channels"] == [] and "absent" in d and "static" in d["absent"]
    assert d["per_lag"]["1"]["alines_without_reference"] == 48


def test_intensity_only_input_gives_no_channel_and_a_note(tmp_path, capsys):
    inten = np.abs(layered_field(8, LAYERS[:2], seed=1)) ** 2
    m = compute_maps(seq_of(inten.astype(np.float32)), metrics=("mean_db",), doppler=True)
    assert m.channels == ("mean_db@original",)
    assert "intensity only" in m.meta["doppler"]["absent"]
    save_sequence(tmp_path / "i.npy", inten.astype(np.float32))
    assert (
        main(
            [
                "maps",
                str(tmp_path / "i.npy"),
                "--metrics",
                "mean_db",
                "--doppler",
                "--out",
                str(tmp_path / "i.npz"),
                "--no-progress",
            ]
        )
        == 0
    )
    assert "note: --doppler" in capsys.readouterr().out


def test_slabs_and_lags_and_the_cli(tmp_path, capsys, field):
    data = with_bulk(field[:, :, :24], 17)
    whole = compute_maps(seq_of(data), metrics=("mean_db",), doppler=(1, 2))
    # depth slabs of 5 rows (the maps) and lateral slabs of 5 A-lines (the reference): the same channels
    cut = compute_maps(seq_of(data), metrics=("mean_db",), doppler=(1, 2), slab_elements=5 * data.shape[0] * 24)
    np.testing.assert_array_equal(whole.maps, cut.maps)
    assert whole.channels[-2:] == ("doppler_phase_1@original", "doppler_phase_2@original")
    two = whole.maps[whole.index("doppler_phase_2@original")].astype(np.float64)
    mean, se = layer_mean(two, FLOW)
    assert abs(mean - (-2 * K * V_FLOW * 2 * DT)) <= Z_SE * se
    save_sequence(tmp_path / "f.npy", data.astype(np.complex64))
    out = tmp_path / "f.npz"
    assert (
        main(
            ["maps", str(tmp_path / "f.npy"), "--doppler", "--doppler-lags", "1,2", "--out", str(out), "--no-progress"]
        )
        == 0
    )
    text = capsys.readouterr().out
    assert "Doppler reference" in text
    maps = read_maps(out)
    assert maps.meta["doppler"]["channels"] == ["doppler_phase_1", "doppler_phase_2"]
    assert maps.meta["doppler"]["per_lag"]["1"]["reference_share"] > 0


def test_the_rule_s_constants_follow_from_the_noise():
    c = 0.05
    s = min_reference_snr(c)
    assert (2 * s + 1) / (s + 1) ** 2 == pytest.approx(c)  # a static pixel at that SNR has the threshold contrast
    assert 0 < min_whiteness(32) < 1 and min_whiteness(32) < min_whiteness(128)
    assert phase_tolerance(2, 32) > phase_tolerance(1, 32) > phase_tolerance(1, 64)
    from scipy.stats import binom

    from torchdoct.measured.doppler import WHITE_TEST_LEVEL, _binomial_threshold, white_population

    n = np.array([1, 2, 5, 10, 15, 30, 100, 1000, 12345])
    np.testing.assert_array_equal(
        _binomial_threshold(n, 0.5, WHITE_TEST_LEVEL), binom.isf(WHITE_TEST_LEVEL, n, 0.5) + 1
    )
    assert white_population(np.array([10, 9, 950, 0]), np.array([10, 15, 1000, 0])).tolist() == [
        True,
        False,
        True,
        False,
    ]


def test_refusals():
    e = layered_field(4, LAYERS[:1], seed=2)
    with pytest.raises(ValueError, match="lag"):
        compute_maps(seq_of(e), metrics=("mean_db",), doppler=(T,))
    with pytest.raises(ValueError, match="original"):
        compute_maps(seq_of(e), ["axial=7.6"], metrics=("mean_db",), doppler=True)


def test_thin_static_layer_falls_back_to_the_b_scan_reference():
    """Five static rows per A-line are too few for an A-line reference: the B-scan's (a bulk phase common to the
    B-scan at each frame) takes over, the same in one lateral slab and in slabs of four A-lines (four passes)."""
    layers = [(5, "static", 0.0), (16, "flow", V_FLOW)]
    e = with_bulk(layered_field(48, layers, seed=7), 19)
    whole = compute_maps(seq_of(e), metrics=("mean_db",), doppler=True)
    info = whole.meta["doppler"]["per_lag"]["1"]
    assert info["alines_bscan_reference"] > 0 and info["bscans_with_reference"] == 1
    ch = whole.maps[whole.index(NAME)].astype(np.float64)
    mean, se = layer_mean(ch, slice(9, 21))
    assert abs(mean - (-2 * K * V_FLOW * DT)) <= Z_SE * se, (mean, se)
    cut = compute_maps(seq_of(e), metrics=("mean_db",), doppler=True, slab_elements=4 * T * e.shape[1])
    np.testing.assert_array_equal(whole.maps, cut.maps)
    # a bulk phase of its own per A-line: the B-scan holds no common reference, so no channel (in one slab
    # and in four passes), not a reference borrowed from the few A-lines that happen to share a phase
    e = with_bulk(layered_field(48, layers, seed=7), 29, per_aline=True)
    for slab in (1 << 23, 4 * T * e.shape[1]):
        m = compute_maps(seq_of(e), metrics=("mean_db",), doppler=True, slab_elements=slab)
        assert NAME not in m.channels
        cov = m.meta["doppler"]["per_lag"]["1"]["bscan_aline_coverage"][0]
        assert cov < 0.5, cov


def test_volume_b_scans_and_slabs(field):
    e = with_bulk(field[:, :, :48], 23, per_aline=True)
    vol = np.ascontiguousarray(e.reshape(T, e.shape[1], 3, 16).transpose(0, 2, 1, 3))  # [T, Y, Z, X]
    meta = {
        "axes": "TYZX",
        "pitch_um": {"z": DZ, "x": 2.0, "y": 2.0},
        "frame_times_s": [DT * i for i in range(T)],
        "system": SYSTEM,
    }
    seq = SequenceData(data=vol, meta=validate_meta(meta, vol.shape), source="v.npy")
    whole = compute_maps(seq, metrics=("mean_db",), doppler=True)
    cut = compute_maps(seq, metrics=("mean_db",), doppler=True, slab_elements=T * 16 * vol.shape[2])
    np.testing.assert_array_equal(whole.maps, cut.maps)
    ch = whole.maps[whole.index(NAME)].astype(np.float64)  # [Y, Z, X]
    flat = ch.transpose(1, 0, 2).reshape(ch.shape[1], -1)  # [Z, A-lines]
    mean, se = layer_mean(flat, FLOW)
    assert abs(mean - (-2 * K * V_FLOW * DT)) <= Z_SE * se, (mean, se)
    assert len(whole.meta["doppler"]["per_lag"]["1"]["bscan_reference_share"] or [0, 0, 0]) == 3


def test_rendered_vessel_phantom_with_oblique_flow():
    """The shipped vessel-slab phantom rendered with its flow turned to 0.6 µm/s at 60° from the beam
    (``v_z = 0.3`` µm/s, deeper), white noise 30 dB below the static tissue and a random bulk phase per frame
    and A-line. Inside the vessel (its label eroded by 4 pixels, 8 µm > 3 s_z: no pixel shares the PSF with the
    tissue) the mean channel recovers ``−2kn·v_z·Δt``; the tissue's is 0. Units: one A-line in three (6 µm
    apart, beyond the lateral PSF), each its mean over the region."""
    import dataclasses

    from scipy.ndimage import binary_erosion

    from torchdoct import load_phantom, render
    from torchdoct.sim.config import Flow

    p = load_phantom("vessel-slab")
    pops = list(p.scene.populations)
    vessel = next(i for i, q in enumerate(pops) if q.name == "vessel")
    pops[vessel] = dataclasses.replace(
        pops[vessel], motion=(Flow(speed_um_per_s=0.6, polar_angle_deg=60.0, azimuth_deg=30.0),)
    )
    p = dataclasses.replace(p, scene=dataclasses.replace(p.scene, populations=tuple(pops)))
    res = render(p, seed=1, threads=1)
    e = res.data[0].numpy().astype(np.complex128)
    lab = res.labels
    rng = np.random.default_rng(0)
    power = float((np.abs(e) ** 2).mean(0)[lab == 1].mean())
    e = e + (rng.standard_normal(e.shape) + 1j * rng.standard_normal(e.shape)) * math.sqrt(power * 1e-3 / 2)
    e = (e * np.exp(1j * rng.uniform(-math.pi, math.pi, (e.shape[0], 1, e.shape[2])))).astype(np.complex64)
    dt = 0.2048
    meta = {
        "axes": "TZX",
        "pitch_um": {"z": 2.0, "x": 2.0},
        "frame_times_s": [dt * i for i in range(e.shape[0])],
        "system": SYSTEM,
    }
    m = compute_maps(
        SequenceData(data=e, meta=validate_meta(meta, e.shape), source="vessel.npy"), metrics=("mean_db",), doppler=True
    )
    ch = m.maps[m.index(NAME)].astype(np.float64)
    for code, truth in ((4, -2 * K * 0.3 * dt), (1, 0.0)):  # the vessel, the static tissue
        inner = binary_erosion(lab == code, iterations=4)
        cols = [np.nanmean(ch[:, x][inner[:, x]]) for x in range(0, ch.shape[1], 3) if inner[:, x].sum() > 3]
        a = np.array(cols)
        mean, se = float(a.mean()), float(a.std(ddof=1) / math.sqrt(a.size))
        assert abs(mean - truth) <= Z_SE * se, (code, mean, truth, se)


def test_a_non_finite_sample_masks_its_pixel(field):
    e = with_bulk(field[:, :, :24], 31)
    e[7, 22, 5] = np.nan
    m = compute_maps(seq_of(e), metrics=("mean_db",), doppler=True)
    ch = m.maps[m.index(NAME)]
    assert np.isnan(ch[22, 5]) and np.isfinite(ch[FLOW]).sum() == ch[FLOW].size - 1


@pytest.mark.parametrize("lag", [1, 4])
def test_static_pixel_phase_spread_is_the_predicted_one(lag):
    """Static pixels of one amplitude at SNR s = 100 in white noise, 20 per A-line, a random bulk phase per
    frame: the channel's standard deviation over the pixels is the first-order prediction of
    docs/concepts/doppler-reference.md §3, ``√((1 + 1/N)(m/(s(T − m)²) + 1/(2s²(T − m))))`` with ``N = 19``
    (leave-one-out), the formula that sets the reference's width h (6000 pixels: within 5 %)."""
    rng = np.random.default_rng(lag)
    snr, n_z, n_lines = 100.0, 20, 300
    s = np.exp(1j * rng.uniform(0, 2 * np.pi, (n_z, n_lines))) * math.sqrt(snr)
    e = s[None] + (rng.standard_normal((T, n_z, n_lines)) + 1j * rng.standard_normal((T, n_z, n_lines))) / math.sqrt(2)
    e = e * np.exp(1j * rng.uniform(-np.pi, np.pi, (T, 1, 1)))
    m = compute_maps(seq_of(e), metrics=("mean_db",), doppler=(lag,))
    ch = m.maps[m.index(f"doppler_phase_{lag}@original")].astype(np.float64)
    assert np.isfinite(ch).all()
    n, big_n = T - lag, n_z - 1
    predicted = math.sqrt((1 + 1 / big_n) * (lag / (snr * n * n) + 1 / (2 * snr * snr * n)))
    assert abs(float(ch.std()) / predicted - 1) < 0.05, (ch.std(), predicted)


def test_signature_maps_of_complex_data_add_the_doppler_channel_and_no_doppler_leaves_it_out(tmp_path, capsys, field):
    """``maps --signature`` gives the classifier what its rules read: on complex data the Doppler channel (rule 10
    of classifier.ambiguity) where a static reference exists, as ``--doppler`` gives it; ``--no-doppler`` leaves
    it out, and the two flags together are refused."""
    save_sequence(tmp_path / "f.npy", field[:, :, :24].astype(np.complex64))

    def run(*flags):
        out = tmp_path / f"m{len(flags)}{'-'.join(f.strip('-') for f in flags)}.npz"
        code = main(["maps", str(tmp_path / "f.npy"), "--signature", *flags, "--out", str(out), "--no-progress"])
        return code, out

    code, out = run()
    assert code == 0
    got = read_maps(out)
    assert NAME in got.channels and got.meta["doppler"]["channels"] == ["doppler_phase_1"]
    explicit = compute_maps(seq_of(field[:, :, :24].astype(np.complex64)), metrics=("mean_db",), doppler=True)
    np.testing.assert_array_equal(got.maps[got.index(NAME)], explicit.maps[explicit.index(NAME)])
    code, out = run("--no-doppler")
    assert code == 0 and not any(c.startswith("doppler_phase_") for c in read_maps(out).channels)
    capsys.readouterr()
    code, _ = run("--doppler", "--no-doppler")
    assert code != 0 and "--no-doppler contradict" in capsys.readouterr().err


def test_the_drift_statistic_of_noise_a_constant_and_a_drift():
    """Step 6 of the reference rule: the lag-1 autocorrelation of a pixel's intensity fluctuations is near
    ``−1/T`` for white noise (its mean over many pixels within 3.5 standard errors), 0 for a constant, and
    near 1 for a slow drift, whose drift contrast (the lag-1 autocovariance over the squared mean) is about
    its variance over the squared mean; the bound of a population is the constant plus 3.5 standard errors
    of a white population's mean, so it tightens with the population towards the constant."""
    import torch

    from torchdoct.measured.doppler import MAX_POPULATION_DRIFT, drift_statistic, max_population_drift

    rng = np.random.default_rng(3)
    white = drift_statistic(torch.from_numpy(rng.exponential(1.0, (T, 4000))))[0]
    sd = math.sqrt((T - 2) / ((T - 1) * (T + 1)))
    assert abs(float(white.mean()) + 1 / T) <= Z_SE * sd / math.sqrt(4000)
    assert float(drift_statistic(torch.ones(T, 3)).abs().max()) == 0.0  # both statistics of a constant
    ramp = torch.linspace(1.0, 2.0, T, dtype=torch.float64)[:, None] + 0.01 * torch.from_numpy(
        rng.standard_normal((T, 50))
    )
    r1, contrast = drift_statistic(ramp)
    assert float(r1.min()) > 0.8  # the ramp's share of its fluctuation
    expected = torch.linspace(1.0, 2.0, T, dtype=torch.float64).var(unbiased=False) / 1.5**2  # its contrast
    assert torch.allclose(contrast, expected.expand_as(contrast), rtol=0.15)
    bound = max_population_drift(np.array([10, 1000, 10**8]), T)
    assert bound[0] > bound[1] > bound[2] > MAX_POPULATION_DRIFT and bound[2] == pytest.approx(
        MAX_POPULATION_DRIFT, abs=1e-3
    )


def test_a_flow_steadier_than_its_noise_is_not_a_b_scan_reference():
    """Without static tissue, an axial flow whose intensity drift hides under the noise pixel by pixel
    passes the per-pixel tests and moves as one phase population: it was the B-scan's reference, and every
    other pixel's phase then measured motion against the flow. As a population its fluctuations drift
    (step 6 of docs/concepts/doppler-reference.md §4): no B-scan takes it, and at 15 dB no scope at all."""
    f = layered_field(96, [(16, "flow", 1.0), (16, "ballistic", 0.3)], snr_db=20.0, seed=5)
    per_lag = compute_maps(seq_of(f), metrics=("mean_db",), doppler=True).meta["doppler"]["per_lag"]["1"]
    assert per_lag["alines_bscan_reference"] == 0 and per_lag["bscans_with_reference"] == 0, per_lag
    f = layered_field(96, [(16, "flow", 1.5), (16, "ballistic", 0.3)], snr_db=15.0, seed=5)
    m = compute_maps(seq_of(f), metrics=("mean_db",), doppler=True)
    assert NAME not in m.channels and "drift" in m.meta["doppler"]["absent"]


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_the_pattern_statistic_cancels_a_common_phase_and_tells_a_sliding_pattern_from_static_noise():
    """Step 7 of the reference rule (docs/concepts/doppler-reference.md §4): the product of axially neighbouring
    fields cancels any phase common to the A-line at a frame, so a random bulk phase per frame, or a Doppler
    rotation of the whole A-line, leaves both statistics unchanged (to rounding); a constant field gives 0;
    static tissue in white noise moves its pattern (significance above ``PATTERN_MOVED_MIN`` and size at least
    ``PATTERN_CHANGE_MIN``) in far fewer pixels than a population may (``MAX_MOVED_SHARE``), at any SNR, while
    an axial flow whose speckle slides 1.2 µm over the sequence moves it in most of its pixels even at 11 dB."""
    import torch

    from torchdoct.measured.doppler import MAX_MOVED_SHARE, PATTERN_CHANGE_MIN, PATTERN_MOVED_MIN, pattern_statistic

    def stat(e):  # [T, Z, X] → per pixel [2, X, Z]
        return pattern_statistic(torch.from_numpy(np.ascontiguousarray(e)).permute(0, 2, 1)).numpy()

    def moved(e):
        sig, size = stat(e)
        return (sig > PATTERN_MOVED_MIN) & (size >= PATTERN_CHANGE_MIN)

    static = layered_field(200, [(32, "static", 0.0)], snr_db=20.0, seed=1)
    u = stat(static)
    spin = np.exp(1j * 0.6 * np.arange(T))[:, None, None]  # one Doppler rotation for every pixel
    for common in (with_bulk(static, 4), static * spin):
        np.testing.assert_allclose(stat(common), u, rtol=1e-9, atol=1e-12)
    assert float(np.abs(stat(np.repeat(static[:1], T, 0))).max()) == 0.0
    for snr in (11.0, 20.0, 30.0):
        share = float(moved(layered_field(200, [(32, "static", 0.0)], snr_db=snr, seed=1)).mean())
        assert share < MAX_MOVED_SHARE / 2, (snr, share)
    flow = moved(layered_field(200, [(32, "flow", V_FLOW)], snr_db=11.0, seed=2))
    assert float(flow.mean()) > 0.5  # most of its pixels


def test_a_flow_steadier_than_its_noise_at_11_db_is_no_reference_once_its_pattern_is_read(monkeypatch):
    """Without static tissue at 11 dB, an axial flow beside random-ballistic motion passes the intensity tests
    (steps 2, 4 and 6: the noise hides its drift from a few tens of pixels) and became the B-scan's reference,
    so the random-ballistic layer showed the flow's Doppler phase reversed, the drift that rule 10 reads as
    flow. Its pattern moves (step 7): no scope takes it and the channel is absent. With step 7 switched off
    (monkeypatched) the B-scan takes it again, so this test fails without it."""
    from torchdoct.measured import doppler

    f = with_bulk(layered_field(96, [(16, "flow", V_FLOW), (16, "ballistic", 0.3)], snr_db=11.0, seed=5), 13)
    m = compute_maps(seq_of(f), metrics=("mean_db",), doppler=True)
    assert NAME not in m.channels and m.meta["doppler"]["per_lag"]["1"]["reference_pixels"] == 0
    monkeypatch.setattr(doppler, "moved_population", lambda moved, n: np.zeros(np.shape(n), bool))
    m = compute_maps(seq_of(f), metrics=("mean_db",), doppler=True)
    assert m.meta["doppler"]["per_lag"]["1"]["alines_bscan_reference"] == 96
    mean, se = layer_mean(m.maps[m.index(NAME)].astype(np.float64), slice(20, 32))  # the ballistic layer
    assert abs(mean - 2 * K * V_FLOW * DT) <= Z_SE * se, (mean, se)  # the flow's Doppler phase, reversed
