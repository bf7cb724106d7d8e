"""Resolution reduction of complex OCT data (paper Eqs. 1-8; torchdoct.measured.resolution)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchdoct.conventions import (
    amplitude_sigma_axial_um,
    amplitude_sigma_lateral_um,
    wavenumber_per_um,
)
from torchdoct.measured.resolution import (
    ResolutionTarget,
    axial_filter_sigma_um,
    axial_window_sigma_per_um,
    depth_spectrum_center,
    gaussian_filter_axis,
    lateral_filter_sigma_um,
    parse_resolution,
    reduce_resolution,
)
from torchdoct.sim import metrics

SYSTEM = {"name": "840nm-high", "wavelength_um": 0.84, "lateral_resolution_um": 4.9, "axial_resolution_um": 3.8}


# ----------------------------------------------------------------------------------------------------------
# helpers: a pixel-grid sum of Gaussian PSFs (common phase convention: exp(i·2kn·z_j), no carrier)
# ----------------------------------------------------------------------------------------------------------
def render_tzx(
    pos: np.ndarray, amp: np.ndarray, z_um: np.ndarray, x_um: np.ndarray, *, sx: float, sy: float, sz: float, k: float
) -> np.ndarray:
    """E[t, z_p, x_p] = Σ_j b_j·h(r_j − r_p)·exp(i2k z_j) at y_p = 0; pos [T, J, 3] (x, y, z) in µm."""
    out = np.empty((pos.shape[0], len(z_um), len(x_um)), dtype=np.complex128)
    for t in range(pos.shape[0]):
        x, y, z = pos[t, :, 0], pos[t, :, 1], pos[t, :, 2]
        c = amp * np.exp(-y * y / (2 * sy * sy)) * np.exp(2j * k * z)
        hz = np.exp(-((z_um[:, None] - z[None, :]) ** 2) / (2 * sz * sz))
        hx = np.exp(-((x[:, None] - x_um[None, :]) ** 2) / (2 * sx * sx))
        out[t] = (hz * c[None, :]) @ hx
    return out


def scatterers(
    rng: np.random.Generator,
    box: tuple[tuple[float, float], ...],
    density: float,
    n_frames: int,
    dt_s: float,
    d_um2_per_s: float,
    moving_fraction: float,
) -> np.ndarray:
    """Poisson scatterers in ``box`` ((x0,x1),(y0,y1),(z0,z1)); a fraction diffuses (N(0, 2DΔt) per axis)."""
    lo = np.array([b[0] for b in box])
    hi = np.array([b[1] for b in box])
    n = rng.poisson(density * np.prod(hi - lo))
    p0 = lo + (hi - lo) * rng.random((n, 3))
    moving = rng.random(n) < moving_fraction
    steps = rng.normal(0.0, math.sqrt(2 * d_um2_per_s * dt_s), (n_frames - 1, n, 3)) * moving[None, :, None]
    return np.concatenate([p0[None], p0[None] + np.cumsum(steps, axis=0)], axis=0)


def intensity_width(profile: np.ndarray, pitch: float, level: float) -> float:
    """Full width (µm) where the normalised profile crosses ``level`` (log-linear interpolation)."""
    i = profile / profile.max()
    k = int(np.argmax(i))

    def cross(step: int) -> float:
        j = k
        while i[j + step] > level:
            j += step
        a, b = math.log(i[j]), math.log(i[j + step])
        return (j + step * (math.log(level) - a) / (b - a)) * pitch

    return cross(1) - cross(-1)


# ----------------------------------------------------------------------------------------------------------
# formulas
# ----------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("orig,target", [(4.9, 9.8), (4.9, 14.7), (4.9, 18.0), (3.0, 3.1)])
def test_lateral_sigma_is_paper_eq4(orig, target):
    assert lateral_filter_sigma_um(orig, target) == pytest.approx(0.5 * math.sqrt((target**2 - orig**2) / 2), rel=1e-12)


@pytest.mark.parametrize("orig,target", [(3.8, 7.6), (3.8, 11.4), (3.8, 14.0)])
def test_axial_window_is_paper_eq8(orig, target):
    sigma_s = axial_window_sigma_per_um(orig, target)
    assert sigma_s == pytest.approx(2 * math.sqrt(math.log(2) / (target**2 - orig**2)), rel=1e-12)
    assert axial_filter_sigma_um(orig, target) == pytest.approx(1 / sigma_s, rel=1e-12)
    # Eq. 7: the target FWHM from the combined sigma
    s_total = math.sqrt(amplitude_sigma_axial_um(orig) ** 2 + axial_filter_sigma_um(orig, target) ** 2)
    assert 2 * math.sqrt(math.log(2)) * s_total == pytest.approx(target, rel=1e-12)


def test_finer_target_is_an_error_and_equal_is_identity():
    with pytest.raises(ValueError, match="finer than the original"):
        lateral_filter_sigma_um(4.9, 4.0)
    with pytest.raises(ValueError, match="finer than the original"):
        reduce_resolution(
            np.zeros((2, 4, 4), np.complex64), pitch_um={"z": 1, "x": 1}, system=SYSTEM, axial_resolution_um=3.0
        )
    assert lateral_filter_sigma_um(4.9, 4.9) == 0.0
    assert axial_window_sigma_per_um(3.8, 3.8) == math.inf
    field = np.ones((2, 4, 4), np.complex64)
    assert (
        reduce_resolution(
            field, pitch_um={"z": 1, "x": 1}, system=SYSTEM, lateral_resolution_um=4.9, axial_resolution_um=3.8
        )
        is field
    )
    t = torch.ones(2, 4, 4, dtype=torch.complex128)
    assert reduce_resolution(t, pitch_um={"z": 1, "x": 1}, system=SYSTEM) is t


def test_parse_resolution_labels():
    assert parse_resolution("original") == ResolutionTarget()
    assert parse_resolution("axial=14").label == "axial=14"
    assert parse_resolution("lateral=18, axial=14").label == "axial=14,lateral=18"
    assert parse_resolution("lateral=9.8").resolved(SYSTEM) == (9.8, 3.8)
    for bad in ("axial", "depth=3", "axial=x", "axial=14,axial=15", "axial=-1"):
        with pytest.raises(ValueError):
            parse_resolution(bad)


def test_bad_inputs():
    with pytest.raises(TypeError, match="complex"):
        reduce_resolution(
            np.ones((2, 4, 4), np.float32), pitch_um={"z": 1, "x": 1}, system=SYSTEM, lateral_resolution_um=9.8
        )
    with pytest.raises(ValueError, match="pitch_um"):
        reduce_resolution(np.ones((2, 4, 4), np.complex64), pitch_um={"z": 1}, system=SYSTEM, lateral_resolution_um=9.8)
    with pytest.raises(ValueError, match="axes"):
        reduce_resolution(
            np.ones((2, 4, 4), np.complex64),
            pitch_um={"z": 1, "x": 1},
            system=SYSTEM,
            lateral_resolution_um=9.8,
            axes="TYZX",
        )
    with pytest.raises(ValueError, match="edge_mode"):
        reduce_resolution(
            np.ones((2, 4, 4), np.complex64),
            pitch_um={"z": 1, "x": 1},
            system=SYSTEM,
            lateral_resolution_um=9.8,
            edge_mode="nearest",
        )
    with pytest.raises(ValueError, match="normalization"):
        reduce_resolution(
            np.ones((2, 4, 4), np.complex64),
            pitch_um={"z": 1, "x": 1},
            system=SYSTEM,
            lateral_resolution_um=9.8,
            normalization="energy",
        )


# ----------------------------------------------------------------------------------------------------------
# point-scatterer PSF widths
# ----------------------------------------------------------------------------------------------------------
def _point_psf(pz: float, px: float, nz: int, nx: int, frac=(0.37, 0.21)) -> tuple[np.ndarray, float, float]:
    z = np.arange(nz) * pz
    x = np.arange(nx) * px
    z0 = (nz // 2 + frac[0]) * pz
    x0 = (nx // 2 + frac[1]) * px
    sz = amplitude_sigma_axial_um(SYSTEM["axial_resolution_um"])
    sx = amplitude_sigma_lateral_um(SYSTEM["lateral_resolution_um"])
    e = np.exp(-((z[:, None] - z0) ** 2) / (2 * sz * sz) - (x[None, :] - x0) ** 2 / (2 * sx * sx) + 0.7j)
    return e[None].astype(np.complex128), z0, x0


@pytest.mark.parametrize(
    "lat,ax", [(None, 7.6), (None, 11.4), (None, 14.0), (9.8, None), (14.7, None), (18.0, None), (18.0, 14.0)]
)
@pytest.mark.parametrize("norm", ["power", "peak", "sum"])
def test_point_psf_has_the_target_width(lat, ax, norm):
    pz = px = 0.5
    e, _, _ = _point_psf(pz, px, 240, 240)
    r = reduce_resolution(
        e,
        pitch_um={"z": pz, "x": px},
        system=SYSTEM,
        lateral_resolution_um=lat,
        axial_resolution_um=ax,
        normalization=norm,
    )
    i = np.abs(r[0]) ** 2
    kz, kx = np.unravel_index(np.argmax(i), i.shape)
    fwhm_z = intensity_width(i[:, kx], pz, 0.5)
    w_x = intensity_width(i[kz, :], px, math.exp(-2))
    assert fwhm_z == pytest.approx(ax or SYSTEM["axial_resolution_um"], rel=0.02)
    assert w_x == pytest.approx(lat or SYSTEM["lateral_resolution_um"], rel=0.02)
    # normalization: power keeps Σ|E|² (mean intensity of a random medium), peak keeps the PSF peak
    p_in, p_out = float((np.abs(e) ** 2).sum()), float(i.sum())
    r_lat = amplitude_sigma_lateral_um(lat) / amplitude_sigma_lateral_um(4.9) if lat else 1.0
    r_ax = amplitude_sigma_axial_um(ax) / amplitude_sigma_axial_um(3.8) if ax else 1.0
    expected = {"power": 1.0, "peak": r_lat * r_ax, "sum": 1.0 / (r_lat * r_ax)}[norm]
    assert p_out / p_in == pytest.approx(expected, rel=1e-6)


def test_point_psf_widths_in_a_volume_along_y_and_x():
    """TYZX: the lateral Gaussian acts on every en-face plane (Y and X)."""
    p = 0.5
    y = x = np.arange(120) * p
    z = np.arange(3) * 1.0
    sx = amplitude_sigma_lateral_um(4.9)
    sz = amplitude_sigma_axial_um(3.8)
    e = np.exp(
        -((y[:, None, None] - 30.2) ** 2) / (2 * sx * sx)
        - (z[None, :, None] - 1.0) ** 2 / (2 * sz * sz)
        - (x[None, None, :] - 29.9) ** 2 / (2 * sx * sx)
    )[None].astype(np.complex64)
    r = reduce_resolution(
        torch.from_numpy(e), pitch_um={"y": p, "z": 1.0, "x": p}, system=SYSTEM, lateral_resolution_um=14.7, axes="TYZX"
    )
    assert isinstance(r, torch.Tensor) and r.dtype == torch.complex64
    i = (r.abs() ** 2)[0, :, 1, :].double().numpy()
    ky, kx = np.unravel_index(np.argmax(i), i.shape)
    assert intensity_width(i[:, kx], p, math.exp(-2)) == pytest.approx(14.7, rel=0.02)
    assert intensity_width(i[ky, :], p, math.exp(-2)) == pytest.approx(14.7, rel=0.02)


def test_point_psf_width_at_a_coarse_pitch():
    """At 1.5 µm (z) × 2 µm (x) pixels the exact Gaussian transfer function keeps the widths."""
    pz, px = 1.5, 2.0
    e, _, _ = _point_psf(pz, px, 120, 120)
    r = reduce_resolution(
        e, pitch_um={"z": pz, "x": px}, system=SYSTEM, lateral_resolution_um=18.0, axial_resolution_um=14.0
    )
    i = np.abs(r[0]) ** 2
    kz, kx = np.unravel_index(np.argmax(i), i.shape)
    # Gaussian fit of log-intensity near the peak (sampling-free width estimate)
    for prof, pitch, conv in ((i[:, kx], pz, "axial"), (i[kz, :], px, "lateral")):
        sel = prof > prof.max() * 1e-3
        c = np.polyfit(np.flatnonzero(sel) * pitch, np.log(prof[sel]), 2)
        s_amp = math.sqrt(-1.0 / c[0])  # |E|² ∝ exp(−u²/s²)
        width = 2 * math.sqrt(math.log(2)) * s_amp if conv == "axial" else 2 * math.sqrt(2) * s_amp
        assert width == pytest.approx(14.0 if conv == "axial" else 18.0, rel=0.02)


# ----------------------------------------------------------------------------------------------------------
# filter mechanics: edges, dtypes, axial centre
# ----------------------------------------------------------------------------------------------------------
def test_edge_modes_on_a_constant_field():
    c = torch.full((1, 40, 30), 2.0 - 1.0j, dtype=torch.complex128)
    y = gaussian_filter_axis(c, 2, 3.0, edge_mode="reflect")
    assert torch.allclose(y, c, atol=1e-12)
    y = gaussian_filter_axis(c, 2, 3.0, edge_mode="wrap")
    assert torch.allclose(y, c, atol=1e-12)
    y = gaussian_filter_axis(c, 2, 3.0, edge_mode="constant")
    assert torch.allclose(y[..., 15], c[..., 15], atol=1e-6)
    j = np.arange(-60, 61)
    g = np.exp(-(j**2) / 18.0)
    inside = g[(j >= 0) & (j < 30)].sum() / g.sum()  # the part of the sampled kernel that is on the grid
    assert float(y[0, 0, 0].abs()) / abs(2 - 1j) == pytest.approx(inside, rel=1e-6)
    g = gaussian_filter_axis(c, 1, 2.0, gain=1.7)
    assert torch.allclose(g, 1.7 * c, atol=1e-12)


def test_wrap_mode_commutes_with_circular_shift():
    g = torch.Generator().manual_seed(3)
    x = torch.randn(2, 32, 24, dtype=torch.complex128, generator=g)
    a = gaussian_filter_axis(torch.roll(x, 5, dims=2), 2, 1.3, edge_mode="wrap")
    b = torch.roll(gaussian_filter_axis(x, 2, 1.3, edge_mode="wrap"), 5, dims=2)
    assert torch.allclose(a, b, atol=1e-12)


def test_numpy_in_numpy_out_and_dtypes():
    rng = np.random.default_rng(0)
    for dt in (np.complex64, np.complex128):
        x = (rng.standard_normal((3, 20, 16)) + 1j * rng.standard_normal((3, 20, 16))).astype(dt)
        x.flags.writeable = False
        y = reduce_resolution(
            x, pitch_um={"z": 1.0, "x": 1.5}, system=SYSTEM, axial_resolution_um=7.6, lateral_resolution_um=9.8
        )
        assert isinstance(y, np.ndarray) and y.dtype == dt and y.shape == x.shape
        t = reduce_resolution(
            torch.from_numpy(x.copy()),
            pitch_um={"z": 1.0, "x": 1.5},
            system=SYSTEM,
            axial_resolution_um=7.6,
            lateral_resolution_um=9.8,
        )
        np.testing.assert_allclose(t.numpy(), y, rtol=0, atol=1e-5 if dt == np.complex64 else 1e-12)


def test_axial_centroid_window_follows_a_depth_carrier():
    """Measured data carry exp(i2π f_c z): the centroid window equals the zero-centred one on the envelope."""
    e, _, _ = _point_psf(1.0, 1.0, 200, 40)
    fc = 0.31  # cycles per depth pixel
    carrier = np.exp(2j * np.pi * fc * np.arange(200))[None, :, None]
    assert depth_spectrum_center(e * carrier) == pytest.approx(fc, abs=1e-3)
    assert abs(depth_spectrum_center(e)) < 1e-3
    ref = reduce_resolution(e, pitch_um={"z": 1.0, "x": 1.0}, system=SYSTEM, axial_resolution_um=14.0)
    got = reduce_resolution(
        e * carrier, pitch_um={"z": 1.0, "x": 1.0}, system=SYSTEM, axial_resolution_um=14.0, axial_center="centroid"
    )
    np.testing.assert_allclose(np.abs(got), np.abs(ref), atol=1e-3 * np.abs(ref).max())
    wrong = reduce_resolution(e * carrier, pitch_um={"z": 1.0, "x": 1.0}, system=SYSTEM, axial_resolution_um=14.0)
    assert np.abs(wrong).max() < 0.1 * np.abs(ref).max()  # a zero-centred window misses the carrier band


# ----------------------------------------------------------------------------------------------------------
# reduced high-resolution simulation == simulation at the target resolution (same scatterers)
# ----------------------------------------------------------------------------------------------------------
N_FRAMES = 8
DT_S = 0.2048
DELAYS = (0.2048, 0.6144)


def _stats(e: np.ndarray) -> tuple[float, float, float]:
    """Mean intensity, mean LIV and mean OCDS over the pixels of E [T, Z, X]."""
    i = torch.from_numpy(np.abs(e) ** 2).movedim(0, -1)
    times = [t * DT_S for t in range(e.shape[0])]
    return (float(i.mean()), float(metrics.liv(i).mean()), float(metrics.ocds(i, times, delay_range_s=DELAYS).mean()))


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
@pytest.mark.parametrize("case", ["axial", "lateral"])
def test_reduced_equals_direct_simulation(case):
    """Same scatterers (static + diffusing), 8 frames: the reduced high-res sequence matches a direct
    simulation at the target resolution pixel by pixel (``peak``) and in mean intensity, LIV and OCDS
    within the Monte-Carlo standard error over realizations; ``power`` keeps the high-res mean intensity."""
    rng = np.random.default_rng(11 if case == "axial" else 12)
    k = wavenumber_per_um(0.84)
    sx0, sz0 = amplitude_sigma_lateral_um(4.9), amplitude_sigma_axial_um(3.8)
    if case == "axial":
        pz, px, nz, nx = 1.0, 1.5, 112, 10
        target = {"axial_resolution_um": 14.0}
        sxt, szt = sx0, amplitude_sigma_axial_um(14.0)
        halo = int(math.ceil(5 * axial_filter_sigma_um(3.8, 14.0) / pz)) + 1
        inner = (slice(halo, nz - halo), slice(None))
    else:
        pz, px, nz, nx = 1.5, 1.0, 8, 84
        target = {"lateral_resolution_um": 18.0}
        sxt, szt = amplitude_sigma_lateral_um(18.0), sz0
        halo = int(math.ceil(5 * lateral_filter_sigma_um(4.9, 18.0) / px)) + 1
        inner = (slice(None), slice(halo, nx - halo))
    z_um, x_um = np.arange(nz) * pz, np.arange(nx) * px
    mz, mx = 6 * szt + 2, 6 * sxt + 2
    box = ((-mx, x_um[-1] + mx), (-6 * sx0, 6 * sx0), (-mz, z_um[-1] + mz))
    rows = {"high": [], "reduced_peak": [], "reduced_power": [], "direct": []}
    field_err = []
    for _ in range(40):
        pos = scatterers(rng, box, 0.03, N_FRAMES, DT_S, 0.005, 0.5)
        amp = np.ones(pos.shape[1])
        high = render_tzx(pos, amp, z_um, x_um, sx=sx0, sy=sx0, sz=sz0, k=k)
        direct = render_tzx(pos, amp, z_um, x_um, sx=sxt, sy=sx0, sz=szt, k=k)  # y keeps the original PSF
        peak = reduce_resolution(high, pitch_um={"z": pz, "x": px}, system=SYSTEM, normalization="peak", **target)
        power = reduce_resolution(high, pitch_um={"z": pz, "x": px}, system=SYSTEM, **target)
        sl = (slice(None),) + inner
        field_err.append(np.sqrt(np.mean(np.abs(peak[sl] - direct[sl]) ** 2) / np.mean(np.abs(direct[sl]) ** 2)))
        rows["high"].append(_stats(high[sl]))
        rows["reduced_peak"].append(_stats(peak[sl]))
        rows["reduced_power"].append(_stats(power[sl]))
        rows["direct"].append(_stats(direct[sl]))
    a = {k_: np.array(v) for k_, v in rows.items()}
    n = a["direct"].shape[0]
    assert max(field_err) < 1e-4, max(field_err)

    def check(x, y, col, what):
        se = math.sqrt(np.var(x[:, col], ddof=1) / n + np.var(y[:, col], ddof=1) / n)
        d = abs(x[:, col].mean() - y[:, col].mean())
        assert se > 0 and d <= 4 * se, f"{what}: {x[:, col].mean():.5g} vs {y[:, col].mean():.5g} (SE {se:.3g})"

    for col, what in enumerate(("mean intensity", "LIV", "OCDS")):
        check(a["reduced_peak"], a["direct"], col, f"{case} {what}")
        if col:  # LIV and OCDS are scale invariant: the normalization does not change them
            np.testing.assert_allclose(a["reduced_power"][:, col], a["reduced_peak"][:, col], rtol=1e-6, atol=1e-9)
    check(a["reduced_power"], a["high"], 0, f"{case} power-normalized mean intensity vs high resolution")
    # the resolution change is visible: the direct target simulation has a different mean intensity
    ratio = (szt / sz0) * (sxt / sx0)
    assert a["direct"][:, 0].mean() / a["high"][:, 0].mean() == pytest.approx(ratio, rel=0.15)
