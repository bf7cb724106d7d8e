"""How often rule 5 of :mod:`classifier.ambiguity` (a held pattern that moved) fires: on direction-symmetric
motions (its false detections) and on slow flow (its detections), on patches of the patch simulator.

Run (from the repository root)::

    python -m tests.reference.translation_rule --out DIR [--trials 160] [--pitch-um 1.5] [--seed 5000]

Writes ``<out>/translation-rule.json`` and ``.md`` (not over existing files without ``--force``).

**Data.** Each trial is one static-free B-scan patch (:func:`torchdoct.sim.patch.simulate_patch`: 21 × 21
pixels, 840 nm, 4.9/3.8 µm, 32 frames at 204.8 ms, density 0.02 µm⁻³, the lowest of the training prior:
the fewest scatterers per PSF, where a few scatterers moving alone come nearest a translation), with its own
scatterers; the sample is the centre pixel (the maps' speckle channels,
:func:`torchdoct.sim.speckle.map_speckle_features`, window 9, offsets ±2), judged as the maps judge it (its
window and the vote of the windows of its 9-pixel neighbourhood) and by its own window alone. Conditions,
with and without 20 dB noise:

* the null motions: random-ballistic motion at :data:`BALLISTIC_UM_S` and diffusion at :data:`DIFFUSION_UM2_S`
  (the grid's three levels of each, and one more decade below and between);
* flow at :data:`FLOW_UM_S` at the grid's polar and azimuth angles (the slow one: the speed no earlier rule
  sees).

Reported per condition: the share of trials where the rule fires, with its binomial standard error. The
rule's thresholds are physical (a held pattern, a move of a fraction of a pitch, a straight line); this
records what they give, on patches independent of the phantom grid (another simulator path and seeds).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

#: Random-ballistic speeds (µm/s): the grid's B-scan levels and a decade around them.
BALLISTIC_UM_S = (0.003, 0.0123, 0.03, 0.0536, 0.1, 0.233)
#: Diffusion coefficients (µm²/s): the grid's B-scan levels and one between.
DIFFUSION_UM2_S = (9.26e-5, 3e-4, 8.25e-4, 7.36e-3)
#: Flow speeds (µm/s): the grid's slow and mid B-scan levels (the mid one leaves the offset grid within the
#: longest lag: the rule judges it on the lags its pattern held through).
FLOW_UM_S = (0.335, 1.54)
ANGLES_DEG = (10.0, 45.0, 80.0)
#: Patch side (pixels): the centre's window (9), the windows of its 9-pixel neighbourhood that vote, and
#: the ±2-pixel offset grid.
PATCH_PX = 21
AZIMUTHS_DEG = (0.0, 45.0, 90.0)


def conditions() -> list[dict]:
    out: list[dict] = []
    for snr in (None, 20.0):
        out += [dict(motion="ballistic", speed_um_s=v, snr_db=snr) for v in BALLISTIC_UM_S]
        out += [dict(motion="diffusion", diffusion_um2_s=d, snr_db=snr) for d in DIFFUSION_UM2_S]
        out += [
            dict(motion="flow", speed_um_s=v, polar_deg=p, azimuth_deg=a, snr_db=snr)
            for v in FLOW_UM_S
            for p in ANGLES_DEG
            for a in AZIMUTHS_DEG
        ]
    return out


def fires(cond: dict, trials: int, seed: int, pitch_um: float) -> tuple[np.ndarray, np.ndarray]:
    """Rule 5 per trial of one condition at the patch's centre pixel: ``(rule, window)``, bool ``[trials]``
    each; ``rule`` as the maps apply it (the centre's window and the vote of the windows around it,
    :data:`classifier.ambiguity.TRANSLATION_SUPPORT_MIN`), ``window`` the centre's own window alone."""
    import torch

    from classifier.ambiguity import translated
    from torchdoct.sim.patch import simulate_patch
    from torchdoct.sim.speckle import map_speckle_features, speckle_motion

    n = PATCH_PX
    field = simulate_patch(
        cond["motion"],
        trials=trials,
        seed=seed,
        shape=(n, n),
        pitch_um=(pitch_um, pitch_um),
        density_per_um3=0.02,
        speed_um_s=cond.get("speed_um_s", 0.0),
        diffusion_um2_s=cond.get("diffusion_um2_s", 0.0),
        polar_deg=cond.get("polar_deg", 0.0),
        azimuth_deg=cond.get("azimuth_deg", 0.0),
        snr_db=cond["snr_db"],
    )
    names = map_speckle_features(2, n_frames=field.shape[1])
    with torch.no_grad():
        _, x = speckle_motion(field, {"z": pitch_um, "x": pitch_um}, 0.2048, names, window=9, max_offset=2)
    maps = x.double().numpy()  # [trials, F, n, n]
    pitch = {"z": pitch_um, "x": pitch_um}
    centre = (n // 2) * n + n // 2
    rule, window = np.zeros(trials, bool), np.zeros(trials, bool)
    for t in range(trials):
        channels = {f"{name}@original": maps[t, j] for j, name in enumerate(names)}
        seen, _ = translated(channels, pitch, window_px=9)
        alone, _ = translated({k: v.reshape(-1) for k, v in channels.items()}, pitch, window_px=9)
        assert seen is not None and alone is not None
        rule[t], window[t] = seen[centre], alone[centre]
    return rule, window


def _se(p: float, n: int) -> float:
    """Binomial standard error of a share ``p`` of ``n`` trials (at least that of one trial in ``n``)."""
    return math.sqrt(max(p * (1 - p), 1.0 / n) / n)


def run(trials: int = 160, pitch_um: float = 1.5, seed: int = 5000, progress: bool = True) -> dict:
    rows = []
    t0 = time.perf_counter()
    conds = conditions()
    for i, c in enumerate(conds):
        f, alone = fires(c, trials, seed + i, pitch_um)
        p, q = float(f.mean()), float(alone.mean())
        rows.append(
            {
                **c,
                "trials": trials,
                "fired": p,
                "se": _se(p, trials),
                "fired_window_alone": q,
                "se_window_alone": _se(q, trials),
            }
        )
        if progress:
            print(f"[{i + 1}/{len(conds)}] {c}: {p:.3f}", file=sys.stderr, flush=True)
    from classifier import ambiguity as amb

    null = [r["fired"] for r in rows if r["motion"] != "flow"]
    null_alone = [r["fired_window_alone"] for r in rows if r["motion"] != "flow"]
    return {
        "schema_version": 2,
        "benchmark": "translation-rule",
        "command": f"python -m tests.reference.translation_rule --out DIR --trials {trials} --pitch-um {pitch_um:g} "
        f"--seed {seed}",
        "pitch_um": pitch_um,
        "thresholds": {
            "hold_min": amb.TRANSLATION_HOLD_MIN,
            "growth_min_pitch": amb.TRANSLATION_GROWTH_MIN,
            "linear_max_pitch": amb.TRANSLATION_LINEAR_MAX,
            "support_min": amb.TRANSLATION_SUPPORT_MIN,
        },
        "patch_px": PATCH_PX,
        "rows": rows,
        "null_mean": float(np.mean(null)),
        "null_max": float(np.max(null)),
        "null_mean_window_alone": float(np.mean(null_alone)),
        "null_max_window_alone": float(np.max(null_alone)),
        "seconds": time.perf_counter() - t0,
    }


def _label(r: dict) -> str:
    if r["motion"] == "diffusion":
        return f"diffusion D = {r['diffusion_um2_s']:g} µm²/s"
    if r["motion"] == "ballistic":
        return f"random ballistic {r['speed_um_s']:g} µm/s"
    return f"flow {r['speed_um_s']:g} µm/s, polar {r['polar_deg']:g}°, azimuth {r['azimuth_deg']:g}°"


def markdown(res: dict) -> str:
    th = res["thresholds"]
    lines = [
        f"# Rule 5 (a held pattern that moved): how often it fires (static-free B-scan patches, pitch "
        f"{res['pitch_um']:g} µm)",
        "",
        f"Thresholds: held peak ≥ {th['hold_min']:g}, move ≥ {th['growth_min_pitch']:g} pitch, "
        f"line residual ≤ {th['linear_max_pitch']:g} pitch, window vote ≥ {th['support_min']:g}. "
        f"Command: `{res['command']}`.",
        "",
        "| motion | SNR | fired (rule) | SE | fired (window alone) | SE |",
        "|---|---|---|---|---|---|",
    ]
    for r in res["rows"]:
        snr = "none" if r["snr_db"] is None else f"{r['snr_db']:g} dB"
        lines.append(
            f"| {_label(r)} | {snr} | {r['fired']:.3f} | {r['se']:.3f} | {r['fired_window_alone']:.3f} | "
            f"{r['se_window_alone']:.3f} |"
        )
    lines += [
        "",
        f"Direction-symmetric motions (false detections): mean {res['null_mean']:.4f}, worst condition "
        f"{res['null_max']:.4f} (window alone: {res['null_mean_window_alone']:.4f}, "
        f"{res['null_max_window_alone']:.4f}).",
        "",
    ]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--trials", type=int, default=160)
    ap.add_argument("--pitch-um", type=float, default=1.5)
    ap.add_argument("--seed", type=int, default=5000)
    ap.add_argument("--force", action="store_true")
    a = ap.parse_args(argv)
    out = Path(a.out)
    paths = [out / "translation-rule.json", out / "translation-rule.md"]
    if not a.force and any(p.exists() for p in paths):
        print(f"error: {paths[0]} exists; give --force to replace it", file=sys.stderr)
        return 2
    res = run(a.trials, a.pitch_um, a.seed)
    out.mkdir(parents=True, exist_ok=True)
    paths[0].write_text(json.dumps(res, indent=2) + "\n")
    paths[1].write_text(markdown(res))
    print(markdown(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
