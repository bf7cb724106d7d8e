"""What the speckle-motion features add: gradient boosting on static-free B-scan patches, per-pixel
signature against the window's signature against the speckle features (torchdoct.sim.speckle).

Run (from the repository root)::

    python -m tests.reference.speckle_ceiling --out DIR [--per-class 400] [--window 9] [--seed 0]

Writes ``<out>/speckle-ceiling.json`` and ``.md`` (not over existing files without ``--force``).

**Data.** Every draw is one B-scan patch (:func:`torchdoct.sim.patch.simulate_patch`: 13 × 13 pixels of
2 µm, 840 nm, 4.9/3.8 µm, 32 frames at 204.8 ms, density 0.055 µm⁻³, no static tissue, no noise unless
``--snr-db``) with its own scatterers and parameters: flow at a log-uniform speed in
``FLOW_UM_S`` with an isotropic direction, random-ballistic motion (isotropic directions) at a
log-uniform speed in ``BALLISTIC_UM_S``, diffusion at a log-uniform D in ``DIFFUSION_UM2_S``. The centre
pixel is the sample. Features:

* ``pixel``: the signature's intensity features (:func:`torchdoct.sim.signature.default_features`, the
  intensity part) of the centre pixel;
* ``pooled``: the same averaged over the ``w × w`` window around it (what ``doct-classify --pool w``
  gives a per-pixel model);
* ``speckle``: :func:`torchdoct.sim.speckle.default_speckle_features` of the window;
* ``pooled+speckle``.

**Model.** scikit-learn's ``HistGradientBoostingClassifier`` (default settings, fixed seed) trained on
the even draws, tested on the odd draws. Reported: balanced accuracy over the three classes, and the
ROC AUC of flow against random-ballistic motion (the score ``p(flow)`` on the flow and ballistic test
pixels). A matched prior (train and test from the same law): an upper bound of what each feature set
gives on this data, not a shipped model's accuracy.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

FLOW_UM_S = (0.05, 2.0)
BALLISTIC_UM_S = (0.003, 0.3)
DIFFUSION_UM2_S = (0.0003, 0.3)
CLASSES = ("diffusion", "ballistic", "flow")
SHAPE = (13, 13)
PITCH_UM = 2.0
DT_S = 0.2048
N_FRAMES = 32


def draw_params(k: int, seed: int) -> dict:
    """Class and parameters of draw ``k`` (class ``k mod 3``)."""
    rng = np.random.default_rng([seed, k])
    cls = CLASSES[k % 3]

    def logu(lo, hi):
        return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))

    if cls == "flow":
        return {
            "motion": "flow",
            "speed_um_s": logu(*FLOW_UM_S),
            "polar_deg": math.degrees(math.acos(rng.uniform(-1.0, 1.0))),
            "azimuth_deg": rng.uniform(0, 360),
        }
    if cls == "ballistic":
        return {"motion": "ballistic", "speed_um_s": logu(*BALLISTIC_UM_S)}
    return {"motion": "diffusion", "diffusion_um2_s": logu(*DIFFUSION_UM2_S)}


def features(k: int, seed: int, window: int, snr_db: float | None) -> dict[str, np.ndarray]:
    """The four feature sets of draw ``k`` (module docstring)."""
    from torchdoct.sim.patch import simulate_patch
    from torchdoct.sim.signature import available_features, default_features, pixel_features
    from torchdoct.sim.speckle import speckle_motion

    p = draw_params(k, seed)
    t0 = time.perf_counter()
    e = simulate_patch(
        trials=1,
        seed=seed * 1_000_003 + k,
        shape=SHAPE,
        pitch_um=(PITCH_UM, PITCH_UM),
        n_frames=N_FRAMES,
        frame_interval_s=DT_S,
        snr_db=snr_db,
        **p,
    )[0]  # [T, Z, X]
    sim_s = time.perf_counter() - t0
    times = [i * DT_S for i in range(N_FRAMES)]
    names = available_features(default_features(N_FRAMES), False)
    _, sig = pixel_features((e.abs() ** 2).movedim(0, -1).to(torch.float64), times, names)  # [Z, X, F]
    cz, cx = SHAPE[0] // 2, SHAPE[1] // 2
    h = window // 2
    pooled = sig[cz - h : cz + h + 1, cx - h : cx + h + 1].reshape(-1, sig.shape[-1])
    pooled = torch.nanmean(pooled, 0)
    _, sp = speckle_motion(e[None], {"z": PITCH_UM, "x": PITCH_UM}, DT_S, window=window)
    return {
        "pixel": sig[cz, cx].numpy(),
        "pooled": pooled.numpy(),
        "speckle": sp[0, :, cz, cx].numpy(),
        "patch_seconds": sim_s,
    }


def pixel_seconds_per_trial(trials: int = 400, seed: int = 0) -> dict[str, float]:
    """Wall time per trial of the point simulator (``torchdoct.simulate``, one pixel, float32, one thread, the
    default truncation) for one mid-range cell of each motion: the cost of a per-pixel training sample."""
    from torchdoct.sim.config import Analysis, Diffusion, Flow, OCTSystem, Population, Protocol, RandomBallistic, Scene
    from torchdoct.sim.simulate import simulate

    system = OCTSystem(name="840nm-high", wavelength_um=0.84, lateral_resolution_um=4.9, axial_resolution_um=3.8)
    motions = {
        "diffusion": Diffusion(diffusion_um2_per_s=0.01),
        "ballistic": RandomBallistic(speed_um_per_s=0.05),
        "flow": Flow(speed_um_per_s=0.3, polar_angle_deg=45.0),
    }
    out = {}
    for name, m in motions.items():
        scene = Scene(
            systems=(system,),
            protocol=Protocol(n_frames=N_FRAMES, frame_interval_s=DT_S),
            analysis=Analysis(metrics=("liv", "ocds")),
            name=name,
            populations=(Population(density_per_um3=0.055, motion=(m,)),),
        )
        simulate(scene, trials=8, seed=seed, dtype="float32", threads=1, progress=False)  # warm-up
        t0 = time.perf_counter()
        simulate(scene, trials=trials, seed=seed, dtype="float32", threads=1, progress=False)
        out[name] = (time.perf_counter() - t0) / trials
    return out


def run(per_class: int, window: int, seed: int, snr_db: float | None) -> dict:
    from sklearn.ensemble import HistGradientBoostingClassifier
    from sklearn.metrics import balanced_accuracy_score, roc_auc_score
    from tqdm.auto import tqdm

    torch.set_num_threads(1)
    n = 3 * per_class
    t0 = time.perf_counter()
    rows = [features(k, seed, window, snr_db) for k in tqdm(range(n), desc="patches", unit="patch")]
    sim_s = time.perf_counter() - t0
    y = np.array([k % 3 for k in range(n)])
    sets = {"pixel": ["pixel"], "pooled": ["pooled"], "speckle": ["speckle"], "pooled+speckle": ["pooled", "speckle"]}
    train, test = np.arange(n) % 2 == 0, np.arange(n) % 2 == 1
    patch_s = float(sum(r["patch_seconds"] for r in rows))
    pixel = pixel_seconds_per_trial()
    out: dict = {
        "per_class": per_class,
        "window": window,
        "seed": seed,
        "snr_db": snr_db,
        "simulation_seconds": sim_s,
        "patch_simulation_seconds_per_sample": patch_s / n,
        "pixel_simulation_seconds_per_sample": pixel,
        "priors": {"flow_um_s": FLOW_UM_S, "ballistic_um_s": BALLISTIC_UM_S, "diffusion_um2_s": DIFFUSION_UM2_S},
        "results": {},
    }
    for name, parts in sets.items():
        x = np.concatenate([np.stack([r[p] for r in rows]) for p in parts], axis=1).astype(np.float64)
        clf = HistGradientBoostingClassifier(random_state=0).fit(x[train], y[train])
        pred = clf.predict(x[test])
        prob = clf.predict_proba(x[test])
        fb = np.isin(y[test], (1, 2))
        auc = roc_auc_score(y[test][fb] == 2, prob[fb, 2])
        conf = np.zeros((3, 3), dtype=int)
        for t, q in zip(y[test], pred):
            conf[t, q] += 1
        out["results"][name] = {
            "balanced_accuracy": float(balanced_accuracy_score(y[test], pred)),
            "auc_flow_vs_ballistic": float(auc),
            "n_features": int(x.shape[1]),
            "confusion_true_by_predicted": conf.tolist(),
        }
    base = out["results"]["pooled"]["balanced_accuracy"]
    gain = out["results"]["pooled+speckle"]["balanced_accuracy"] - base
    extra = out["patch_simulation_seconds_per_sample"] - float(np.mean(list(pixel.values())))
    out["balanced_accuracy_gain_over_pooled"] = gain
    out["gain_per_extra_second_per_1000_samples"] = gain / (1000.0 * extra) if extra > 0 else None
    return out


def markdown(res: dict) -> str:
    lines = [
        f"# Speckle-motion ceiling (static-free B-scan patches, window {res['window']}, "
        f"{res['per_class']} draws per class, SNR {res['snr_db'] or 'none'})",
        "",
        "| features | n | balanced accuracy | ROC AUC flow vs ballistic |",
        "|---|---|---|---|",
    ]
    for k, v in res["results"].items():
        lines.append(f"| {k} | {v['n_features']} | {v['balanced_accuracy']:.3f} | {v['auc_flow_vs_ballistic']:.3f} |")
    pix = res["pixel_simulation_seconds_per_sample"]
    lines += [
        "",
        f"Simulation and features: {res['simulation_seconds']:.0f} s for {3 * res['per_class']} patches "
        "(one thread, under the machine's load at the time).",
        "",
        "| cost per training sample | seconds |",
        "|---|---|",
        f"| patch simulation (13 × 13 pixels, one realisation) | {res['patch_simulation_seconds_per_sample']:.4f} |",
    ]
    lines += [f"| pixel simulation, {k} (torchdoct.simulate, one pixel) | {v:.5f} |" for k, v in pix.items()]
    g = res["gain_per_extra_second_per_1000_samples"]
    lines += [
        "",
        f"Balanced accuracy gained by the speckle features over the pooled signature: "
        f"{res['balanced_accuracy_gain_over_pooled']:+.3f}"
        + (f", i.e. {g:.2e} per extra second of simulation per 1000 samples." if g is not None else "."),
    ]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--per-class", type=int, default=400)
    ap.add_argument("--window", type=int, default=9)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--snr-db", type=float, default=None)
    ap.add_argument("--force", action="store_true")
    a = ap.parse_args(argv)
    out = Path(a.out)
    paths = [out / "speckle-ceiling.json", out / "speckle-ceiling.md"]
    if not a.force and any(p.exists() for p in paths):
        print(f"error: {paths[0]} exists; give --force to replace it", file=sys.stderr)
        return 2
    res = run(a.per_class, a.window, a.seed, a.snr_db)
    out.mkdir(parents=True, exist_ok=True)
    paths[0].write_text(json.dumps(res, indent=2) + "\n")
    paths[1].write_text(markdown(res))
    print(markdown(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
