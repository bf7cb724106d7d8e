"""The decorrelation signature (torchdoct.sim.signature): closed forms, limits, invariances, names.

Statistical checks use circular complex Gaussian fields (fully developed speckle, N_eff → ∞) with
fixed seeds: independent frames (fully decorrelated) and a complex AR(1) process
``E_i = a·E_{i−1} + √(1−a²)·e_i`` whose field correlation is ``g1(m) = a^m``, so that
``ρ_I(m) = |g1|²`` (Siegert) and ``ρ_dB(m) = (6/π²)·Li₂(|g1|²)`` (physics.md §2.4, §5.4). Tolerances are
z = 4 Monte Carlo standard errors from the sample plus the estimator's known O(1/(T−m)) bias bound.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchdoct.sim import theory
from torchdoct.sim.metrics import liv
from torchdoct.sim.signature import (
    DEFAULT_FEATURES,
    available_features,
    default_features,
    feature_unit,
    needs_field,
    parse_feature,
    signature,
)

DT_S = 0.2048
Z = 4.0
ALL = ("rho_db_1", "rho_db_5", "rho_lin_1", "rho_lin_5", "g1_1", "g1_5", "phase_ramp", "lin_contrast", "db_variance")


def _times(n):
    return [DT_S * i for i in range(n)]


def _speckle(shape, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.complex(
        torch.randn(*shape, generator=g, dtype=torch.float64), torch.randn(*shape, generator=g, dtype=torch.float64)
    ) / math.sqrt(2.0)


def _ar1(pixels, frames, a, seed=0):
    e = _speckle((pixels, frames), seed)
    out = torch.empty_like(e)
    out[:, 0] = e[:, 0]
    for i in range(1, frames):
        out[:, i] = a * out[:, i - 1] + math.sqrt(1 - a * a) * e[:, i]
    return out


def _mean_se(v):
    v = v.double()
    return float(v.mean()), float(v.std() / math.sqrt(v.numel()))


def test_static_pixel_is_fully_correlated():
    e = torch.full((5, 32), 2.0 - 1.5j, dtype=torch.complex128)
    names, f = signature(e, _times(32), names=ALL)
    assert names == ALL and f.shape == (5, len(ALL))
    got = dict(zip(names, f[0].tolist()))
    for k in ("rho_db_1", "rho_db_5", "rho_lin_1", "rho_lin_5", "g1_1", "g1_5", "phase_ramp"):
        assert got[k] == pytest.approx(1.0, abs=1e-12), k
    assert got["lin_contrast"] == 0.0 and got["db_variance"] == 0.0


def test_decorrelated_speckle_correlations_vanish():
    t = 32
    e = _speckle((20000, t), seed=1)
    names, f = signature(e, _times(t), names=ALL)
    got = {n: f[:, i] for i, n in enumerate(names)}
    for k in ("rho_db_1", "rho_db_5", "rho_lin_1", "rho_lin_5"):
        m = parse_feature(k)[1]
        mean, se = _mean_se(got[k])
        assert abs(mean) <= 2.0 / (t - m) + Z * se, (k, mean, se)  # lag-estimator bias is O(1/(T-m))
    for k in ("g1_1", "g1_5"):  # E|g1_hat|^2 = 1/(T-m) to first order for independent frames
        m = parse_feature(k)[1]
        mean, se = _mean_se(got[k] ** 2 * (t - m))
        assert abs(mean - 1.0) <= 0.1 + Z * se, (k, mean)
    # Gaussian speckle: Var(10 log10 I) = (10/ln10)^2 pi^2/6, ddof 0 over T frames of independent speckle
    mean, se = _mean_se(got["db_variance"])
    assert mean == pytest.approx(theory.db_variance_gaussian_speckle() * (t - 1) / t, abs=Z * se)
    torch.testing.assert_close(got["db_variance"], liv(e.abs() ** 2))


@pytest.mark.parametrize("a", [0.5, 0.9])
def test_ar1_field_matches_the_closed_forms(a):
    t = 1024  # long sequences: the estimators' bias, O(1/((1 − a)·T)) for a correlated series, stays small
    e = _ar1(1000, t, a, seed=2)
    names, f = signature(e, _times(t), names=("g1_1", "g1_3", "rho_lin_1", "rho_lin_3", "rho_db_1", "rho_db_3"))
    got = {n: f[:, i] for i, n in enumerate(names)}
    for m in (1, 3):
        g = a**m
        expect = {f"g1_{m}": g, f"rho_lin_{m}": g * g, f"rho_db_{m}": float(theory.rho_db_gaussian_limit(g))}
        for k, v in expect.items():
            mean, se = _mean_se(got[k])
            assert abs(mean - v) <= 2.0 / ((1 - a) * (t - m)) + Z * se, (k, mean, v, se)


def test_bulk_phase_and_scale_invariance():
    t = 32
    e = _ar1(500, t, 0.8, seed=3) * torch.exp(1j * torch.linspace(0, 3, t, dtype=torch.float64))  # some Doppler
    names, f0 = signature(e, _times(t), names=ALL)
    # scale-free: a gain and a constant phase change nothing
    _, f1 = signature(e * (7.3 * np.exp(0.4j)), _times(t), names=ALL)
    torch.testing.assert_close(f1, f0, rtol=1e-9, atol=1e-9)
    # a random bulk phase per frame leaves the intensity features exactly unchanged
    phi = torch.rand(1, t, generator=torch.Generator().manual_seed(4), dtype=torch.float64) * 2 * math.pi
    _, f2 = signature(e * torch.exp(1j * phi), _times(t), names=ALL)
    inten = [i for i, n in enumerate(names) if not needs_field(n)]
    field = [i for i, n in enumerate(names) if needs_field(n)]
    torch.testing.assert_close(f2[:, inten], f0[:, inten], rtol=1e-9, atol=1e-9)
    assert float((f2[:, field] - f0[:, field]).abs().max()) > 0.1  # the field group sees the bulk phase
    # a linear bulk drift (constant bulk velocity) leaves the field features unchanged as well
    drift = torch.exp(1j * 1.7 * torch.arange(t, dtype=torch.float64))
    _, f3 = signature(e * drift, _times(t), names=ALL)
    torch.testing.assert_close(f3, f0, rtol=1e-9, atol=1e-9)


def test_flow_phase_ramp_is_one():
    t = 32  # a pure Doppler rotation of a static speckle: constant phase increment
    e = _speckle((10, 1), seed=5) * torch.exp(-1j * 0.9 * torch.arange(t, dtype=torch.float64))
    _, f = signature(e, _times(t), names=("phase_ramp", "g1_1", "g1_7"))
    torch.testing.assert_close(f, torch.ones_like(f))


def test_names_shapes_units_and_intensity_only():
    e = _speckle((2, 3, 4, 32), seed=6).to(torch.complex64)
    names, f = signature(e, _times(32))
    assert names == DEFAULT_FEATURES == default_features(32)
    assert f.shape == (2, 3, 4, len(names)) and f.dtype == torch.float32
    inten = e.abs() ** 2
    names_i, fi = signature(inten, _times(32))
    assert names_i == available_features(DEFAULT_FEATURES, False) and not any(needs_field(n) for n in names_i)
    assert all(n in names for n in names_i) and fi.shape[-1] == len(names_i)
    torch.testing.assert_close(fi, f[..., [names.index(n) for n in names_i]])
    assert feature_unit("rho_db_3") == "1" and feature_unit("db_variance") == "dB^2"
    assert all(parse_feature(n)[1] <= 29 for n in default_features(32))
    assert all(parse_feature(n)[1] <= 5 for n in default_features(8))
    with pytest.raises(ValueError, match="complex field"):
        signature(inten, _times(32), names=("g1_1",))
    with pytest.raises(ValueError, match="unknown signature feature"):
        signature(e, _times(32), names=("g2_1",))
    with pytest.raises(ValueError, match="lag 30 needs at least 33 frames"):
        signature(e, _times(32), names=("rho_db_30",))
    with pytest.raises(ValueError, match="uniform"):
        signature(e, [0.0, 0.1, 0.3] + [0.1 * i for i in range(3, 32)], names=("rho_db_1",))
    with pytest.raises(ValueError, match="32 frames but 31"):
        signature(e, _times(31))


def test_empty_volume_gives_nan():
    e = _speckle((3, 32), seed=7)
    e[1, 5] = 0
    _, f = signature(e, _times(32), names=ALL)
    assert torch.isnan(f[1]).all() and torch.isfinite(f[[0, 2]]).all()


@pytest.mark.parametrize("omega", [0.9, -2.3, 3.0, 5.5, 2 * math.pi + 0.4])
def test_g1_phase_of_a_pure_rotation_is_the_wrapped_angle(omega):
    # E_i = exp(i·ω·t_i) (t_i = i·Δt): G(m) = (T − m)·exp(−i·ω·m·Δt), so |ĝ1_m| = 1 and
    # g1_phase_m = −ω·m·Δt wrapped into (−π, π]
    t = 32
    tt = torch.tensor(_times(t), dtype=torch.float64)
    w = omega / DT_S  # rad/s
    e = (3.0 - 1.0j) * torch.exp(1j * w * tt)[None, :]
    lags = (1, 2, 5, 13, 29)
    names = tuple(f"g1_phase_{m}" for m in lags) + tuple(f"g1_{m}" for m in lags)
    _, f = signature(e, _times(t), names=names)
    for i, m in enumerate(lags):
        want = math.remainder(-omega * m, 2 * math.pi)  # in [−π, π]
        if want <= -math.pi:
            want += 2 * math.pi
        got = float(f[0, i])
        assert -math.pi < got <= math.pi
        assert abs(math.remainder(got - want, 2 * math.pi)) < 1e-9, (m, got, want)
    torch.testing.assert_close(f[0, len(lags) :], torch.ones(len(lags), dtype=torch.float64))


def test_g1_phase_sign_follows_the_flow_closed_form():
    # a static speckle moved deeper at v_z: E ∝ exp(+i·2kn·z(t)) gives arg G(m) = −2kn·v_z·m·Δt
    # (theory.g1_flow's phase), here with 2kn·v_z·Δt = 0.7 rad per frame
    t = 32
    e = _speckle((4, 1), seed=11) * torch.exp(1j * 0.7 * torch.arange(t, dtype=torch.float64))
    _, f = signature(e, _times(t), names=("g1_phase_1", "g1_phase_3"))
    flow = theory.g1_flow(
        np.array([1, 3]) * DT_S,
        speed_um_per_s=0.7 / (2 * 2 * math.pi / 0.84 * DT_S),
        polar_angle_deg=0.0,
        wavelength_um=0.84,
        lateral_resolution_um=1e6,
        axial_resolution_um=1e6,
    )
    torch.testing.assert_close(f, torch.from_numpy(np.angle(flow))[None, :].expand(4, 2), rtol=0, atol=1e-6)
    torch.testing.assert_close(f[0], torch.tensor([-0.7, -2.1], dtype=torch.float64))


def test_g1_phase_names_units_and_undefined_values():
    assert parse_feature("g1_phase_7") == ("g1_phase", 7) and parse_feature("g1_7") == ("g1", 7)
    assert feature_unit("g1_phase_1") == "rad" and needs_field("g1_phase_1")
    assert "g1_phase_1" not in available_features(("g1_phase_1", "rho_lin_1"), False)
    with pytest.raises(ValueError, match="g1_phase_M"):
        parse_feature("g1_phase_0")
    e = _speckle((4, 32), seed=12)
    e[1] = 0  # G = 0: no angle
    e[2, 3] = complex("nan")
    e[3, 1:] = 0  # one non-zero frame only: G(m) = 0 at every lag, but I = 0 already makes it NaN
    _, f = signature(e, _times(32), names=("g1_phase_1", "g1_phase_4"))
    assert torch.isfinite(f[0]).all() and torch.isnan(f[1:]).all()
    # I > 0 at every frame but G(2) = 0 exactly: E_i·E*_{i+2} = +1, +1, −1, −1, ... over 28 pairs
    alt2 = torch.tensor(([1.0] * 4 + [-1.0] * 4) * 4, dtype=torch.complex128)[None, :30]
    assert complex((alt2[0, :-2] * alt2[0, 2:].conj()).sum()) == 0
    _, fa = signature(alt2, _times(30), names=("g1_phase_2", "g1_2", "g1_phase_1"))
    assert math.isnan(float(fa[0, 0])) and float(fa[0, 1]) == 0.0 and math.isfinite(float(fa[0, 2]))
    alt = torch.tensor([1, 1j, -1, -1j] * 8, dtype=torch.complex128)[None, :]
    _, fb = signature(alt, _times(32), names=("g1_phase_2",))  # E_i E*_{i+2} = −1 for every i: angle π, not −π
    assert float(fb[0, 0]) == pytest.approx(math.pi, abs=1e-12)


# ----------------------------------------------------------------------------------------------------------
# torchdoct maps --signature
# ----------------------------------------------------------------------------------------------------------
SYSTEM = {"name": "t", "wavelength_um": 0.84, "lateral_resolution_um": 4.9, "axial_resolution_um": 3.8}


def test_cli_maps_signature_channels(tmp_path, capsys):
    import tifffile

    from torchdoct.cli import main
    from torchdoct.measured.io import read_maps, read_sequence, write_sequence
    from torchdoct.measured.resolution import reduce_resolution

    t = 32
    data = _ar1(12 * 10, t, 0.7, seed=8).T.reshape(t, 12, 10).numpy().astype(np.complex64)
    seq_path = write_sequence(
        tmp_path / "seq.npz",
        data,
        {"axes": "TZX", "pitch_um": {"z": 1.5, "x": 2.0}, "frame_times_s": _times(t), "system": SYSTEM},
    )
    out = tmp_path / "maps.npz"
    assert (
        main(
            [
                "maps",
                str(seq_path),
                "--resolution",
                "original",
                "--resolution",
                "lateral=18",
                "--signature",
                "--out",
                str(out),
                "--no-progress",
            ]
        )
        == 0
    )
    assert "intensity only" not in capsys.readouterr().out
    maps = read_maps(out)
    n = len(DEFAULT_FEATURES)
    from torchdoct.sim.speckle import map_speckle_features

    n_xc = len(map_speckle_features(2, n_frames=t))  # --signature adds the speckle channels, after the rest
    assert maps.maps.shape == (6 + 2 * n + n_xc, 12, 10)
    assert all(c.startswith("xc_") and c.endswith("@original") for c in maps.channels[6 + 2 * n :])
    bare = tmp_path / "bare.npz"
    assert (
        main(
            [
                "maps",
                str(seq_path),
                "--resolution",
                "original",
                "--resolution",
                "lateral=18",
                "--signature",
                "--no-speckle",
                "--out",
                str(bare),
                "--no-progress",
            ]
        )
        == 0
    )
    np.testing.assert_array_equal(read_maps(bare).maps, maps.maps[: 6 + 2 * n])  # the other channels are unchanged
    maps = read_maps(bare)
    chans = maps.meta["channels"]
    assert [c["name"] for c in chans[6 : 6 + n]] == [f"{f}@original" for f in DEFAULT_FEATURES]
    lat = [c for c in chans if c["resolution"] == "lateral=18" and c["metric"] == "g1_1"]
    assert len(lat) == 1 and lat[0]["lateral_resolution_um"] == 18.0 and lat[0]["unit"] == "1"
    assert maps.meta["signature"]["intensity_only"] is False
    # the channels are the extractor applied to the (reduced) field, pixel by pixel
    seq = read_sequence(seq_path)
    red = reduce_resolution(
        torch.from_numpy(seq.data), pitch_um=seq.pitch_um, system=seq.system, lateral_resolution_um=18.0, axes="TZX"
    )
    _, ref = signature(red.movedim(0, -1), _times(t))
    got = maps.maps[
        [i for i, c in enumerate(chans) if c["resolution"] == "lateral=18" and c["metric"] in DEFAULT_FEATURES]
    ]
    np.testing.assert_allclose(got, ref.permute(2, 0, 1).numpy(), rtol=1e-5, atol=1e-6)
    # intensity-only input: only the intensity part, and the tool says so
    tifffile.imwrite(tmp_path / "i.tif", (np.abs(data) ** 2).astype(np.float32))
    assert (
        main(
            [
                "maps",
                str(tmp_path / "i.tif"),
                "--pitch-um",
                "z=1.5,x=2",
                "--frame-interval-s",
                "0.2048",
                "--wavelength-um",
                "0.84",
                "--lateral-resolution-um",
                "4.9",
                "--axial-resolution-um",
                "3.8",
                "--signature",
                "--no-speckle",
                "--out",
                str(tmp_path / "i.npz"),
                "--no-progress",
            ]
        )
        == 0
    )
    assert "holds intensity only: the signature has only its intensity part" in capsys.readouterr().out
    imaps = read_maps(tmp_path / "i.npz")
    names = [c["metric"] for c in imaps.meta["channels"][3:]]
    assert names == list(available_features(DEFAULT_FEATURES, False)) and imaps.meta["signature"]["intensity_only"]
    orig = [i for i, c in enumerate(chans) if c["resolution"] == "original" and c["metric"] in names]
    np.testing.assert_allclose(imaps.maps[3:], maps.maps[orig], rtol=1e-4, atol=1e-5)


# ----------------------------------------------------------------------------------------------------------
# pixel_features: one function for the training data and the maps' slab loop
# ----------------------------------------------------------------------------------------------------------
def test_pixel_features_takes_names_or_a_spec_and_does_not_depend_on_the_chunks():
    from types import SimpleNamespace

    from torchdoct.sim.signature import pixel_features

    t = 32
    x = _ar1(3 * 37, t, 0.8, seed=21).reshape(3, 37, t)  # [N, C, T], contiguous as the training data's
    names, ref = signature(x, _times(t))
    assert names == DEFAULT_FEATURES
    for spec_or_names in (None, DEFAULT_FEATURES, SimpleNamespace(metrics=list(DEFAULT_FEATURES))):
        got_names, got = pixel_features(x, _times(t), spec_or_names)
        assert got_names == names and torch.equal(got, ref)
    # chunks of pixels (memory only): the same numbers whatever the chunk size, up to the float64 round-off of
    # torch's reductions (their order of summation may follow the number of rows)
    for chunk in (1, 7, 37, 10_000):
        got_names, got = pixel_features(x, _times(t), DEFAULT_FEATURES, chunk_pixels=chunk)
        assert got_names == names and got.shape == ref.shape, chunk
        torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="chunk_pixels"):
        pixel_features(x, _times(t), None, chunk_pixels=0)


def test_the_signature_module_imports_nothing_of_measured():
    import ast
    from pathlib import Path

    import torchdoct.sim.signature as mod

    tree = ast.parse(Path(mod.__file__).read_text(encoding="utf-8"))
    found = {n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    found |= {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    assert not any("measured" in m for m in found), found


def _field_seq(shape, seed, *, volume=False):
    from torchdoct.measured.io import SequenceData, validate_meta

    t = shape[0]
    e = _ar1(int(np.prod(shape[1:])), t, 0.85, seed=seed).T.reshape(shape).numpy()  # complex128 [T, (Y), Z, X]
    meta = {
        "axes": "TYZX" if volume else "TZX",
        "pitch_um": {"z": 1.5, "x": 2.0, **({"y": 3.0} if volume else {})},
        "frame_times_s": _times(t),
        "system": SYSTEM,
    }
    return SequenceData(data=e, meta=validate_meta(meta, e.shape), source="test.npy")


@pytest.mark.parametrize("volume", [False, True])
def test_signature_channels_of_small_slabs_equal_the_whole_volume(volume):
    """The slab loop (small slabs and chunks) gives the signature of the whole field, reduced at once: exact up
    to float64 round-off without an axial reduction; with one, within the axial window's truncation at 5σ'
    (its tail e^-12.5 ≈ 4e-6 of the field), as the DOCT channels (test_maps)."""
    from torchdoct.measured.maps import compute_maps
    from torchdoct.measured.resolution import parse_resolution, reduce_resolution

    t = 16
    # 7 B-scans × 3 µm and 9 × 2 µm: the fields of view along y and x hold the lateral=18 target
    seq = _field_seq((t, 7, 30, 9) if volume else (t, 40, 12), seed=22, volume=volume)
    res = ["original", "lateral=18", "axial=14"]
    names = default_features(t) + ("g1_phase_1", "phase_ramp")
    small = compute_maps(seq, res, metrics=("liv",), signature=names, slab_elements=t * 9 * 4 * 3, chunk_pixels=11)
    assert small.meta["signature"]["features"] == list(names)
    for r in res:
        target = parse_resolution(r)
        whole = reduce_resolution(
            torch.from_numpy(seq.data),
            pitch_um=seq.pitch_um,
            system=SYSTEM,
            lateral_resolution_um=target.lateral_resolution_um,
            axial_resolution_um=target.axial_resolution_um,
            axes=seq.axes,
        )
        _, ref = signature(whole.movedim(0, -1), _times(t), names)
        got = np.stack([small[f"{n}@{r}"] for n in names], -1)
        tol = 1e-4 if target.axial_resolution_um else 1e-9
        np.testing.assert_allclose(got, ref.numpy().astype(np.float32), rtol=tol, atol=tol, err_msg=r)


def test_signature_maps_is_the_slab_loop_and_keeps_the_maps_bscans():
    """``signature_maps`` (maps computed first, the signature appended) gives the channels of one pass with
    ``signature=``, bit for bit, also for a block raster volume whose boundary B-scans the maps dropped."""
    from torchdoct.measured.io import BlockRaster, SequenceData, validate_meta
    from torchdoct.measured.maps import compute_maps, signature_maps

    raster = BlockRaster(n_blocks=2, n_repeats=16, bscans_per_block=3, drop_boundary=1)
    base = _field_seq((16, 6, 10, 8), seed=23, volume=True)
    meta = dict(base.meta, block_raster=raster.to_dict())
    seq = SequenceData(data=base.data.astype(np.complex64), meta=validate_meta(meta, base.data.shape), source="r.npy")
    res = ["original", "lateral=9.8"]
    one = compute_maps(seq, res, signature=True)
    assert one.meta["y_indices"] == [0, 1, 4, 5] and one.maps.shape[1] == 4
    two, note = signature_maps(compute_maps(seq, res), seq, res)
    assert note is None and two.channels == one.channels and two.meta["signature"] == one.meta["signature"]
    np.testing.assert_array_equal(two.maps, one.maps)
    assert one.channels[6:] == tuple(f"{f}@{r}" for r in res for f in default_features(16))  # after liv, ocds, mean_db
