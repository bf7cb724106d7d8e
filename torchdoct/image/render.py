"""Spatial simulator: time sequences of complex B-scans [T, Z, X] and volumes [T, Y, Z, X] of a phantom.

Every pixel holds the point model's sum over scatterers (physics.md §5.1, paper Eq. 11) with the PSF
centred on that pixel::

    E(t; x_p, y_p, z_p) = Σ_j b_j · h(r_j(t) − r_p) · exp(i·2·k·n·z_j(t)),
    h(r) = exp(−x²/(2 s_x²) − y²/(2 s_y²) − z²/(2 s_z²)),  s_x = Δx/(2√2),  s_y = Δy/(2√2),
    s_z = Δz/(2√ln2),  k = 2π/λ₀  (Δy = Δx unless the system gives ``lateral_resolution_y_um``)

(:mod:`torchdoct.conventions`; µm, s). The phase is the scatterer's absolute depth phase: a pixel and
its neighbour see one scatterer with the same phase, so there is no carrier across pixels and the
depth spectrum of a B-scan is centred at zero spatial frequency.

What runs, and nothing else:

* **Seeding.** Each population (background, regions) is seeded as a Poisson medium only in the box
  that the PSF of some pixel can reach at the truncation tolerance during the protocol: the grid's
  extent plus the largest PSF truncation half-width of the scene's systems plus the population's
  reach (``|v|·duration`` per axis for straight paths, ``5·√(2·D·duration)`` for diffusion), cut to
  the region's bounding box dilated by the reach. For a B-scan that is a slab around its plane.
* **Motion.** Static populations are splatted once and added to every frame; populations with only
  ballistic or flow motion move on straight paths drawn once (a flow region is a rigid translation,
  no per-frame random draws); diffusing populations take one Gaussian step per frame (float64).
* **Region membership.** A scatterer counts at a frame only while it is inside its region and not
  inside a later region (later regions paint over earlier ones; the background lies under all), so
  each region keeps its density at every frame and the ground-truth labels are exact.
* **Splatting.** The Gaussian PSF is separable: each scatterer adds the outer product of its
  axial and lateral PSF windows (``2·h/pitch + 2`` pixels per axis) to the image, chunked over
  scatterers so memory stays bounded. Each axis window is cut at the truncation tolerance (``h`` the
  half-width of the axis); with ``[simulation] truncation = "taper"`` it is multiplied by the taper
  window (:func:`torchdoct.conventions.taper_window`) of that axis's exponent, so scatterers enter each
  axis's window continuously. Positions are float64 and phases are reduced mod 2π in
  float64 before the working dtype is used, so float32 output keeps its phase accuracy at any depth.
* **Noise** (only with ``[noise]``): circular complex Gaussian per pixel and frame at ``snr_db``
  below the mean noise-free intensity ``ρ·b²·π^{3/2}·s_x²·s_z`` (physics.md §5.2) of the brightest
  population, per system.

Randomness: population ``i`` draws from its own generator seeded from ``(seed, i)``, noise from
``(seed, "noise", system)``; chunking changes neither the draws nor the order of the sums, so a seed
gives bit-identical output for any chunk size.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from ..conventions import (
    TAPER_START,
    amplitude_sigma_axial_um,
    amplitude_sigma_lateral_um,
    mean_intensity,
    noise_sigma,
    truncation_half_widths_um,
    wavenumber_per_um,
)
from ..figures import CONTINUOUS_CMAP, LABEL_COLORS
from ..runtime.interrupt import progress_disabled
from ..runtime.resources import check_resources
from ..runtime.threads import map_ordered, one_torch_thread, resolve_threads
from ..sim.config import Population
from ..sim.samplers import unit_directions
from ..sim.streams import seeded_generator
from .phantom import MOTION_CODES, Phantom

__all__ = [
    "render",
    "RenderResult",
    "DIFFUSION_REACH_SIGMAS",
    "MAX_SCATTERERS",
    "ScatterersLimitError",
    "save_preview",
    "preview_figure",
]

_F64 = torch.float64
_TWO_PI = 2.0 * math.pi
#: A diffusing scatterer is seeded up to this many RMS displacements (per axis, over the protocol)
#: outside the imaged box; the walk's maximum passes it with probability < 1e-6.
DIFFUSION_REACH_SIGMAS = 5.0
#: Largest expected number of seeded scatterers (all populations) that :func:`render` accepts without
#: ``max_scatterers`` (``--max-scatterers``): the shipped phantoms seed at most 3e5.
MAX_SCATTERERS = 2e7
#: Bytes held per seeded scatterer (float64 position, velocity and walk, one frame's positions and masks).
_BYTES_PER_SCATTERER = 128


class ScatterersLimitError(ValueError):
    """A phantom grid whose seeded scatterers would exceed the limit (refused before any work)."""


#: Complex PSF-window elements per splat chunk (bounds the temporary memory to ~64 MB).
_SPLAT_ELEMENTS = 1 << 22


def _complex_of(dtype: torch.dtype) -> torch.dtype:
    return torch.complex64 if dtype == torch.float32 else torch.complex128


@dataclass
class _SystemOptics:
    name: str
    sx: float  # amplitude sigma, lateral x (µm)
    sz: float  # amplitude sigma, axial (µm)
    kn: float  # 2πn/λ₀ (rad/µm)
    half: tuple[float, float, float]  # truncation half-widths (x, y, z), µm
    sy: float = 0.0  # amplitude sigma, lateral y (µm)
    log_tol: float = 0.0  # ln(tolerance), for the taper
    taper: bool = False


@dataclass
class _PopulationState:
    index: int
    name: str
    pop: Population
    region: int | None  # None = background
    pos0: torch.Tensor  # [N, 3] float64 positions at the first frame
    vel: torch.Tensor | None  # [N, 3] float64, µm/s (flow + ballistic), None if no drift
    diffusion: float
    gen: torch.Generator
    walk: torch.Tensor | None = None  # [N, 3] accumulated diffusion displacement


@dataclass
class RenderResult:
    """Complex sequences of one phantom, its ground truth, and what was run.

    ``data``: [S, T, Z, X] (B-scan) or [S, T, Y, Z, X] (volume), complex64/complex128, one entry per
    rendered system (``system_names``). ``labels``: motion code per pixel (:data:`MOTION_CODES`),
    ``label_params``: [2, ...] float32 diffusion coefficient (µm²/s) and speed (µm/s) per pixel,
    ``regions``: index into ``region_table`` per pixel (−1: outside every region and no background).
    """

    phantom: Phantom
    data: torch.Tensor
    system_names: list[str]
    labels: np.ndarray
    label_params: np.ndarray
    regions: np.ndarray
    frame_times_s: tuple[float, ...]
    seed: int
    elapsed_s: float
    work: dict[str, Any] = field(default_factory=dict)

    def system_index(self, system: str | int | None) -> int:
        if system is None:
            return 0
        if isinstance(system, int):
            return system
        if system not in self.system_names:
            raise ValueError(f"system {system!r} was not rendered; rendered: {self.system_names}")
        return self.system_names.index(system)

    def metadata(self, system: str | int | None = None) -> dict[str, Any]:
        """Sequence-file metadata (axes, pitch, frame times, system, labels legend, provenance)."""
        s = self.phantom.scene.systems[
            [x.name for x in self.phantom.scene.systems].index(self.system_names[self.system_index(system)])
        ]
        return {
            "axes": self.phantom.grid.axes,
            "pitch_um": self.phantom.grid.pitch_um,
            "frame_times_s": list(self.frame_times_s),
            "system": {
                "name": s.name,
                "wavelength_um": s.wavelength_um,
                "lateral_resolution_um": s.lateral_resolution_um,
                "axial_resolution_um": s.axial_resolution_um,
                "refractive_index": s.refractive_index,
                **({} if s.lateral_resolution_y_um is None else {"lateral_resolution_y_um": s.lateral_resolution_y_um}),
            },
            "phantom": self.phantom.to_dict(),
            "seed": self.seed,
            "labels_legend": {str(v): k for k, v in MOTION_CODES.items()},
            "label_params": ["diffusion_um2_per_s", "speed_um_per_s"],
            "regions": self.phantom.region_table(),
        }

    def intensity(self, system: str | int | None = None) -> torch.Tensor:
        """|E|² with frames last: [..., T] (the layout of :mod:`torchdoct.sim.metrics`)."""
        e = self.data[self.system_index(system)]
        return (e.real**2 + e.imag**2).movedim(0, -1)

    def maps(self, system: str | int | None = None) -> dict[str, torch.Tensor]:
        """LIV (dB²), OCDS (1/s) and mean dB intensity per pixel, with the scene's analysis settings.

        Pixels whose intensity is 0 at some frame (no scatterer within reach) are NaN.
        """
        from ..sim.metrics import liv, ocds, to_db

        i = self.intensity(system)
        zero = (i <= 0).any(-1)
        an = self.phantom.scene.analysis
        out = {
            "liv": liv(i),
            "mean_db": to_db(i.clamp_min(torch.finfo(i.dtype).tiny)).mean(-1),
            "ocds": ocds(
                i,
                self.frame_times_s,
                delay_range_s=an.ocds_delay_range_s,
                scale=an.ocds_scale,
                estimator=an.ocds_estimator,
            ),
        }
        return {k: torch.where(zero, torch.full_like(v, math.nan), v) for k, v in out.items()}


def _optics(phantom: Phantom, names: Sequence[str], tol: float, taper: bool = False) -> list[_SystemOptics]:
    out = []
    for s in phantom.scene.systems:
        if s.name in names:
            out.append(
                _SystemOptics(
                    s.name,
                    amplitude_sigma_lateral_um(s.lateral_resolution_um),
                    amplitude_sigma_axial_um(s.axial_resolution_um),
                    wavenumber_per_um(s.wavelength_um, s.refractive_index),
                    truncation_half_widths_um(
                        s.lateral_resolution_um,
                        s.axial_resolution_um,
                        tol,
                        lateral_resolution_y_um=s.lateral_resolution_y_um,
                    ),
                    sy=amplitude_sigma_lateral_um(s.lateral_widths_um[1]),
                    log_tol=math.log(tol),
                    taper=taper,
                )
            )
    return out


def _reach_um(pop: Population, duration_s: float) -> tuple[float, float, float]:
    """Largest displacement per axis over the protocol (µm)."""
    vf = pop.flow_velocity_um_per_s
    vb = sum(b.speed_um_per_s for b in pop.ballistic)
    diff = DIFFUSION_REACH_SIGMAS * math.sqrt(2.0 * pop.diffusion_um2_per_s * duration_s)
    return tuple(abs(vf[a]) * duration_s + vb * duration_s + diff for a in range(3))  # type: ignore[return-value]


def _seed_box(
    phantom: Phantom, index: int, region: int | None, half: tuple[float, ...], duration_s: float
) -> tuple[list[float], list[float], float]:
    """The box a population is seeded in (lower and upper corner, µm) and its expected scatterer count:
    the grid's extent plus the PSF truncation half-width plus the population's reach, cut to its region."""
    pop = phantom.scene.populations[index]
    grid = phantom.grid
    reach = _reach_um(pop, duration_s)
    lo, hi = [], []
    bounds = phantom.regions[region].bounds_um() if region is not None else None
    for a, ax in enumerate("xyz"):
        c0, c1 = grid.extent_um(ax)
        l, h = c0 - half[a] - reach[a], c1 + half[a] + reach[a]
        if bounds is not None:
            l, h = max(l, bounds[a][0] - reach[a]), min(h, bounds[a][1] + reach[a])
        lo.append(l)
        hi.append(h)
    volume = math.prod(max(0.0, h - l) for l, h in zip(lo, hi))
    return lo, hi, pop.density_per_um3 * volume


def _seed_population(
    phantom: Phantom, index: int, region: int | None, half: tuple[float, ...], duration_s: float, seed: int
) -> _PopulationState | None:
    pop = phantom.scene.populations[index]
    gen = seeded_generator(seed, index)
    lo, hi, mean = _seed_box(phantom, index, region, half, duration_s)
    n = int(torch.poisson(torch.tensor([mean], dtype=_F64), generator=gen).item()) if mean > 0 else 0
    lo_t, hi_t = torch.tensor(lo, dtype=_F64), torch.tensor(hi, dtype=_F64)
    pos = lo_t + (hi_t - lo_t) * torch.rand(n, 3, generator=gen, dtype=_F64)
    vel = None
    if pop.ballistic or any(pop.flow_velocity_um_per_s):
        vel = torch.tensor(pop.flow_velocity_um_per_s, dtype=_F64).expand(n, 3).clone()
        scale = phantom.regions[region].flow_scale(pos) if region is not None else None
        if scale is not None:  # a Poiseuille cylinder: the flow's speed falls off from the axis
            vel *= scale[:, None]
        for b in pop.ballistic:
            vel += b.speed_um_per_s * unit_directions(torch.rand(n, 2, generator=gen, dtype=_F64), b.directions)
    name = phantom.scene.populations[index].name or f"population{index}"
    if region is not None:
        name = phantom.regions[region].name
    st = _PopulationState(index, name, pop, region, pos, vel, pop.diffusion_um2_per_s, gen)
    if st.diffusion > 0:
        st.walk = torch.zeros_like(pos)
    return st


def _inside(
    phantom: Phantom, st: _PopulationState, pos: torch.Tensor, reach_box: tuple[torch.Tensor, torch.Tensor]
) -> torch.Tensor:
    """Scatterers that count at this frame: inside their region and within some pixel's PSF box."""
    keep = ((pos >= reach_box[0]) & (pos <= reach_box[1])).all(-1)
    if st.region is not None:
        keep &= phantom.regions[st.region].contains(pos, phantom.grid)
    # later regions paint over earlier ones; the background lies under every region
    later = phantom.regions if st.region is None else phantom.regions[st.region + 1 :]
    for r in later:
        keep &= ~r.contains(pos, phantom.grid)
    return keep


def _axis_taper(ex: torch.Tensor, log_tol: float) -> torch.Tensor:
    """The taper window (:func:`torchdoct.conventions.taper_window`) of one axis's PSF exponents ``ex``."""
    t = ((ex / log_tol - TAPER_START) / (1.0 - TAPER_START)).clamp_(0.0, 1.0)
    return 1.0 - t * t * t * (10.0 - 15.0 * t + 6.0 * t * t)


def _window_pixels(half: float, pitch: float, n: int) -> int:
    """Pixels of one axis's PSF window: ``2·h/pitch + 2``, but never more than the grid's ``n`` (a
    window starting at the grid's first pixel it reaches covers every pixel within ``h`` of the
    scatterer), so a pitch far below the PSF width (``--pitch-um 1e-6``) costs the grid, not ``h/pitch``."""
    return int(min(math.floor(2.0 * half / pitch) + 2, n))


def _axis_window(
    coord: torch.Tensor,
    first: float,
    pitch: float,
    n: int,
    half: float,
    sigma: float,
    dtype: torch.dtype,
    taper_log_tol: float | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """PSF amplitude window along one axis: pixel indices [N, K] (clamped) and weights [N, K].

    Weights are ``exp(−d²/(2σ²))`` for pixels within ``half`` of the scatterer, else 0; with
    ``taper_log_tol`` (``ln tol``) they are multiplied by the taper window of ``−d²/(2σ²)``.
    """
    k = _window_pixels(half, pitch, n)
    i0 = torch.ceil((coord - half - first) / pitch).clamp_(0.0, float(n))  # the window starts inside the grid
    idx = i0[:, None] + torch.arange(k, dtype=_F64)
    d = first + idx * pitch - coord[:, None]
    ok = (idx >= 0) & (idx <= n - 1) & (d.abs() <= half)
    ex = -(d * d) / (2.0 * sigma * sigma)
    amp = torch.exp(ex)
    if taper_log_tol is not None:
        amp = amp * _axis_taper(ex, taper_log_tol)
    w = amp.to(dtype) * ok
    return idx.clamp_(0, n - 1).long(), w


def _splat(
    out: torch.Tensor, pos: torch.Tensor, refl: float, opt: _SystemOptics, phantom: Phantom, dtype: torch.dtype
) -> int:
    """Add the field of scatterers at ``pos`` [N, 3] (float64) to ``out`` (flat complex image)."""
    grid = phantom.grid
    n = pos.shape[0]
    if n == 0:
        return 0
    hx, hy, hz = opt.half
    volume = grid.kind == "volume"
    kx = _window_pixels(hx, grid.pitch_x_um, grid.n_x)
    kz = _window_pixels(hz, grid.pitch_z_um, grid.n_z)
    ky = _window_pixels(hy, grid.pitch_y_um, grid.n_y) if volume else 1
    chunk = max(1, _SPLAT_ELEMENTS // (kx * ky * kz))
    x0, z0 = grid.extent_um("x")[0], grid.extent_um("z")[0]
    y0 = grid.extent_um("y")[0]
    sy = opt.sy or opt.sx
    lt = opt.log_tol if opt.taper else None
    for s in range(0, n, chunk):
        p = pos[s : s + chunk]
        phase = torch.remainder(2.0 * opt.kn * p[:, 2], _TWO_PI).to(dtype)
        ix, wx = _axis_window(p[:, 0], x0, grid.pitch_x_um, grid.n_x, hx, opt.sx, dtype, lt)
        iz, wz = _axis_window(p[:, 2], z0, grid.pitch_z_um, grid.n_z, hz, opt.sz, dtype, lt)
        if volume:
            iy, wy = _axis_window(p[:, 1], y0, grid.pitch_y_um, grid.n_y, hy, sy, dtype, lt)
            a = refl * torch.ones_like(phase)
        else:
            dy = p[:, 1] - grid.y_um
            ey = -(dy * dy) / (2.0 * sy * sy)
            a = refl * torch.exp(ey)
            if lt is not None:
                a = a * _axis_taper(ey, lt)
            a = a.to(dtype)
        w = torch.complex(a * torch.cos(phase), a * torch.sin(phase))
        wzx = wz[:, :, None] * wx[:, None, :]  # [N, kz, kx]
        idx = iz[:, :, None] * grid.n_x + ix[:, None, :]
        if volume:
            wzx = wy[:, :, None, None] * wzx[:, None]
            idx = iy[:, :, None, None] * (grid.n_z * grid.n_x) + idx[:, None]
        vals = w.view(-1, *([1] * (wzx.dim() - 1))) * wzx
        out.index_add_(0, idx.reshape(-1), vals.reshape(-1))
    return n


def _pixel_labels(phantom: Phantom) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ground truth at pixel centres: motion code, (D, v) parameters, region-table index."""
    grid = phantom.grid
    zc = torch.tensor(grid.coords_um("z"), dtype=_F64)
    xc = torch.tensor(grid.coords_um("x"), dtype=_F64)
    yc = torch.tensor(grid.coords_um("y"), dtype=_F64)
    Y, Z, X = torch.meshgrid(yc, zc, xc, indexing="ij")
    pos = torch.stack([X, Y, Z], dim=-1)  # [Y, Z, X, 3]
    table = phantom.region_table()
    region = torch.full(pos.shape[:-1], -1, dtype=torch.int16)
    offset = 0
    if phantom.background:
        region[:] = 0
        offset = 1
    for i, r in enumerate(phantom.regions):
        region[r.contains(pos, grid)] = i + offset
    codes = torch.tensor([row["motion_code"] for row in table] + [MOTION_CODES["empty"]], dtype=torch.int8)
    d = torch.tensor([row["diffusion_um2_per_s"] for row in table] + [0.0], dtype=torch.float32)
    v = torch.tensor([row["speed_um_per_s"] for row in table] + [0.0], dtype=torch.float32)
    look = region.long().clone()
    look[look < 0] = len(table)
    labels, params = codes[look], torch.stack([d[look], v[look]])
    for i, r in enumerate(phantom.regions):  # a Poiseuille cylinder: the flow's speed at the pixel centre
        scale = r.flow_scale(pos)
        if scale is not None:
            pop = phantom.scene.populations[r.population]
            flow = math.sqrt(sum(c * c for c in pop.flow_velocity_um_per_s))
            local = (flow * scale + sum(b.speed_um_per_s for b in pop.ballistic)).to(params.dtype)
            inside = region == i + offset
            params[1][inside] = local[inside]
    if grid.kind == "bscan":
        labels, params, region = labels[0], params[:, 0], region[0]
    return labels.numpy(), params.numpy(), region.numpy()


@one_torch_thread
def _check_intensity_scale(scene: Any, names: Sequence[str], dtype: torch.dtype) -> None:
    """The brightest population's mean intensity per system within what ``dtype`` holds
    (:func:`torchdoct.sim.simulate.check_intensity_scale`): else the image would be zeros."""
    from ..conventions import mean_intensity
    from ..sim.simulate import check_intensity_scale

    brightest = {
        s.name: max(
            mean_intensity(
                p.density_per_um3,
                s.lateral_resolution_um,
                s.axial_resolution_um,
                p.reflectivity,
                lateral_resolution_y_um=s.lateral_resolution_y_um,
            )
            for p in scene.populations
        )
        for s in scene.systems
        if s.name in names
    }
    check_intensity_scale(scene, brightest, dtype)


def render(
    phantom: Phantom,
    *,
    systems: Sequence[str] | str | None = None,
    seed: int | None = None,
    dtype: str | torch.dtype | None = None,
    device: str | torch.device | None = None,
    truncation_tolerance: float | None = None,
    threads: int | None = None,
    progress: bool = False,
    max_scatterers: float | None = None,
) -> RenderResult:
    """Render the complex image sequence of ``phantom`` for its systems (all, or the named ones).

    ``seed``, ``dtype`` and ``truncation_tolerance`` default to the scene's ``[simulation]`` values.
    ``threads``: frames splatted at once, each on one torch thread (:mod:`torchdoct.runtime.threads`; default:
    the usable cores); the output is bit-identical for any value.
    All systems see the same scatterers. The expected number of scatterers seeded is checked first:
    over ``max_scatterers`` (default :data:`MAX_SCATTERERS`) it is a :class:`ScatterersLimitError`
    naming the count and the memory it would take. Returns a :class:`RenderResult` (see the module docstring
    for what runs).
    """
    t_start = time.perf_counter()
    from ..sim.config import check_scene_argument, whole_argument

    check_scene_argument("td.render(phantom)", phantom, Phantom, "td.load_phantom")
    scene = phantom.scene
    sim = scene.simulation
    seed = sim.seed if seed is None else whole_argument("seed", seed)
    tol = sim.truncation_tolerance if truncation_tolerance is None else float(truncation_tolerance)
    dtype = getattr(torch, dtype) if isinstance(dtype, str) else (dtype or getattr(torch, sim.dtype))
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"dtype must be float32 or float64; got {dtype}")
    from ..runtime.device import check_device

    device = torch.device(check_device(None if device is None else str(device), "device") or "cpu")
    threads = resolve_threads(threads)
    all_names = [s.name for s in scene.systems]
    if systems is not None and not isinstance(systems, (str, list, tuple)):
        raise TypeError(f"systems must be a system name or a list of them; got {type(systems).__name__} {systems!r}")
    names = all_names if systems is None else ([systems] if isinstance(systems, str) else list(systems))
    for nm in names:
        if nm not in all_names:
            raise ValueError(f"system {nm!r} is not in the phantom; its systems are {all_names}")
    _check_intensity_scale(scene, names, dtype)
    optics = _optics(phantom, names, tol, sim.truncation == "taper")
    half = tuple(max(o.half[a] for o in optics) for a in range(3))
    grid = phantom.grid
    times = torch.tensor(scene.protocol.times_s, dtype=_F64)
    t_rel = times - times[0]
    duration = float(t_rel[-1])
    T = times.numel()
    n_pix = math.prod(grid.shape)
    cdt = _complex_of(dtype)

    lo = torch.tensor([grid.extent_um(a)[0] - half[i] for i, a in enumerate("xyz")], dtype=_F64)
    hi = torch.tensor([grid.extent_um(a)[1] + half[i] for i, a in enumerate("xyz")], dtype=_F64)
    box = (lo, hi)

    out_bytes = len(optics) * T * n_pix * (16 if dtype == torch.float64 else 8)
    check_resources(  # the sequence plus one copy when written (torchdoct.runtime.resources)
        "the rendered sequence",
        2 * out_bytes,
        "render fewer pixels or frames, one system at a time (--system), or in float32",
        detail=f"{out_bytes / 2**30:.2f} GB alone: {len(optics)} system(s) × {T} frames × {n_pix} pixels, and one "
        "copy when written",
    )

    states = []
    pop_regions: list[int | None] = [None] * len(scene.populations)
    for i, r in enumerate(phantom.regions):
        pop_regions[r.population] = i
    expected = sum(_seed_box(phantom, ip, pop_regions[ip], half, duration)[2] for ip in range(len(scene.populations)))
    limit = MAX_SCATTERERS if max_scatterers is None else float(max_scatterers)
    if not expected <= limit:  # checked before anything is drawn or allocated (NaN/inf included)
        fov = " × ".join(
            f"{grid.extent_um(a)[1] - grid.extent_um(a)[0] + p:.4g}"
            for a, p in (("x", grid.pitch_x_um), ("z", grid.pitch_z_um))
        )
        raise ScatterersLimitError(
            f"{phantom.name}: the grid ({' × '.join(str(n) for n in grid.shape)} pixels, field of view {fov} µm "
            f"x × z) and the PSF and motion reach around it would hold {expected:.3g} scatterers, about "
            f"{expected * _BYTES_PER_SCATTERER / 2**30:.3g} GB; the limit is {limit:.3g}: use fewer pixels or a "
            f"smaller --pitch-um, or raise the limit with --max-scatterers N"
        )
    for ip in range(len(scene.populations)):
        st = _seed_population(phantom, ip, pop_regions[ip], half, duration, seed)
        if st is not None:
            states.append(st)

    work: dict[str, Any] = {"stages": [], "populations": {}}
    data = torch.zeros(len(optics), T, n_pix, dtype=cdt, device=device)
    # static populations: one splat, added to every frame
    static = [st for st in states if st.vel is None and st.walk is None]
    moving = [st for st in states if not (st.vel is None and st.walk is None)]
    if static:
        work["stages"].append("static splat (once)")
        for st in static:
            keep = _inside(phantom, st, st.pos0, box)
            p = st.pos0[keep].to(device)
            for k, o in enumerate(optics):
                img = torch.zeros(n_pix, dtype=cdt, device=device)
                _splat(img, p, st.pop.reflectivity, o, phantom, dtype)
                data[k] += img
            work["populations"][st.name] = {"scatterers": int(st.pos0.shape[0]), "evaluated_once": int(keep.sum())}
    if moving:
        drift = [st for st in moving if st.walk is None]
        diff = [st for st in moving if st.walk is not None]
        if drift:
            work["stages"].append("straight paths drawn once (ballistic/flow), splat per frame")
        if diff:
            work["stages"].append("diffusion: one Gaussian step per frame, splat per frame")
        # drop straight-path scatterers that never count at any frame
        for st in drift:
            assert st.vel is not None  # moving without a walk: a straight path
            ever = torch.zeros(st.pos0.shape[0], dtype=torch.bool)
            for t in t_rel:
                ever |= _inside(phantom, st, st.pos0 + st.vel * t, box)
            st.pos0, st.vel = st.pos0[ever], st.vel[ever]
        for st in moving:
            work["populations"][st.name] = {"scatterers": int(st.pos0.shape[0]), "evaluations": 0}
        from tqdm.auto import tqdm

        bar = tqdm(
            total=T, desc=f"render {phantom.name}", unit="frame", disable=progress_disabled(progress), leave=False
        )

        def positions():  # frame by frame, in order: the walks advance here (one stream per population)
            for f in range(T):
                ps = []
                for st in moving:
                    pos = st.pos0
                    if st.vel is not None:
                        pos = pos + st.vel * t_rel[f]
                    if st.walk is not None:
                        if f > 0:
                            sd = math.sqrt(2.0 * st.diffusion * float(t_rel[f] - t_rel[f - 1]))
                            st.walk += sd * torch.randn(st.walk.shape, generator=st.gen, dtype=_F64)
                        pos = pos + st.walk
                    keep = _inside(phantom, st, pos, box)
                    ps.append((st, pos[keep].to(device)))
                yield f, ps

        def splat_frame(item):  # frames are independent images: they splat in parallel, bit-identically
            f, ps = item
            for st, p in ps:
                for k, o in enumerate(optics):
                    _splat(data[k, f], p, st.pop.reflectivity, o, phantom, dtype)
            return ps

        for ps in map_ordered(splat_frame, positions(), threads):
            for st, p in ps:
                work["populations"][st.name]["evaluations"] += int(p.shape[0]) * len(optics)
            bar.update(1)
        bar.close()
    else:
        work["stages"].append("no motion stage")
    if scene.noise is not None:
        work["stages"].append(f"noise at {scene.noise.snr_db} dB")
        for k, o in enumerate(optics):
            sysobj = scene.systems[all_names.index(o.name)]
            i_ref = max(
                mean_intensity(
                    p.density_per_um3,
                    sysobj.lateral_resolution_um,
                    sysobj.axial_resolution_um,
                    p.reflectivity,
                    lateral_resolution_y_um=sysobj.lateral_resolution_y_um,
                )
                for p in scene.populations
            )
            sigma = noise_sigma(i_ref, scene.noise.snr_db)
            g = seeded_generator(seed, 1 << 20, all_names.index(o.name))
            noise = torch.randn(T, n_pix, 2, generator=g, dtype=_F64).to(dtype) * sigma
            data[k] += torch.complex(noise[..., 0], noise[..., 1]).to(device)
    else:
        work["stages"].append("no noise stage")
    labels, params, regions = _pixel_labels(phantom)
    data = data.reshape(len(optics), T, *grid.shape)
    return RenderResult(
        phantom=phantom,
        data=data,
        system_names=[o.name for o in optics],
        labels=labels,
        label_params=params,
        regions=regions,
        frame_times_s=tuple(scene.protocol.times_s),
        seed=seed,
        elapsed_s=time.perf_counter() - t_start,
        work=work,
    )


#: Ground-truth colour per motion code: the classifier's class colours (:data:`torchdoct.figures.LABEL_COLORS`).
_LABEL_COLOURS = {code: LABEL_COLORS[name] for name, code in MOTION_CODES.items()}


def save_preview(
    result: RenderResult, path: str, system: str | int | None = None, liv_range_db2: tuple[float, float] = (0.0, 30.0)
) -> None:
    """PNG preview (:func:`preview_figure`) written to ``path``."""
    import matplotlib.pyplot as plt

    fig = preview_figure(result, system, liv_range_db2)
    try:
        fig.savefig(path, dpi=90, format="png")
    finally:
        plt.close(fig)


def preview_figure(
    result: RenderResult, system: str | int | None = None, liv_range_db2: tuple[float, float] = (0.0, 30.0)
) -> Any:
    """Preview figure: frame 0 in dB, the LIV map (dB²) and the ground-truth motion labels, on the
    project's µm axes (:mod:`torchdoct.figures`; pixel edges at the phantom's coordinates)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    grid = result.phantom.grid
    k = result.system_index(system)
    inten = result.intensity(k)
    maps = result.maps(k)
    labels = result.labels
    frame = inten[..., 0]
    liv_map = maps["liv"]
    if grid.kind == "volume":  # middle Y plane
        mid = grid.n_y // 2
        frame, liv_map, labels = frame[mid], liv_map[mid], labels[mid]
    frame_db = 10.0 * torch.log10(frame.clamp_min(1e-30)).numpy()
    from ..figures import show_bscan

    top = float(np.percentile(frame_db, 99.5))
    pitch = {"z": grid.pitch_z_um, "x": grid.pitch_x_um}
    fig, ax = plt.subplots(1, 3, figsize=(14, 4.8), constrained_layout=True)
    im0 = show_bscan(ax[0], frame_db, pitch_um=pitch, cmap="gray", vmin=top - 40.0, vmax=top)
    ax[0].set_title("frame 0, intensity (dB)")
    fig.colorbar(im0, ax=ax[0], shrink=0.8).set_label("intensity (dB)")
    cmap = plt.get_cmap(CONTINUOUS_CMAP).with_extremes(bad="#808080")
    im1 = show_bscan(ax[1], liv_map.numpy(), pitch_um=pitch, cmap=cmap, vmin=liv_range_db2[0], vmax=liv_range_db2[1])
    ax[1].set_title("LIV (dB²)")
    fig.colorbar(im1, ax=ax[1], shrink=0.8).set_label("LIV (dB²)")
    codes = sorted(_LABEL_COLOURS)
    show_bscan(
        ax[2],
        labels,
        pitch_um=pitch,
        cmap=ListedColormap([_LABEL_COLOURS[c] for c in codes]),
        vmin=-0.5,
        vmax=len(codes) - 0.5,
    )
    ax[2].set_title("ground truth: motion")
    names = {v: k for k, v in MOTION_CODES.items()}
    present = sorted({int(c) for c in np.unique(labels)})
    ax[2].legend(
        handles=[Patch(color=_LABEL_COLOURS[c], label=names[c]) for c in present], loc="lower right", fontsize=8
    )
    s = result.phantom.scene.systems[[x.name for x in result.phantom.scene.systems].index(result.system_names[k])]
    fig.suptitle(
        f"{result.phantom.name}: {s.name} ({s.wavelength_um * 1000:.0f} nm, "
        f"{s.lateral_resolution_um}/{s.axial_resolution_um} µm), {len(result.frame_times_s)} frames, "
        f"seed {result.seed}"
    )
    return fig
