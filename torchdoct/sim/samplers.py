"""Samplers of the point simulator: the scatterers of each population, their motion and their field.

One sampler per kind of population (:attr:`torchdoct.sim.plan.PopulationPlan.sampler`): ``static`` (one
evaluation, constant over frames), ``drift`` (straight paths: flow and random-ballistic motion, with the
scatterers that enter the truncation box during the protocol), ``diffusive`` (random walks with drift,
per-frame draws) and ``periodic`` (pure diffusion on a periodic cell, in the fused kernel of
:mod:`torchdoct.sim.kernel`). :func:`scene_field` sums them over a scene's populations for one chunk of
blocks; :func:`torchdoct.simulate` adds the noise and runs the chunks.

Kept whole (over 600 lines): the four samplers share the draw, compaction and evaluation kernels (the
amplitude with its truncation or taper, the straight-path evaluation, the culling against the box), and
the reproducibility contract of :mod:`torchdoct.sim.simulate` is easiest to check on them in one place.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from ..conventions import TAPER_START, amplitude_sigma_axial_um, amplitude_sigma_lateral_um, wavenumber_per_um
from . import kernel
from .config import Population, Scene
from .plan import BLOCK_TRIALS, Plan, PopulationPlan, ellipsoid_entry_bound
from .streams import CapacityError, Draws

__all__ = ["unit_directions", "scene_field", "SAMPLERS"]

_F64 = torch.float64
#: Position of unused slots (µm): far enough that the PSF amplitude underflows to exactly 0.
_FAR = 1.0e6
_TWO_PI = 2.0 * math.pi


def unit_directions(u: torch.Tensor, law: str) -> torch.Tensor:
    """Unit vectors [..., 3] from uniforms ``u`` [..., 2] on [0, 1).

    ``law``: ``"isotropic"`` (cos of the polar angle uniform on [−1, 1]) or ``"uniform-angles"`` (the
    polar angle uniform on [0, π], the reference paper's text and code; physics.md §10.2). The azimuth
    is uniform on [0, 2π). The polar angle is measured from the depth (z) axis.
    """
    return torch.stack(_direction_components(u[..., 0], u[..., 1], law), dim=-1)


def _direction_components(u0: torch.Tensor, u1: torch.Tensor, law: str) -> tuple[torch.Tensor, ...]:
    """The (x, y, z) components of :func:`unit_directions` from the two uniforms."""
    if law == "isotropic":
        mu = 2.0 * u0 - 1.0
    else:
        mu = torch.cos(math.pi * u0)
    st = torch.sqrt(torch.clamp(1.0 - mu * mu, min=0.0))
    phi = _TWO_PI * u1
    return st * torch.cos(phi), st * torch.sin(phi), mu


def _directions(draws: Draws, law: str, n: int) -> torch.Tensor:
    """Unit vectors [N, n, 3] of one direction law (see :func:`unit_directions`)."""
    return unit_directions(draws.rand(n, 2), law)


def _velocities(pop: Population, draws: Draws, n: int) -> torch.Tensor:
    """Drift velocity of each scatterer (µm/s), [N, n, 3]: flow + Σ ballistic speed·direction."""
    v = (
        torch.tensor(pop.flow_velocity_um_per_s, dtype=_F64, device=draws.device)
        .expand(BLOCK_TRIALS * len(draws.gens), n, 3)
        .clone()
    )
    for b in pop.ballistic:
        v += b.speed_um_per_s * _directions(draws, b.directions, n)
    return v


def _inside(pos: torch.Tensor, half: torch.Tensor) -> torch.Tensor:
    return (pos.abs() <= half).all(dim=-1)


@dataclass
class _Optics:
    kn: torch.Tensor  # [S] 2πn/λ (rad/µm), float64
    a_lat: torch.Tensor  # [S] 1/(2 s_x²), working dtype
    a_ax: torch.Tensor  # [S] 1/(2 s_z²), working dtype
    ry: list[float]  # [S] s_x²/s_y² (float64; exactly 1.0 for an isotropic lateral PSF)

    @classmethod
    def of(cls, scene: Scene, dtype: torch.dtype, device: torch.device) -> _Optics:
        kn = [wavenumber_per_um(s.wavelength_um, s.refractive_index) for s in scene.systems]
        sx = [amplitude_sigma_lateral_um(s.lateral_resolution_um) for s in scene.systems]
        sy = [amplitude_sigma_lateral_um(s.lateral_widths_um[1]) for s in scene.systems]
        sz = [amplitude_sigma_axial_um(s.axial_resolution_um) for s in scene.systems]
        return cls(
            torch.tensor(kn, dtype=_F64, device=device),
            torch.tensor([0.5 / x**2 for x in sx], dtype=dtype, device=device),
            torch.tensor([0.5 / z**2 for z in sz], dtype=dtype, device=device),
            [1.0 if x == y else (x / y) ** 2 for x, y in zip(sx, sy)],
        )


def _sum_field(amp: torch.Tensor, phase: torch.Tensor, dim: int) -> torch.Tensor:
    """Σ amp·e^{i·phase} along ``dim`` (real arithmetic: complex exp is slow on CPU)."""
    return torch.complex((amp * torch.cos(phase)).sum(dim), (amp * torch.sin(phase)).sum(dim))


#: Exponents below -_EXP_FLOOR are clamped and their amplitude set to exactly 0: the PSF amplitude
#: there (e^-60 ~ 1e-26) is far below any truncation tolerance, and exp() of large negative
#: arguments is several times slower.
_EXP_FLOOR = 60.0


def _truncated_amplitude(exponent: torch.Tensor, log_tol: float) -> torch.Tensor:
    """PSF amplitude ``exp(exponent)`` truncated at the tolerance: exactly 0 where ``exponent < ln tol``
    (``exponent`` is overwritten). Below it the exponent is first set to ``-_EXP_FLOOR``: ``exp`` of
    arguments that underflow is 20-30 times slower than of moderate ones."""
    floor = torch.nn.functional.threshold(exponent, log_tol, -_EXP_FLOOR, inplace=True)
    return torch.nn.functional.threshold(torch.exp(floor, out=floor), 2.0 * math.exp(-_EXP_FLOOR), 0.0, inplace=True)


def _amplitude(exponent: torch.Tensor) -> torch.Tensor:
    """``exp(exponent)`` with arguments below ``-_EXP_FLOOR`` giving exactly 0 (in place on exponent)."""
    return torch.nn.functional.threshold(torch.exp(exponent.clamp_(min=-_EXP_FLOOR)), 2.0 * math.exp(-_EXP_FLOOR), 0.0)


def _taper_window(exponent: torch.Tensor, log_tol: float) -> torch.Tensor:
    """The taper window (:func:`torchdoct.conventions.taper_window`) of PSF exponents, in their dtype:
    1 above ``TAPER_START·ln tol``, 0 below ``ln tol``, ``1 − t³(10 − 15t + 6t²)`` between
    (``t = (exponent/ln tol − a)/(1 − a)``). The torch code's twin of the fused kernel's window."""
    t = ((exponent / log_tol - TAPER_START) / (1.0 - TAPER_START)).clamp_(0.0, 1.0)
    return 1.0 - t * t * t * (10.0 - 15.0 * t + 6.0 * t * t)


def _path_coefficients(
    p: torch.Tensor,
    v: torch.Tensor | None,
    t_ref: torch.Tensor | None,
    kn: float,
    a_lat: float,
    a_ax: float,
    ry: float = 1.0,
):
    """Per-scatterer coefficients of the field exponent of one system, about the closest approach.

    For a straight path ``r(t) = p + v·(t − t_ref)`` the PSF exponent is a quadratic in t; written
    about its vertex ``t*`` it is ``e* + a2·(t − t*)²`` (both ≤ 0, so no cancellation in float32),
    and the phase is ``φ* + ω·(t − t*)`` with ``φ* = (2kn·z(t*)) mod 2π`` and ``ω = 2kn·v_z``.
    Inputs float64 [3, N, C] (component-major) / [N, C]; returns float64 (e*, a2, t*, φ*, ω) of
    shape [N, C]. ``ry = s_x²/s_y²`` (1: the isotropic lateral PSF).
    """
    px, py, pz = p

    def norm_w(x, y, z, xx, yy, zz):  # −(a_lat·(x·xx + ry·y·yy) + a_ax·z·zz)
        out = x * xx
        if ry == 1.0:
            out.addcmul_(y, yy)
        else:
            out.addcmul_(y, yy, value=ry)
        return out.mul_(-a_lat).addcmul_(z, zz, value=-a_ax)

    if v is None:
        return norm_w(px, py, pz, px, py, pz), None, None, torch.remainder(pz * (2.0 * kn), _TWO_PI), None
    vx, vy, vz = v * (p[:1] < 0.5 * _FAR)  # unused slots stand still
    a2 = norm_w(vx, vy, vz, vx, vy, vz)
    # exponent(t_ref + u) = e(p) + 2u·(−(p·v)_w) + a2·u², stationary at u = (p·v)_w / a2
    shift = norm_w(px, py, pz, vx, vy, vz).div_(a2).neg_().nan_to_num_(nan=0.0, posinf=0.0, neginf=0.0)
    t_star = t_ref + shift
    rx, ry_, rz = torch.addcmul(px, vx, shift), torch.addcmul(py, vy, shift), torch.addcmul(pz, vz, shift)
    e = norm_w(rx, ry_, rz, rx, ry_, rz)
    phi = torch.remainder(rz.mul_(2.0 * kn), _TWO_PI)
    return e, a2, t_star, phi, vz * (2.0 * kn)


def _eval_paths(
    p_ref: torch.Tensor,
    vel: torch.Tensor | None,
    t_ref: torch.Tensor | None,
    times: torch.Tensor,
    optics: _Optics,
    systems: tuple[int, ...],
    refl: float,
    dtype: torch.dtype,
    tolerance: float,
    taper: bool = False,
) -> torch.Tensor:
    """Field [N, len(systems), T] of scatterers on straight paths ``p_ref + vel·(t − t_ref)``
    (positions and velocities component-major, [3, N, C]); ``taper``: amplitudes times the taper window.

    ``vel is None`` means static scatterers: one evaluation, repeated over the frames.
    """
    _, N, C = p_ref.shape
    T = times.numel()
    cdt = _complex_of(dtype)
    if vel is None:
        out = torch.empty(N, len(systems), dtype=cdt, device=p_ref.device)
        for k, s in enumerate(systems):
            e, _, _, phi, _ = _path_coefficients(
                p_ref, None, None, float(optics.kn[s]), float(optics.a_lat[s]), float(optics.a_ax[s]), optics.ry[s]
            )
            e = e.to(dtype)
            w = _taper_window(e, math.log(tolerance)) if taper else None
            amp = _amplitude(e)
            if w is not None:
                amp = amp * w
            if refl != 1.0:
                amp = amp * refl
            out[:, k] = _sum_field(amp, phi.to(dtype), dim=1)
        return out[:, :, None].expand(N, len(systems), T)
    log_tol = math.log(tolerance)
    if dtype == torch.float32 and p_ref.device.type == "cpu":
        # the fused kernel: float64 coefficients, float32 evaluation, exact sums (torchdoct.sim.kernel)
        acc = kernel.path_fields(
            p_ref,
            vel,
            t_ref,
            [2.0 * float(optics.kn[s]) / _TWO_PI for s in systems],
            [float(optics.a_lat[s]) for s in systems],
            [float(optics.a_ax[s]) for s in systems],
            times,
            log_tol,
            ry=[optics.ry[s] for s in systems],
            taper=taper,
        )
        field = kernel.sums_to_field(acc)
        return field * refl if refl != 1.0 else field
    out = torch.empty(N, len(systems), T, dtype=cdt, device=p_ref.device)
    for k, s in enumerate(systems):
        coef = _path_coefficients(
            p_ref, vel, t_ref, float(optics.kn[s]), float(optics.a_lat[s]), float(optics.a_ax[s]), optics.ry[s]
        )
        out[:, k] = _eval_straight(*coef, times, log_tol, refl, dtype, taper)
    return out


#: Frames evaluated together for straight paths: long protocols are cut into tiles of this many
#: frames and each tile evaluates only the paths visible during it.
_TILE_FRAMES = 64
#: (path, frame) pairs evaluated at once: small enough for the temporaries to stay in cache.
_PIECE_ELEMENTS = 1 << 18
_PAD_EXPONENT = -1.0e30


def _eval_straight(
    e: torch.Tensor,
    a2: torch.Tensor,
    t_star: torch.Tensor,
    phi: torch.Tensor,
    omega: torch.Tensor,
    times: torch.Tensor,
    log_tol: float,
    refl: float,
    dtype: torch.dtype,
    taper: bool = False,
) -> torch.Tensor:
    """Field [N, T] of straight paths, counting each path only at the frames where its amplitude
    exceeds the tolerance.

    With the exponent ``e* + a2·(t − t*)²`` a path is above ``tolerance`` during
    ``|t − t*| ≤ √((ln tol − e*)/a2)``. Per block of 64 trials and per tile of :data:`_TILE_FRAMES`
    frames, the paths visible in the tile are packed to the front of each trial's row (padded to
    the block's longest row with paths of zero amplitude) and evaluated densely, the exponent
    truncated below the tolerance; each trial's field is the sum over its row. Shapes depend only
    on the block's own paths, so the bits do not depend on the chunk. Dense rows cost about 5 ns per
    (path, frame) against about 60 ns for gathering only the visible pairs.
    """
    if dtype == torch.float32 and e.device.type == "cpu":
        # the fused kernel (torchdoct.sim.kernel): phases in turns, exact sums
        acc = kernel.eval_straight(e, a2, t_star, phi / _TWO_PI, omega / _TWO_PI, times, log_tol, taper=taper)
        field = kernel.sums_to_field(acc)
        return field * refl if refl != 1.0 else field
    N, C = e.shape
    T = times.numel()
    dev = e.device
    visible = e >= log_tol  # paths that ever reach the tolerance
    re = torch.zeros(N, T, dtype=dtype, device=dev)
    im = torch.zeros(N, T, dtype=dtype, device=dev)
    if not bool(visible.any()):
        return torch.complex(re, im)
    if T > _TILE_FRAMES:
        moving = a2 < 0
        half = torch.sqrt(
            torch.where(moving, (log_tol - e) / torch.where(moving, a2, -torch.ones_like(a2)), torch.zeros_like(e))
        )
        lo = torch.where(moving, t_star - half, torch.full_like(e, -math.inf))
        hi = torch.where(moving, t_star + half, torch.full_like(e, math.inf))
    coef = (e, a2, t_star, phi, omega)
    pad = torch.tensor([_PAD_EXPONENT, 0.0, 0.0, 0.0, 0.0], dtype=dtype, device=dev)
    t = times.to(dtype)
    for b0 in range(0, N, BLOCK_TRIALS):
        rows = slice(b0, min(N, b0 + BLOCK_TRIALS))
        for f0 in range(0, T, _TILE_FRAMES):
            f1 = min(T, f0 + _TILE_FRAMES)
            vis = visible[rows]
            if T > _TILE_FRAMES:
                vis = vis & (lo[rows] <= times[f1 - 1]) & (hi[rows] >= times[f0])
            count = vis.sum(1)
            width = int(count.max())
            if width == 0:
                continue
            # visible paths to the front of each row, in order (masked_select and masked_scatter both
            # go in row-major order); the rest of the row is padding
            front = torch.arange(width, device=dev) < count[:, None]
            packed = pad.view(1, 5, 1).expand(vis.shape[0], 5, width).clone()  # [rows, 5, width]
            for i, x in enumerate(coef):
                packed[:, i].masked_scatter_(front, x[rows].masked_select(vis).to(dtype))
            per_piece = max(1, _PIECE_ELEMENTS // (width * (f1 - f0)))
            tt = t[f0:f1]
            for i0 in range(0, vis.shape[0], per_piece):
                c = packed[i0 : i0 + per_piece, :, :, None]  # [k, 5, width, 1]
                tau = tt - c[:, 2]  # [k, width, frames]
                ex = tau * tau
                ex.mul_(c[:, 1]).add_(c[:, 0])
                w = _taper_window(ex, log_tol) if taper else None
                amp = _truncated_amplitude(ex, log_tol)
                if w is not None:
                    amp.mul_(w)
                if refl != 1.0:
                    amp.mul_(refl)
                ph = tau.mul_(c[:, 4]).add_(c[:, 3])
                out = slice(b0 + i0, b0 + i0 + c.shape[0])
                re[out, f0:f1] = (amp * torch.cos(ph)).sum(1)
                im[out, f0:f1] = amp.mul_(torch.sin(ph, out=ph)).sum(1)
    return torch.complex(re, im)


def _path_meets_box(
    p_ref: torch.Tensor,
    vel: torch.Tensor | None,
    t_ref: torch.Tensor | None,
    T: float,
    half: tuple[float, float, float],
) -> torch.Tensor:
    """Whether ``p_ref + vel·(t − t_ref)`` is inside the box for some t in [0, T] (slab test;
    positions and velocities [3, N, C])."""
    if vel is None:
        return (p_ref[0].abs() <= half[0]) & (p_ref[1].abs() <= half[1]) & (p_ref[2].abs() <= half[2])
    lo = torch.zeros(p_ref.shape[1:], dtype=p_ref.dtype, device=p_ref.device)
    hi = torch.full_like(lo, T)
    inf = torch.full_like(lo, math.inf)
    for a in range(3):
        v = vel[a]
        p = p_ref[a]
        moving = v != 0
        vs = torch.where(moving, v, torch.ones_like(v))
        t1 = t_ref + (-half[a] - p) / vs
        t2 = t_ref + (half[a] - p) / vs
        inside = p.abs() <= half[a]
        tmin = torch.where(moving, torch.minimum(t1, t2), torch.where(inside, -inf, inf))
        tmax = torch.where(moving, torch.maximum(t1, t2), torch.where(inside, inf, -inf))
        lo = torch.maximum(lo, tmin)
        hi = torch.minimum(hi, tmax)
    return lo <= hi


def _eval_culled(pp: PopulationPlan, pop: Population, p_ref, vel, t_ref, times, optics, dtype, plan):
    """Evaluate each group of systems on the scatterers that can reach its own PSF box.

    ``p_ref``, ``vel``: [3, N, C] (component-major)."""
    N = p_ref.shape[1]
    S = optics.kn.numel()
    if vel is not None and dtype == torch.float32 and p_ref.device.type == "cpu":
        # the fused kernel skips, per system, the paths that stay below the tolerance: no culling here
        return _eval_paths(
            p_ref,
            vel,
            t_ref,
            times,
            optics,
            tuple(range(S)),
            pop.reflectivity,
            dtype,
            plan.truncation_tolerance,
            plan.truncation == "taper",
        )
    out = torch.empty(N, S, times.numel(), dtype=_complex_of(dtype), device=p_ref.device)
    T = float(times[-1])
    for half, idx, _, cap in pp.system_groups:
        if tuple(half) == tuple(pp.domain_half_widths_um):
            sel = (p_ref, vel, t_ref)
        else:
            mask = _path_meets_box(p_ref, vel, t_ref, T, half)
            tensors = [t for t in (p_ref, vel, t_ref) if t is not None]
            _, got = _compact(mask, cap, f"population {pp.index} systems {idx}", *tensors, fill=(_FAR, 0.0, 0.0))
            sel = (got[0], got[1], got[2]) if vel is not None else (got[0], None, None)
        out[:, list(idx)] = _eval_paths(
            *sel,
            times,
            optics,
            tuple(idx),
            pop.reflectivity,
            dtype,
            plan.truncation_tolerance,
            plan.truncation == "taper",
        )
    return out


def _complex_of(dtype: torch.dtype) -> torch.dtype:
    return torch.complex64 if dtype == torch.float32 else torch.complex128


def _uniform_box(draws: Draws, n: torch.Tensor, cap: int, half: tuple[float, float, float]):
    """Poisson points uniform in a box: positions [N, cap, 3] (unused slots far away), valid mask."""
    h = torch.tensor(half, dtype=_F64, device=draws.device)
    pos = (2.0 * draws.rand(cap, 3) - 1.0) * h
    valid = torch.arange(cap, device=draws.device)[None, :] < n[:, None]
    pos = torch.where(valid[..., None], pos, torch.full_like(pos, _FAR))
    return pos, valid


def _compact(mask: torch.Tensor, cap: int, what: str, *tensors: torch.Tensor, fill=None, keep: bool = False):
    """Move the True entries of ``mask`` [N, P] to the front (order kept), keep ``cap`` slots.

    ``tensors``: [..., N, P] (leading dims, e.g. components, broadcast against the mask); returns the
    valid mask [N, cap] and the tensors [..., N, cap], slots past the count set to ``fill`` (one value
    per tensor, default 0). ``keep``: only as many slots as the largest count (at least one)."""
    n = mask.sum(1)
    if int(n.max()) > cap:
        raise CapacityError(f"{what}: {int(n.max())} entries exceed the {cap} reserved slots")
    if keep:
        cap = max(1, int(n.max()))
    valid = torch.arange(cap, device=mask.device)[None, :] < n[:, None]
    out = []
    for i, t in enumerate(tensors):
        c = torch.full((*t.shape[:-1], cap), 0.0 if fill is None else fill[i], dtype=t.dtype, device=t.device)
        out.append(c.masked_scatter_(valid, t.masked_select(mask)))
    return valid, out


def _simulate_static(pp: PopulationPlan, pop: Population, draws: Draws, times, optics, dtype, plan):
    n = draws.poisson(pp.expected_scatterers_per_trial, pp.capacity, f"population {pp.index} count")
    pos, _ = _uniform_box(draws, n, pp.capacity, pp.domain_half_widths_um)
    return _eval_culled(pp, pop, pos.permute(2, 0, 1).contiguous(), None, None, times, optics, dtype, plan)


def _simulate_drift(pp: PopulationPlan, pop: Population, draws: Draws, times, optics, dtype, plan):
    """Straight paths that meet the tolerance ellipsoid during the protocol (see :mod:`torchdoct.sim.plan`).

    The Poisson counts come from the blocks' generators; every path's numbers come from the
    counter-based uniforms of its block's key (:func:`torchdoct.sim.kernel.drift_paths`): initial paths
    uniform in the ellipsoid, and entrants. In coordinates scaled by H the ellipsoid is the unit ball
    and a path of velocity v has velocity w = v/H; such paths enter at the rate ρ·Hx·Hy·Hz·π·|w|.
    Velocities are drawn from the law and kept with probability |w|/w_max; the impact point is
    uniform on the unit disk across w, the entry point where that line meets the sphere on its way
    in, the time uniform. Positions and velocities are component-major ([3, N, slots], float64)."""
    H = pp.domain_half_widths_um
    n0_mean = 4.0 * math.pi / 3.0 * pp.density_per_um3 * math.prod(H)
    n0 = draws.poisson(n0_mean, pp.capacity, f"population {pp.index} count")
    E = pp.entry_capacity if pp.entry_proposal_capacity else 0
    T = float(times[-1])
    if E:
        n_prop = draws.poisson(
            pp.entry_proposal_rate_per_s * T, pp.entry_proposal_capacity, f"population {pp.index} entrants"
        )
    else:
        n_prop = torch.zeros_like(n0)
    keys = draws.keys()
    ballistic = [(b.speed_um_per_s, 0 if b.directions == "isotropic" else 1) for b in pop.ballistic]
    try:
        p, v, t_ref, _ = kernel.drift_paths(
            keys,
            n0,
            n_prop,
            tuple(H),
            tuple(pop.flow_velocity_um_per_s),
            ballistic,
            ellipsoid_entry_bound(pop, H),
            T,
            E,
        )
    except OverflowError:
        raise CapacityError(
            f"population {pp.index} entrants: accepted entrants exceed the {E} reserved slots"
        ) from None
    dev = draws.device
    return _eval_culled(pp, pop, p.to(dev), v.to(dev), t_ref.to(dev), times, optics, dtype, plan)


def _shell_points(draws: Draws, P: int, inner: tuple, outer: tuple) -> torch.Tensor:
    """Points uniform in the shell between two centred boxes, [N, P, 3] (three disjoint slab pairs)."""
    R = torch.tensor(inner, dtype=_F64, device=draws.device)
    O = torch.tensor(outer, dtype=_F64, device=draws.device)
    # slab a: |x_a| in (R_a, O_a], axes before a within R, axes after a within O
    vols = []
    for a in range(3):
        v = O[a] - R[a]
        for b in range(3):
            if b < a:
                v = v * R[b]
            elif b > a:
                v = v * O[b]
        vols.append(v)
    vols = torch.stack(vols)
    cum = torch.cumsum(vols, 0) / vols.sum()
    u = draws.rand(P, 5)
    slab = torch.searchsorted(cum, u[..., 0].contiguous(), right=True).clamp(max=2)
    side = torch.where(u[..., 1] < 0.5, -1.0, 1.0).to(_F64)
    pts = []
    for b in range(3):
        # coordinate b: in the shell part if b is the slab axis, else within R (b before the
        # slab axis) or within O (b after it)
        lim = torch.where(slab > b, R[b], O[b])
        inner_c = (2.0 * u[..., 2 + b] - 1.0) * lim
        shell_c = side * (R[b] + u[..., 2 + b] * (O[b] - R[b]))
        pts.append(torch.where(slab == b, shell_c, inner_c))
    return torch.stack(pts, dim=-1)


def _simulate_periodic(pp: PopulationPlan, pop: Population, draws: Draws, times, optics, dtype, plan):
    """Pure diffusion on the periodic cell of the plan (see :mod:`torchdoct.sim.plan`).

    The Poisson count and uniform positions are drawn once; each frame every scatterer takes a
    Gaussian step of ``√(2·D·Δt)`` per axis (µm) and is wrapped back into the cell. The cell is small
    (|z| ≤ a few tens of µm), so positions and phases ``2kn·z`` stay exact in float32 without a phase
    reference. Each block of 64 trials walks on its own (its state stays in the cache, its steps are
    drawn straight into one buffer); its scatterers are laid out flat, trial after trial, and the
    field of each trial is the sum over its segment (``segment_reduce``, in scatterer order: the same
    bits whatever the chunk).
    """
    dev = draws.device
    n = draws.poisson(pp.expected_scatterers_per_trial, pp.capacity, f"population {pp.index} count")
    N = n.numel()
    sizes = n.view(-1, BLOCK_TRIALS).sum(1).tolist()
    S = optics.kn.numel()
    T = times.numel()
    half = torch.tensor(pp.domain_half_widths_um, dtype=dtype, device=dev).view(3, 1)
    L = 2.0 * half
    inv_L = 1.0 / L
    q = [2.0 * float(optics.kn[s]) for s in range(S)]
    refl = pop.reflectivity
    log_tol = math.log(plan.truncation_tolerance)
    # systems sharing a PSF share the amplitude (the fused kernel then evaluates the phases only where
    # the amplitude is above the tolerance; the torch code evaluates every scatterer of the cell)
    groups: dict[tuple[float, ...], list[int]] = {}
    for s in range(S):
        key_s = (float(optics.a_lat[s]), float(optics.a_ax[s]))
        groups.setdefault(key_s if optics.ry[s] == 1.0 else key_s + (optics.ry[s],), []).append(s)
    taper = plan.truncation == "taper"
    t = times.tolist()
    sigmas = [math.sqrt(2.0 * pop.diffusion_um2_per_s * (t[f] - t[f - 1])) for f in range(1, T)]
    out = torch.zeros(N, S, T, dtype=_complex_of(dtype), device=dev)
    fused = dtype == torch.float32 and dev.type == "cpu"
    group_of = [next(j for j, members in enumerate(groups.values()) if s in members) for s in range(S)]
    cell, psf_groups, q_turns = tuple(L.flatten().tolist()), list(groups), [qs / _TWO_PI for qs in q]
    # each block's key seeds its counter-based streams (kernel)
    for i, (key, M) in enumerate(zip(draws.keys(), sizes)):
        rows = slice(i * BLOCK_TRIALS, (i + 1) * BLOCK_TRIALS)
        pos = kernel.uniform_cell(key, M, tuple(pp.domain_half_widths_um)).to(device=dev, dtype=dtype)
        if fused:
            acc = kernel.walk_periodic(
                pos, n[rows], key, sigmas, cell, psf_groups, group_of, q_turns, log_tol, taper=taper
            )
            field = kernel.sums_to_field(acc)
            out[rows] = field * refl if refl != 1.0 else field
        else:
            out[rows] = _walk_periodic_block(
                pos, key, M, n[rows], L, inv_L, q, groups, refl, log_tol, sigmas, S, T, dtype, dev, taper
            )
    return out


def _walk_periodic_block(
    pos: torch.Tensor,
    key: int,
    M: int,
    n: torch.Tensor,
    L,
    inv_L,
    q,
    groups,
    refl: float,
    log_tol: float,
    sigmas: list[float],
    S: int,
    T: int,
    dtype,
    dev,
    taper: bool = False,
) -> torch.Tensor:
    """The field [64, S, T] of one block's ``M`` scatterers (``n`` per trial) walking on the cell, in
    torch (float64, or a device other than the CPU): the same normals as the fused kernel."""
    res = torch.empty(T, 2, S, n.numel(), dtype=dtype, device=dev)
    wrap = torch.empty(3, M, dtype=dtype, device=dev)
    amp = torch.empty(M, dtype=dtype, device=dev)
    field = torch.empty(2, M, dtype=dtype, device=dev)  # real and imaginary parts of each term
    re, im = field
    lengths = n.to(dev).expand(2, -1).contiguous()

    def evaluate(f: int) -> None:
        for grp, systems in groups.items():
            a_lat, a_ax = grp[0], grp[1]
            torch.mul(pos[0], pos[0], out=amp)
            if len(grp) > 2:  # anisotropic lateral PSF: ry = s_x²/s_y²
                amp.addcmul_(pos[1], pos[1], value=grp[2])
            else:
                amp.addcmul_(pos[1], pos[1])
            amp.mul_(-a_lat).addcmul_(pos[2], pos[2], value=-a_ax)
            w = _taper_window(amp, log_tol) if taper else None
            _truncated_amplitude(amp, log_tol)
            if w is not None:
                amp.mul_(w)
            if refl != 1.0:
                amp.mul_(refl)
            for s in systems:
                torch.mul(pos[2], q[s], out=im)
                torch.cos(im, out=re)
                im.sin_()
                field.mul_(amp)
                res[f, :, s] = torch.segment_reduce(field, "sum", lengths=lengths, axis=1)

    evaluate(0)
    for f in range(1, T):
        step = kernel._block_normals(key, f, M)
        pos.add_(step.to(device=dev, dtype=dtype), alpha=sigmas[f - 1])
        torch.mul(pos, inv_L, out=wrap).round_()
        pos.addcmul_(wrap, L, value=-1.0)
        evaluate(f)
    return torch.complex(res[:, 0], res[:, 1]).permute(2, 1, 0)


def _simulate_diffusive(pp: PopulationPlan, pop: Population, draws: Draws, times, optics, dtype, plan):
    """Diffusion with drift: a random walk tracked frame by frame in the region R (see :mod:`torchdoct.sim.plan`).

    State per slot (float64, component-major [N, 3, C]): position, depth at which the phase was
    referenced and that phase ``(2kn·z_ref) mod 2π``. Unused slots sit far away. Each frame: one
    step for every slot, slots that left R are freed (set far away), immigrants from the medium
    outside fill free slots, and the field is evaluated on the slots inside the PSF box only.
    """
    dev = draws.device
    R = pp.domain_half_widths_um
    Rt = torch.tensor(R, dtype=_F64, device=dev).view(1, 3, 1)
    rho = pp.density_per_um3
    C = pp.capacity
    P = pp.immigrant_proposal_capacity
    D = pop.diffusion_um2_per_s
    n0 = draws.poisson(pp.expected_scatterers_per_trial, C, f"population {pp.index} count")
    pos0, alive = _uniform_box(draws, n0, C, R)
    pos = pos0.transpose(1, 2).contiguous()  # [N, 3, C]
    vel = _velocities(pop, draws, C).transpose(1, 2).contiguous()
    N = pos.shape[0]
    S = optics.kn.numel()
    T = times.numel()
    kn2 = [2.0 * float(optics.kn[s]) for s in range(S)]
    zref = pos[:, 2].clone()
    phi0 = torch.stack([torch.remainder(k * zref, _TWO_PI) for k in kn2]).to(dtype)  # [S, N, C]
    cdt = _complex_of(dtype)
    out_re = torch.zeros(S, N * T, dtype=dtype, device=dev)
    out_im = torch.zeros(S, N * T, dtype=dtype, device=dev)
    prop_slots = torch.arange(P, device=dev)[None, :]
    shell_vol = 8.0 * (math.prod(pp.immigrant_shell_half_widths_um) - math.prod(R))
    a_lat = [float(optics.a_lat[s]) for s in range(S)]
    a_ax = [float(optics.a_ax[s]) for s in range(S)]
    taper = plan.truncation == "taper"
    log_tol = math.log(plan.truncation_tolerance)

    # systems grouped by their own PSF box: each evaluates only the slots inside it
    boxes: dict[tuple[float, float, float], list[int]] = {}
    for s, sp in enumerate(plan.systems):
        boxes.setdefault(sp.truncation_half_widths_um, []).append(s)
    groups = [
        (torch.tensor([1.0 / h for h in half], dtype=_F64, device=dev).view(1, 3, 1), idx)
        for half, idx in boxes.items()
    ]

    def evaluate(f: int) -> None:
        for inv_box, systems in groups:
            # only slots inside the system's PSF box carry an amplitude above the tolerance
            b, c = torch.nonzero((pos * inv_box).abs_().amax(1) <= 1.0, as_tuple=True)
            if b.numel() == 0:
                continue
            p = pos[b, :, c]  # [M, 3] float64
            dz = p[:, 2] - zref[b, c]
            p = p.to(dtype)
            x2, y2 = p[:, 0] * p[:, 0], p[:, 1] * p[:, 1]
            z2 = p[:, 2] * p[:, 2]
            dest = b * T + f
            for s in systems:
                r2 = x2 + y2 if optics.ry[s] == 1.0 else x2 + y2 * optics.ry[s]
                ex = torch.add(r2 * (-a_lat[s]), z2, alpha=-a_ax[s])
                w = _taper_window(ex, log_tol) if taper else None
                amp = _amplitude(ex)
                if w is not None:
                    amp = amp * w
                if pop.reflectivity != 1.0:
                    amp = amp * pop.reflectivity
                phase = phi0[s, b, c] + (kn2[s] * dz).to(dtype)
                out_re[s].index_add_(0, dest, amp * torch.cos(phase))
                out_im[s].index_add_(0, dest, amp * torch.sin(phase))

    evaluate(0)
    for f in range(1, T):
        dt = float(times[f] - times[f - 1])
        sigma = math.sqrt(2.0 * D * dt)
        pos.add_(draws.randn(3, C), alpha=sigma).add_(vel, alpha=dt)
        inside = (pos.abs() <= Rt).all(1)
        left = alive & ~inside
        alive &= inside
        lb, lc = torch.nonzero(left, as_tuple=True)
        pos[lb, :, lc] = _FAR
        # immigrants: the Poisson medium outside R, one step later, landing inside R
        n_prop = draws.poisson(rho * shell_vol, P, f"population {pp.index} immigrants")
        y = _shell_points(draws, P, R, pp.immigrant_shell_half_widths_um)
        vy = _velocities(pop, draws, P)
        y = y + sigma * draws.randn(P, 3) + vy * dt
        acc = (prop_slots < n_prop[:, None]) & _inside(y, Rt.view(3))
        n_acc = acc.sum(1)
        dead = ~alive
        dead_rank = torch.cumsum(dead, 1) - 1
        if bool((n_acc > dead.sum(1)).any()):
            raise CapacityError(f"population {pp.index}: tracked scatterers exceed the {C} reserved slots")
        fill = dead & (dead_rank < n_acc[:, None])
        fb, fc = torch.nonzero(fill, as_tuple=True)
        if fb.numel():
            order = torch.argsort((~acc).to(torch.int8), dim=1, stable=True)
            src = order[fb, dead_rank[fb, fc]]
            new = y[fb, src]  # [F, 3]
            pos[fb, :, fc] = new
            zref[fb, fc] = new[:, 2]
            for s in range(S):
                phi0[s, fb, fc] = torch.remainder(kn2[s] * new[:, 2], _TWO_PI).to(dtype)
            vel[fb, :, fc] = vy[fb, src]
            alive[fb, fc] = True
        evaluate(f)
    return torch.complex(out_re, out_im).view(S, N, T).permute(1, 0, 2).to(cdt)


#: The sampler of each kind of population (:attr:`torchdoct.sim.plan.PopulationPlan.sampler`).
SAMPLERS: dict[str, Callable] = {
    "static": _simulate_static,
    "drift": _simulate_drift,
    "diffusive": _simulate_diffusive,
    "periodic": _simulate_periodic,
}


def scene_field(
    scene: Scene, plan: Plan, draws: Draws, times: torch.Tensor, dtype: torch.dtype, device: torch.device
) -> torch.Tensor:
    """The noise-free complex field ``[trials, systems, frames]`` of one chunk: every population's
    sampler on the chunk's draws, summed in population order."""
    optics = _Optics.of(scene, dtype, device)
    total = None
    for pp, pop in zip(plan.populations, scene.populations):
        sampler = "periodic" if pp.immigrant_method == "periodic" else pp.sampler
        e = SAMPLERS[sampler](pp, pop, draws, times, optics, dtype, plan)
        total = e if total is None else total + e
    return total
