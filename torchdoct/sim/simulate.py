"""Batched point simulator: the complex OCT signal of one pixel over a protocol, many trials at once.

The signal of system ``s`` at frame time ``t`` is the paper's Eq. (11) (physics.md §5.1)::

    E_s(t) = Σ_j b_j · exp(−(x_j²+y_j²)/(2 s_x²) − z_j²/(2 s_z²)) · exp(i·2·k·n·z_j(t))

with the PSF centred at the origin, ``s_x = Δx/(2√2)``, ``s_z = Δz/(2√ln2)``, ``k = 2π/λ₀``
(:mod:`torchdoct.conventions`; lengths µm, times s). Scatterers form a homogeneous Poisson medium;
only those that can come within the PSF truncation tolerance are drawn (see :mod:`torchdoct.sim.plan`).

Design notes:

* All systems of a scene see the same scatterer realization.
* Randomness: block ``b`` of 64 trials has a ``torch.Generator`` seeded from ``(seed, b)``, which
  draws the Poisson counts and one key per population. The periodic walk and the straight paths take
  every other number from counter-based streams of that key (:mod:`torchdoct.sim.kernel`); static
  populations, walks with drift and noise draw from the block's generator in float32 (4-5 ns each),
  made in the same shapes whatever the chunk. So results are bit-identical for any ``chunk_trials``,
  number of trials or threads, and float32 and float64 runs with one seed simulate the same scatterers.
* Kernels: in float32 on the CPU the periodic walk and the straight paths run in the fused kernel of
  :mod:`torchdoct.sim.kernel` (compiled, or its bit-identical torch reference); float64 and other
  devices use the torch code below with the same draws.
* Phases (torch code): each scatterer's phase is kept as ``φ₀ = (2kn·z_ref) mod 2π`` plus ``2kn·(z(t) − z_ref)``,
  with the displacement from a reference point computed in float64 (walks with drift) or as
  ``v·(t − t*)`` about the closest approach (straight paths), so float32 keeps sub-milliradian phase
  accuracy at any depth or protocol length. Walks on the periodic cell (pure diffusion) never leave
  it (|z| of a few tens of µm), so ``2kn·z`` is exact enough in the working dtype as it is.
* Sums over scatterers are taken per trial in scatterer order (``segment_reduce``/``index_add_``), never
  across trials, so a trial's bits do not depend on which other trials share its chunk.

Modules: :mod:`torchdoct.sim.streams` (the random streams and :class:`~torchdoct.sim.streams.Draws`),
:mod:`torchdoct.sim.samplers` (the scatterers, their motion and their field, one sampler per kind of
population), :mod:`torchdoct.sim.memory` (the memory estimate checked before any work); this module
runs the chunks and adds the noise (:func:`torchdoct.conventions.noise_sigma`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch

from ..conventions import TRUNCATION_MODES, noise_sigma
from ..runtime.interrupt import progress_disabled
from ..runtime.threads import map_ordered, resolve_threads, single_torch_thread
from .config import Diffusion, Scene
from .memory import MemoryLimitError, available_memory_bytes, check_simulation, chunk_bytes, release_free_memory
from .plan import BLOCK_TRIALS, Plan, make_plan
from .samplers import scene_field, unit_directions
from .streams import CapacityError, Draws, block_generator, seeded_generator

#: ``CapacityError``, ``MemoryLimitError``, the generators, ``chunk_bytes``, ``available_memory_bytes`` and
#: ``unit_directions`` are re-exported from their modules (their former home).
__all__ = [
    "simulate",
    "SimulationResult",
    "CapacityError",
    "MemoryLimitError",
    "block_generator",
    "seeded_generator",
    "chunk_bytes",
    "available_memory_bytes",
    "unit_directions",
]


@dataclass
class SimulationResult:
    """Complex signals ``[trials, systems, frames]`` of a scene, with what produced them."""

    scene: Scene
    plan: Plan
    signals: torch.Tensor
    seed: int
    trials: int
    frame_times_s: tuple[float, ...]
    elapsed_s: float = 0.0
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def intensity(self) -> torch.Tensor:
        return self.signals.real**2 + self.signals.imag**2

    @property
    def system_names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.scene.systems)

    def metrics(self) -> dict[str, Any]:
        """The scene's ``[analysis]`` metrics on these signals (see :func:`torchdoct.sim.metrics.compute_metrics`)."""
        from .metrics import compute_metrics

        return compute_metrics(self.signals, self.frame_times_s, self.scene.analysis)

    def summary(self) -> dict[str, Any]:
        from .metrics import summarize

        return summarize(self.metrics(), self.system_names)


def _simulate_chunk(
    scene: Scene, plan: Plan, blocks: list[int], seed: int, dtype: torch.dtype, device: torch.device
) -> torch.Tensor:
    draws = Draws([block_generator(seed, b) for b in blocks], device)
    times = torch.tensor(scene.protocol.times_s, dtype=torch.float64, device=device)
    total = scene_field(scene, plan, draws, times, dtype, device)
    if plan.has_noise:
        assert scene.noise is not None  # the scene's plan: has_noise is scene.noise is not None (make_plan)
        snr_db = scene.noise.snr_db
        amp = torch.tensor(
            [noise_sigma(s.mean_intensity, snr_db) for s in plan.systems],
            dtype=torch.float64,
            device=device,
        ).view(1, -1, 1)
        shape = (len(scene.systems), times.numel())
        noise = torch.complex(draws.randn(*shape) * amp, draws.randn(*shape) * amp).to(total.dtype)
        total = total + noise
    return total.contiguous()


#: Decades of intensity kept between a mean intensity and its data type's limits: a speckle intensity falls
#: this far below its mean in fewer than 1 sample in 10¹⁴, so no sample of any run underflows or is subnormal.
INTENSITY_MARGIN = 1e14
#: Spacings of the data type at the scatterer positions a motion must move per frame: below, the change of
#: every phase from frame to frame is within a few roundings of the phase itself, and LIV and OCDS are noise.
MIN_SPACINGS_PER_FRAME = 10.0


def check_intensity_scale(scene: Scene, mean_intensity: dict[str, float], dtype: torch.dtype) -> None:
    """Refuse (``ValueError`` naming the reflectivities and the fix) a system whose mean intensity
    (``mean_intensity[name]``; for an image, its brightest population's) lies within :data:`INTENSITY_MARGIN`
    of the smallest or largest normal number of ``dtype``."""
    name = "float32" if dtype == torch.float32 else "float64"
    wider = "use float64 (--dtype float64, or dtype='float64'), or " if dtype == torch.float32 else ""
    info = torch.finfo(dtype)
    lo, hi = info.tiny * INTENSITY_MARGIN, info.max / INTENSITY_MARGIN
    refl = ", ".join(f"population[{i}].reflectivity = {p.reflectivity:g}" for i, p in enumerate(scene.populations))
    for system, value in mean_intensity.items():
        if not lo <= value <= hi:
            raise ValueError(
                f"system {system!r}: the mean intensity is {value:.3g} ({refl}), outside what {name} "
                f"computes without underflow or overflow ({lo:.3g} to {hi:.3g}); LIV and OCDS do not "
                f"depend on the intensity scale: {wider}give the reflectivities relative to the brightest "
                "scatterer (the largest 1)"
            )


def check_precision(scene: Scene, plan: Plan, dtype: torch.dtype) -> None:
    """Refuse (``ValueError`` naming the field and the fix) a simulation whose numbers ``dtype`` cannot hold:
    a system's mean intensity (:attr:`SystemPlan.mean_intensity`) within :data:`INTENSITY_MARGIN` of the
    type's smallest or largest normal number, or a motion that moves less than :data:`MIN_SPACINGS_PER_FRAME`
    spacings of the type at the positions (the domain's half-width) over the shortest frame step while
    nothing else changes the signal (no motion that moves more, no noise: those swamp its rounding). LIV
    and OCDS do not depend on the intensity scale; float64 holds what float32 cannot."""
    name = "float32" if dtype == torch.float32 else "float64"
    wider = "simulate in float64 (--dtype float64, or dtype='float64'), or " if dtype == torch.float32 else ""
    info = torch.finfo(dtype)
    check_intensity_scale(scene, {sp.name: sp.mean_intensity for sp in plan.systems}, dtype)
    t = scene.protocol.times_s
    step = min(b - a for a, b in zip(t, t[1:]))
    top = max(plan.domain_half_widths_um)
    spacing = top * info.eps  # the type's spacing at the largest position
    slow, resolved = [], False
    for i, pop in enumerate(scene.populations):
        for j, motion in enumerate(pop.motion):
            if isinstance(motion, Diffusion):
                moved = (2.0 * motion.diffusion_um2_per_s * step) ** 0.5
                key = "diffusion_um2_per_s"
            else:
                moved = motion.speed_um_per_s * step
                key = "speed_um_per_s"
            if moved >= MIN_SPACINGS_PER_FRAME * spacing:
                resolved = True
            elif moved > 0:
                slow.append((f"population[{i}].motion[{j}].{key}", moved))
    if slow and not resolved and not plan.has_noise:  # else the other changes swamp its rounding
        key, moved = slow[0]
        raise ValueError(
            f"{key}: moves {moved:.3g} µm per frame step ({step:g} s), less than "
            f"{MIN_SPACINGS_PER_FRAME:g} {name} spacings of the scatterer positions ({spacing:.3g} µm "
            f"at {top:.3g} µm), and nothing else in the scene (another motion, noise) changes the signal: "
            f"in {name} its LIV and OCDS would be rounding noise; {wider}leave the motion out (at this "
            "speed it is static)"
        )


def simulate(
    scene: Scene,
    *,
    trials: int | None = None,
    seed: int | None = None,
    dtype: torch.dtype | str | None = None,
    device: str | torch.device | None = None,
    truncation_tolerance: float | None = None,
    truncation: str | None = None,
    chunk_trials: int | None = None,
    threads: int | None = None,
    progress: bool = False,
) -> SimulationResult:
    """Simulate ``trials`` independent realizations of ``scene`` (all systems, all frames).

    Returns complex signals ``[trials, systems, frames]`` (complex64 for float32, complex128 for
    float64). Defaults come from the scene's ``[simulation]`` table (``truncation``: ``"hard"`` or
    ``"taper"``, :class:`~torchdoct.sim.config.SimulationSettings`). ``chunk_trials`` (rounded up to a
    multiple of 64) only sets how many trials are computed at once; ``threads`` how many chunks are
    computed at once, each with one torch thread (:mod:`torchdoct.runtime.threads`; default: the usable
    cores). Results are bit-identical for any value of either.
    """
    import time

    from .config import check_scene_argument, whole_argument

    check_scene_argument("td.simulate(scene)", scene)
    st = scene.simulation
    trials = st.trials if trials is None else whole_argument("trials", trials)
    seed = st.seed if seed is None else whole_argument("seed", seed)
    if chunk_trials is not None:
        chunk_trials = whole_argument("chunk_trials", chunk_trials)
    if trials < 1:
        raise ValueError(f"trials must be >= 1; got {trials}")
    if seed < 0:
        raise ValueError(f"seed must be >= 0; got {seed}")
    dtype = dtype or st.dtype
    if isinstance(dtype, str):
        if dtype not in ("float32", "float64"):
            raise ValueError(f"dtype must be 'float32' or 'float64'; got {dtype!r}")
        dtype = getattr(torch, dtype)
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"dtype must be torch.float32 or torch.float64; got {dtype}")
    from ..runtime.device import check_device

    device = torch.device(check_device(None if device is None else str(device), "device") or "cpu")
    threads = resolve_threads(threads)
    if truncation is not None and truncation not in TRUNCATION_MODES:
        raise ValueError(f"truncation must be one of {TRUNCATION_MODES}; got {truncation!r}")
    plan = make_plan(scene, truncation_tolerance=truncation_tolerance, truncation=truncation)
    check_precision(scene, plan, dtype)
    n_blocks = -(-trials // BLOCK_TRIALS)
    # keep a chunk's largest working tensors near 8M elements, and give every thread a chunk; refused
    # before any work when the chunks in flight and the output would not fit (torchdoct.runtime.resources)
    chunk_blocks = check_simulation(
        plan,
        trials=trials,
        n_systems=len(scene.systems),
        n_frames=scene.protocol.n_frames,
        threads=threads,
        chunk_trials=chunk_trials,
        dtype_bytes=torch.finfo(dtype).bits // 8,
    )
    t0 = time.perf_counter()
    pieces = []
    bar = None
    if not progress_disabled(progress):
        from tqdm.auto import tqdm

        bar = tqdm(total=trials, unit="trial", desc=f"simulate {scene.name or 'scene'}")
    done = 0
    last_trim = time.perf_counter()
    chunks = [list(range(b0, min(n_blocks, b0 + chunk_blocks))) for b0 in range(0, n_blocks, chunk_blocks)]
    with single_torch_thread():
        for blocks, piece in zip(
            chunks,
            map_ordered(lambda blocks: _simulate_chunk(scene, plan, blocks, seed, dtype, device), chunks, threads),
        ):
            pieces.append(piece)
            if time.perf_counter() - last_trim > 2.0:  # amortized: a trim costs a few ms of page faults
                release_free_memory()
                last_trim = time.perf_counter()
            if bar is not None:
                step = min(trials, (blocks[-1] + 1) * BLOCK_TRIALS) - done
                bar.update(step)
                done += step
    if bar is not None:
        bar.close()
    signals = torch.cat(pieces)[:trials]
    return SimulationResult(
        scene=scene,
        plan=plan,
        signals=signals,
        seed=seed,
        trials=trials,
        frame_times_s=scene.protocol.times_s,
        elapsed_s=time.perf_counter() - t0,
    )
