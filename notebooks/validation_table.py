"""The validation table of the documentation: the simulator against the closed forms of the point model.

Run ``python notebooks/validation_table.py`` to print it, ``--json FILE`` to also write it as the results
file the documentation renders (``docs/results/validation-table.json``). For each row: 4,096
trials of 32 frames at 204.8 ms, float64, seed 11, 0.055 µm⁻³, the default truncation tolerance;
g1(τ) = ⟨E(t)E*(t+τ)⟩/⟨I⟩ and ⟨I I_τ⟩/⟨I⟩² − 1 over all frame pairs at the lag, with batch-means
standard errors (64 batches), against ``torchdoct.sim.theory`` (physics reference §5.3-5.4:
|g1|² + j/N_eff). "largest |z|" is over ⟨I⟩, the contrast 1 + 1/N_eff, and both statistics at the
row's lag.
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import torch

import torchdoct as td
from torchdoct.conventions import mean_intensity as mean_intensity_theory
from torchdoct.conventions import n_eff
from torchdoct.sim import theory as th

DT, RHO, TRIALS, SEED = 0.2048, 0.055, 4096, 11
HIGH = td.OCTSystem(name="840-high", wavelength_um=0.84, lateral_resolution_um=4.9, axial_resolution_um=3.8)
LAT18 = td.OCTSystem(name="840-lat18", wavelength_um=0.84, lateral_resolution_um=18.0, axial_resolution_um=3.8)

ROWS = [
    ("diffusion D = 0.005 µm²/s", td.Diffusion(diffusion_um2_per_s=0.005), HIGH, 1),
    ("diffusion D = 0.5 µm²/s", td.Diffusion(diffusion_um2_per_s=0.5), HIGH, 1),
    ("diffusion D = 15 µm²/s", td.Diffusion(diffusion_um2_per_s=15.0), HIGH, 1),
    ("ballistic, isotropic, v = 0.1 µm/s", td.RandomBallistic(speed_um_per_s=0.1), HIGH, 6),
    (
        "ballistic, uniform angles, v = 0.1 µm/s",
        td.RandomBallistic(speed_um_per_s=0.1, directions="uniform-angles"),
        HIGH,
        31,
    ),
    ("flow 45°, v = 1 µm/s", td.Flow(speed_um_per_s=1.0, polar_angle_deg=45.0), HIGH, 1),
    (
        "ballistic, uniform angles, v = 6 µm/s, 18 µm lateral",
        td.RandomBallistic(speed_um_per_s=6.0, directions="uniform-angles"),
        LAT18,
        1,
    ),
]


def _batch(stat, E, n=64):
    full = complex(stat(E))
    per = np.array([complex(stat(b)) for b in torch.chunk(E, n)])
    return full, float(np.std(per.real, ddof=1) / math.sqrt(n)), float(np.std(per.imag, ddof=1) / math.sqrt(n))


def _mi(E):
    return float((E.real**2 + E.imag**2).mean())


def _fmt(z: complex, se_re: float, se_im: float, digits: int, imag: bool) -> str:
    """``re ± se`` or, where the theory is complex (flow), ``re ± im·i (± se)``; minus signs typeset."""
    if imag:
        out = f"{z.real:.{digits}f} {'+' if z.imag >= 0 else '−'} {abs(z.imag):.{digits}f}i (± {max(se_re, se_im):.{digits}f})"
    else:
        out = f"{z.real:.{digits}f} ± {se_re:.{digits}f}"
    return out.replace("-", "−")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description="the simulator against the closed forms of the point model")
    ap.add_argument("--json", metavar="FILE", help="also write the rows as JSON")
    args = ap.parse_args(argv)
    records = []
    print("| motion | τ | g1 simulated | g1 theory | ⟨I I_τ⟩/⟨I⟩² − 1 simulated | theory | largest \\|z\\| |")
    print("|---|---|---|---|---|---|---:|")
    for name, motion, system, lag in ROWS:
        scene = td.Scene(
            systems=(system,),
            protocol=td.Protocol(n_frames=32, frame_interval_s=DT),
            populations=(td.Population(density_per_um3=RHO, motion=(motion,)),),
        )
        E = td.simulate(scene, trials=TRIALS, seed=SEED, dtype="float64").signals[:, 0, :]
        ne = n_eff(RHO, system.lateral_resolution_um, system.axial_resolution_um)
        g_th, j_th = (complex(np.atleast_1d(x)[0]) for x in th.g1_and_j(motion, system, np.array([lag * DT])))
        cov_th = abs(g_th) ** 2 + j_th.real / ne
        zs = []
        mi, se, _ = _batch(_mi, E)
        zs.append((mi.real - mean_intensity_theory(RHO, system.lateral_resolution_um, system.axial_resolution_um)) / se)
        c2, se, _ = _batch(lambda x: float(((x.real**2 + x.imag**2) ** 2).mean()) / _mi(x) ** 2 - 1.0, E)
        zs.append((c2.real - (1 + 1 / ne)) / se)
        g, se_re, se_im = _batch(lambda x: complex((x[:, :-lag] * x[:, lag:].conj()).mean()) / _mi(x), E)
        zs.append((g.real - g_th.real) / se_re)
        if abs(g_th.imag) > 1e-6:
            zs.append((g.imag - g_th.imag) / se_im)
        cov, se_c, _ = _batch(
            lambda x: (
                float(((x.real**2 + x.imag**2)[:, :-lag] * (x.real**2 + x.imag**2)[:, lag:]).mean()) / _mi(x) ** 2 - 1.0
            ),
            E,
        )
        zs.append((cov.real - cov_th) / se_c)
        g_sim = _fmt(g, se_re, se_im, 4, abs(g_th.imag) > 1e-6)
        g_ref = (
            f"{g_th.real:.4f} {'+' if g_th.imag >= 0 else '−'} {abs(g_th.imag):.4f}i"
            if abs(g_th.imag) > 1e-6
            else f"{g_th.real:.4f}"
        ).replace("-", "−")
        print(
            f"| {name} | {lag * DT:.4f} s | {g_sim} | {g_ref} | {cov.real:.4f} ± {se_c:.4f} | {cov_th:.4f} | "
            f"{max(abs(z) for z in zs):.1f} |"
        )
        records.append(
            {
                "motion": name,
                "lag_s": lag * DT,
                "g1_simulated": g_sim,
                "g1_theory": g_ref,
                "g1_re": g.real,
                "g1_im": g.imag,
                "g1_se_re": se_re,
                "g1_se_im": se_im,
                "g1_theory_re": g_th.real,
                "g1_theory_im": g_th.imag,
                "intensity_cov_simulated": cov.real,
                "intensity_cov_se": se_c,
                "intensity_cov_theory": cov_th,
                "max_abs_z": max(abs(z) for z in zs),
            }
        )
    if args.json:
        out = {
            "command": "python notebooks/validation_table.py --json FILE",
            "trials": TRIALS,
            "seed": SEED,
            "density_per_um3": RHO,
            "frame_interval_s": DT,
            "n_frames": 32,
            "dtype": "float64",
            "rows": records,
        }
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump(out, f, indent=1, ensure_ascii=False)


if __name__ == "__main__":
    main()
