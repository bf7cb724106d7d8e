"""Feature means of torchdoct's simulator against the reference simulator (:mod:`refsim`): the cells,
the runs, and the z-test (Monte Carlo standard errors of both sides).

The configurations are those of the shipped signature models (``classifier/specs/signature.toml``):
840 nm at 4.9/3.8 µm, axial-reduced to 14 µm and lateral-reduced to 18 µm; 32 frames at 0.2048 s.
Features: every signature feature a shipped model reads (``rho_lin_m`` at the spec's lags,
``lin_contrast``, ``db_variance``), the field group (``g1_m``, ``g1_phase_m``, ``phase_ramp``) and LIV
and OCDS, computed on both sides by torchdoct's own extractors (:func:`torchdoct.sim.signature.signature`
and :func:`torchdoct.sim.metrics.compute_metrics`) — the numbers the models read.

**The test**: per feature and configuration, ``z = (mean_td − mean_ref)/√(SE_td² + SE_ref²)`` with
``SE = SD/√n`` over independent trials. The bound on ``|z|`` is Bonferroni over the comparisons of one
test at a family-wise false-alarm rate :data:`FAMILY_ALPHA`: ``z* = Φ⁻¹(1 − α/(2·K))`` (3.5 for 10
comparisons, 4.3 for 81), fixed before any result is seen.
"""

from __future__ import annotations

import functools
import math
import tomllib
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import refsim
from scipy import special

__all__ = [
    "FAMILY_ALPHA",
    "CONFIGS",
    "RHO_LIN_LAGS",
    "FIELD_LAGS",
    "NAMES",
    "DENSITY",
    "N_FRAMES",
    "DT",
    "CELLS",
    "z_bound",
    "reference_features",
    "recorded_reference",
    "summarize",
    "RECORD",
    "REF_TRIALS",
    "REF_SEED",
    "torchdoct_features",
    "compare",
    "format_failures",
]

#: Family-wise false-alarm rate of one comparison test (over all its features and configurations).
FAMILY_ALPHA = 1e-3
#: Trials and seed of the reference runs the comparison tests read (1024 trials: module docstring of
#: test_reference_features), and the file that records them (:func:`recorded_reference`).
REF_TRIALS = 1024
REF_SEED = 20261201
RECORD = Path(__file__).resolve().parent / "data" / "reference-features.json"
RECORD_COMMAND = "python tests/reference/refcompare.py --record"
_SPEC = Path(__file__).resolve().parents[2] / "classifier" / "specs" / "signature.toml"


def _spec() -> dict:
    with open(_SPEC, "rb") as fh:
        return tomllib.load(fh)


_S = _spec()
#: (name, wavelength µm, lateral 1/e² width along x µm, axial FWHM µm, lateral width along y µm or None
#: = as x): the signature spec's three configurations (indices 0-2), then a B-scan's x-only lateral
#: reduction to 18 µm that keeps 4.9 µm along y (index 3).
CONFIGS = tuple(
    (
        c["name"],
        c["wavelength_um"],
        c["lateral_resolution_um"],
        c["axial_resolution_um"],
        c.get("lateral_resolution_y_um"),
    )
    for c in _S["configuration"]
) + (("lateral=18 x-only", 0.84, 18.0, 3.8, 4.9),)
RHO_LIN_LAGS = tuple(int(m.rsplit("_", 1)[1]) for m in _S["metrics"] if m.startswith("rho_lin_"))
FIELD_LAGS = (1, 2, 3, 4, 6, 8)  # torchdoct.sim.signature.DEFAULT_FIELD_LAGS (the field group's lags)
N_FRAMES = int(_S["protocol"]["n_frames"])
DT = float(_S["protocol"]["frame_interval_s"])
#: Density of the moving scatterers (µm⁻³), inside the training prior's U[0.02, 0.1].
DENSITY = 0.05
NAMES = refsim.feature_names(RHO_LIN_LAGS, FIELD_LAGS)
SIGNATURE_NAMES = tuple(n for n in NAMES if n not in ("liv", "ocds"))

#: Cells: slow motions (short lags carry the bias of a truncated PSF), flow at several angles.
CELLS = {
    "flow v=0.5 θ=20°": refsim.Motion("flow", speed_um_per_s=0.5, polar_angle_deg=20.0, azimuth_deg=30.0),
    "flow v=0.5 θ=0°": refsim.Motion("flow", speed_um_per_s=0.5, polar_angle_deg=0.0),
    "flow v=0.2 θ=0°": refsim.Motion("flow", speed_um_per_s=0.2, polar_angle_deg=0.0),
    "flow v=0.5 θ=45°": refsim.Motion("flow", speed_um_per_s=0.5, polar_angle_deg=45.0, azimuth_deg=200.0),
    "flow v=0.5 θ=70°": refsim.Motion("flow", speed_um_per_s=0.5, polar_angle_deg=70.0, azimuth_deg=100.0),
    "flow v=0.5 θ=90°": refsim.Motion("flow", speed_um_per_s=0.5, polar_angle_deg=90.0),
    "flow v=2 θ=45°": refsim.Motion("flow", speed_um_per_s=2.0, polar_angle_deg=45.0),
    "diffusion D=0.002": refsim.Motion("diffusion", diffusion_um2_per_s=0.002),
    "diffusion D=0.05": refsim.Motion("diffusion", diffusion_um2_per_s=0.05),
    "ballistic v=0.03 iso": refsim.Motion("ballistic", speed_um_per_s=0.03, directions="isotropic"),
    "ballistic v=0.3 uniform-angles": refsim.Motion("ballistic", speed_um_per_s=0.3, directions="uniform-angles"),
}


#: Cells for the B-scan configuration (index 3): flow with a component along y (out of the B-scan
#: plane, where the PSF keeps its original width) and along x, and diffusion.
BSCAN_CELLS = {
    "flow v=2 θ=45° along y": refsim.Motion("flow", speed_um_per_s=2.0, polar_angle_deg=45.0, azimuth_deg=90.0),
    "flow v=2 θ=60° along x": refsim.Motion("flow", speed_um_per_s=2.0, polar_angle_deg=60.0, azimuth_deg=0.0),
    "diffusion D=0.05": CELLS["diffusion D=0.05"],
}


def _motion(cell: str) -> refsim.Motion:
    return CELLS[cell] if cell in CELLS else BSCAN_CELLS[cell]


def z_bound(comparisons: int, alpha: float = FAMILY_ALPHA) -> float:
    """Bonferroni bound ``Φ⁻¹(1 − α/(2K))`` on ``|z|`` for ``K`` comparisons at family-wise rate ``α``."""
    return float(-special.ndtri(alpha / (2.0 * comparisons)))


def _optics(configs: Sequence[int]) -> list[refsim.Optics]:
    return [refsim.Optics(wl, lat, ax, lateral_y_um=lat_y) for _, wl, lat, ax, lat_y in (CONFIGS[i] for i in configs)]


def _torch_features(signals, names: Sequence[str] = NAMES) -> dict[str, np.ndarray]:
    """Features ``{name: [trials, systems]}`` by torchdoct's extractors (signature + LIV/OCDS)."""
    import torch

    from torchdoct.sim.config import Analysis
    from torchdoct.sim.metrics import compute_metrics
    from torchdoct.sim.signature import signature

    x = torch.as_tensor(signals)
    times = [i * DT for i in range(x.shape[-1])]
    sig = tuple(n for n in names if n not in ("liv", "ocds"))
    out: dict[str, np.ndarray] = {}
    if sig:
        _, f = signature(x, times, names=sig)
        for i, n in enumerate(sig):
            out[n] = f[..., i].double().numpy()
    extra = tuple(n for n in names if n in ("liv", "ocds"))
    if extra:
        met = compute_metrics(x, times, Analysis(metrics=extra, ocds_delay_range_s=(DT, 6 * DT)))
        for n in extra:
            out[n] = met[n].double().numpy()
    return out


@functools.cache
def reference_features(
    cell: str, trials: int, seed: int = REF_SEED, configs: tuple[int, ...] = (0, 1, 2)
) -> dict[str, np.ndarray]:
    """Features ``{name: [trials, configs]}`` of the reference simulator's fields for ``cell`` at the
    configurations ``configs`` (indices into :data:`CONFIGS`; cached per session)."""
    e = refsim.simulate(
        _optics(configs),
        _motion(cell),
        density_per_um3=DENSITY,
        n_frames=N_FRAMES,
        frame_interval_s=DT,
        trials=trials,
        seed=seed,
    )
    return _torch_features(e)


def summarize(features: dict[str, np.ndarray]) -> dict[str, list[list[float]]]:
    """Per feature and configuration, what :func:`compare` reads of a side's trials: ``[mean, SD (ddof 1),
    finite trials, NaN trials]`` over the finite trials."""
    out = {}
    for name, values in features.items():
        rows = []
        for s in range(values.shape[1]):
            x = values[:, s]
            f = x[np.isfinite(x)]
            rows.append([float(f.mean()), float(f.std(ddof=1)), int(f.size), int(x.size - f.size)])
        out[name] = rows
    return out


def record_key(cell: str, trials: int, seed: int, configs: Sequence[int]) -> str:
    """The key of one reference run in :data:`RECORD`."""
    return f"{cell} | trials {trials} | seed {seed} | configs {','.join(map(str, configs))}"


def record_runs() -> list[tuple[str, tuple[int, ...]]]:
    """The reference runs the comparison tests read: every cell at the signature configurations, every
    B-scan cell at the x-only lateral reduction."""
    return [(c, (0, 1, 2)) for c in CELLS] + [(c, (3,)) for c in BSCAN_CELLS]


@functools.cache
def _record() -> dict:
    import json

    if not RECORD.is_file():
        raise FileNotFoundError(f"{RECORD} is missing: write it with `{RECORD_COMMAND}`")
    return json.loads(RECORD.read_text(encoding="utf-8"))


def recorded_reference(
    cell: str, trials: int = REF_TRIALS, seed: int = REF_SEED, configs: tuple[int, ...] = (0, 1, 2)
) -> dict[str, list[list[float]]]:
    """The :func:`summarize` of :func:`reference_features` for ``cell`` as :data:`RECORD` holds it: the
    reference simulator is deterministic for a seed, so its run is recorded once (``RECORD_COMMAND``) instead
    of recomputed by every comparison (a minute per cell on one core); a test recomputes runs and checks
    the record against them."""
    runs = _record()["runs"]
    key = record_key(cell, trials, seed, configs)
    if key not in runs:
        raise KeyError(f"{RECORD.name} holds no reference run {key!r}: write it again with `{RECORD_COMMAND}`")
    return runs[key]


def torchdoct_scene(cell: str, configs: Sequence[int] = (0, 1, 2)):
    """The torchdoct scene of a cell: the configurations ``configs``, one population, the paper's protocol."""
    import torchdoct as td

    m = _motion(cell)
    if m.kind == "flow":
        motion = td.Flow(speed_um_per_s=m.speed_um_per_s, polar_angle_deg=m.polar_angle_deg, azimuth_deg=m.azimuth_deg)
    elif m.kind == "ballistic":
        motion = td.RandomBallistic(speed_um_per_s=m.speed_um_per_s, directions=m.directions)
    else:
        motion = td.Diffusion(diffusion_um2_per_s=m.diffusion_um2_per_s)
    systems = tuple(
        td.OCTSystem(
            name=n,
            wavelength_um=wl,
            lateral_resolution_um=lat,
            axial_resolution_um=ax,
            **({} if lat_y is None else {"lateral_resolution_y_um": lat_y}),
        )
        for n, wl, lat, ax, lat_y in (CONFIGS[i] for i in configs)
    )
    return td.Scene(
        systems=systems,
        protocol=td.Protocol(n_frames=N_FRAMES, frame_interval_s=DT),
        populations=(td.Population(density_per_um3=DENSITY, motion=(motion,)),),
        name=cell,
    )


def torchdoct_features(
    cell: str,
    trials: int,
    *,
    seed: int = 7,
    dtype: str = "float32",
    truncation_tolerance: float | None = None,
    configs: Sequence[int] = (0, 1, 2),
    **simulate_kw,
) -> dict[str, np.ndarray]:
    """Features of torchdoct's fields for ``cell`` (``truncation_tolerance=None``: the scene default)."""
    import torch

    import torchdoct as td

    res = td.simulate(
        torchdoct_scene(cell, configs),
        trials=trials,
        seed=seed,
        dtype=dtype,
        truncation_tolerance=truncation_tolerance,
        **simulate_kw,
    )
    return _torch_features(res.signals.to(torch.complex128))


def compare(a: dict, b: dict, configs: Sequence[int] = (0, 1, 2)) -> list[dict]:
    """Per feature and configuration: means, SEs, z of ``a − b`` (NaN trials dropped and counted); each side
    is trials ``{name: [trials, configs]}`` or their :func:`summarize`."""

    def stats(side: dict) -> dict:
        return {k: (summarize({k: v})[k] if isinstance(v, np.ndarray) else v) for k, v in side.items()}

    sa, sb = stats(a), stats(b)
    rows = []
    for name in sa:
        for s, cname in enumerate(CONFIGS[i][0] for i in configs):
            (ma, sda, na, nan_a), (mb, sdb, nb, nan_b) = sa[name][s], sb[name][s]
            se = math.hypot(sda / math.sqrt(na), sdb / math.sqrt(nb))
            d = float(ma - mb)
            rows.append(
                {
                    "feature": name,
                    "config": cname,
                    "a": float(ma),
                    "b": float(mb),
                    "bias": d,
                    "se": se,
                    "z": d / se if se > 0 else (0.0 if d == 0 else math.inf),
                    "nan_a": int(nan_a),
                    "nan_b": int(nan_b),
                }
            )
    return rows


def format_failures(rows: list[dict], bound: float, top: int = 8) -> str:
    worst = sorted(rows, key=lambda r: -abs(r["z"]))[:top]
    return (
        "; ".join(
            f"{r['feature']}@{r['config']}: {r['a']:.5g} vs {r['b']:.5g} (bias {r['bias']:+.2g} ± "
            f"{r['se']:.2g}, z {r['z']:+.1f})"
            for r in worst
        )
        + f"; |z| bound {bound:.2f}"
    )


def main(argv: Sequence[str] | None = None) -> int:
    """``--record``: run every reference run of :func:`record_runs` (``--jobs`` processes) and write
    :data:`RECORD`."""
    import argparse
    import json
    from concurrent.futures import ProcessPoolExecutor

    p = argparse.ArgumentParser(prog="python tests/reference/refcompare.py", description=main.__doc__)
    p.add_argument("--record", action="store_true", required=True)
    p.add_argument("--jobs", type=int, default=1)
    args = p.parse_args(argv)
    runs = record_runs()
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        done = list(pool.map(_summarized_run, runs))
    record = {
        "command": RECORD_COMMAND,
        "trials": REF_TRIALS,
        "seed": REF_SEED,
        "runs": {record_key(c, REF_TRIALS, REF_SEED, k): s for (c, k), s in zip(runs, done)},
    }
    RECORD.parent.mkdir(parents=True, exist_ok=True)
    RECORD.write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")
    print(f"wrote {RECORD.name}: {len(runs)} reference runs")
    return 0


def _summarized_run(run: tuple[str, tuple[int, ...]]) -> dict:
    cell, configs = run
    return summarize(reference_features(cell, REF_TRIALS, REF_SEED, configs))


if __name__ == "__main__":  # pragma: no cover
    import sys

    sys.exit(main())
