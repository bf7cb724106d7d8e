"""Random phantoms: samples drawn from a prior wider than the phantom grid's, scored as a user runs them.

The phantom grid (:mod:`classifier.bench.grid`) and the cases (:mod:`classifier.bench.cases`) are phantoms the
project chose. Data a model has never seen comes from elsewhere: other speeds, densities, noise levels, layer
orders, vessels at any angle, with and without static tissue. This benchmark draws such phantoms at random
from a stated prior (:func:`draw`), renders each, maps it as ``torchdoct maps --signature`` does, classifies it
with the model ``doct-classify`` picks (``signature-bscan`` for B-scans, ``signature`` for volumes) at windows
1 and 5, with the rules of :mod:`classifier.ambiguity` (the default) and without them (``--decide-ballistic``:
the model alone), and scores every pixel of each motion against the rendered labels: coverage (the share of
its pixels decided as one motion) and wrong share (the share decided as another motion). The summary counts,
per geometry, window and decision, the draws whose worst wrong share exceeds the project's bounds (5 % and
10 %), and names the worst draws with their motions, so that a failure mode can be read off and rendered
again (``python -m classifier.bench.random_phantoms --draw GEOMETRY:INDEX --out DIR`` renders one draw).

Run (from the repository root)::

    python -m classifier.bench.random_phantoms --out DIR [--bscans N] [--volumes N] [--seed S] [--force]

It writes ``DIR/random-phantoms.json``, ``.md`` and ``.png`` together (the recorded run:
``docs/benchmarks/random-phantoms.*``, rendered in docs/benchmarks/random-phantoms.md).

The prior (:func:`draw`; every number a module constant): the cases' system (840 nm, lateral resolution 4.9 µm,
the 1/e² width of the intensity PSF, axial 3.8 µm, its FWHM) and protocol (32 frames at 0.2048 s), 2 µm
pixels, 96 × 96 pixels, volumes of :data:`VOLUME_NY` planes along y; one scatterer density per draw,
log-uniform over :data:`DENSITY_RANGE` µm⁻³; diffusion coefficients log-uniform over :data:`DIFFUSION_RANGE`
µm²/s, random-ballistic speeds over :data:`BALLISTIC_RANGE` µm/s (isotropic directions), flow speeds over
:data:`FLOW_RANGE` µm/s in a direction uniform on the sphere; a structure of :data:`STRUCTURES`:

* ``layers``: the three motions as slabs stacked in depth, in random order, each at least
  :data:`LAYER_MIN_UM` deep;
* ``vessel``: a slab of one random motion over the whole image, a sphere of the other (radius over
  :data:`SPHERE_RADIUS_RANGE` µm) and a straight vessel of flow along its own axis (radius over
  :data:`VESSEL_RADIUS_RANGE` µm: a diameter at least the widest footprint of the models' coarsest
  configuration, 1.70 × 14 µm axially; far thinner vessels are the cases' ``thin-vessels``), with a uniform
  (plug) or Poiseuille profile, in a direction uniform on the sphere;

a static context of :data:`CONTEXTS` (``none``; ``under``: static tissue of the same density under every
pixel, a second phantom whose field adds, as the grid's ``background``; ``half``: static tissue in place of
the motions for x < 0) and noise of :data:`SNR_CHOICES` (dB below the mean intensity, ``None``: none). The
ranges are wider than the training prior's identifiable band on purpose: a motion too slow or too fast to
identify should be abstained on, and then counts as neither covered nor wrong.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .cases import _fmt

SCHEMA_VERSION = 1
#: The system, protocol, pixel pitch (µm) and image size (pixels per axis) of every draw: the cases'.
SYSTEM = {"name": "840nm", "wavelength_um": 0.84, "lateral_resolution_um": 4.9, "axial_resolution_um": 3.8}
PROTOCOL = {"n_frames": 32, "frame_interval_s": 0.2048}
PITCH_UM = 2.0
N_PX = 96
#: Planes along y of a volume draw (24 µm: the models' coarsest lateral resolution fits the field of view).
VOLUME_NY = 12
#: The prior's ranges, each drawn log-uniformly: density (µm⁻³), diffusion coefficient (µm²/s),
#: random-ballistic and flow speed (µm/s), sphere and vessel radius (µm).
DENSITY_RANGE = (0.01, 0.1)
DIFFUSION_RANGE = (1e-4, 0.3)
BALLISTIC_RANGE = (0.01, 1.0)
FLOW_RANGE = (0.05, 3.0)
SPHERE_RADIUS_RANGE = (20.0, 35.0)
VESSEL_RADIUS_RANGE = (12.0, 30.0)
#: The shallowest slab of a ``layers`` draw (µm).
LAYER_MIN_UM = 32.0
STRUCTURES = ("layers", "vessel")
CONTEXTS = ("none", "under", "half")
SNR_CHOICES: tuple[float | None, ...] = (None, 30.0, 20.0, 15.0, 10.0)
GEOMETRIES = ("bscan", "volume")
POOLS = (1, 5)
#: The draws of the recorded run per geometry, and its first seed.
N_BSCANS = 120
N_VOLUMES = 24
SEED = 2026
#: The project's bounds on a motion's wrong share (docs/abstention.md).
BOUNDS = (0.05, 0.10)
#: Worst draws listed per geometry, window and decision.
N_WORST = 5
MOTIONS = ("diffusion", "ballistic", "flow")
OUTPUTS = (".json", ".md", ".png")


def _log_uniform(rng: np.random.Generator, lo_hi: tuple[float, float]) -> float:
    lo, hi = lo_hi
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _direction(rng: np.random.Generator) -> tuple[float, float]:
    """A direction uniform on the sphere as (polar angle from the beam, azimuth from +x), degrees."""
    return float(math.degrees(math.acos(rng.uniform(-1.0, 1.0)))), float(rng.uniform(0.0, 360.0))


def _motion(rng: np.random.Generator, kind: str) -> dict[str, Any]:
    if kind == "diffusion":
        return {"kind": "diffusion", "diffusion_um2_per_s": _log_uniform(rng, DIFFUSION_RANGE)}
    if kind == "ballistic":
        return {"kind": "ballistic", "speed_um_per_s": _log_uniform(rng, BALLISTIC_RANGE)}
    polar, azimuth = _direction(rng)
    return {
        "kind": "flow",
        "speed_um_per_s": _log_uniform(rng, FLOW_RANGE),
        "polar_angle_deg": polar,
        "azimuth_deg": azimuth,
    }


def draw(geometry: str, index: int, seed: int = SEED) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Draw ``index`` of ``geometry`` (``bscan`` or ``volume``) from the module's prior: the phantom-file dicts
    whose fields add (the phantom, and for the ``under`` context a second of static tissue) and the draw's
    description. The same ``(geometry, index, seed)`` always gives the same draw."""
    if geometry not in GEOMETRIES:
        raise ValueError(f"geometry {geometry!r}: give one of {', '.join(GEOMETRIES)}")
    if isinstance(index, bool) or not isinstance(index, int) or index < 0:
        raise ValueError(f"draw index {index!r}: give an integer of at least 0")
    rng = np.random.default_rng([int(seed), GEOMETRIES.index(geometry), int(index)])
    fov = N_PX * PITCH_UM
    density = _log_uniform(rng, DENSITY_RANGE)
    structure = str(rng.choice(STRUCTURES))
    kinds = [str(k) for k in rng.permutation(MOTIONS)]
    motions = {k: _motion(rng, k) for k in kinds}
    regions: list[dict[str, Any]] = []
    if structure == "layers":
        spare = fov - 3 * LAYER_MIN_UM
        cuts = np.sort(rng.uniform(0.0, spare, 2))
        edges = [-fov / 2, -fov / 2 + LAYER_MIN_UM + cuts[0], -fov / 2 + 2 * LAYER_MIN_UM + cuts[1], fov / 2]
        for i, k in enumerate(kinds):
            regions.append(
                {
                    "name": k,
                    "shape": "slab",
                    "z_min_um": float(edges[i]),
                    "z_max_um": float(edges[i + 1]),
                    "density_per_um3": density,
                    "motion": [motions[k]],
                }
            )
    else:
        around, inside = [k for k in kinds if k != "flow"]
        regions.append(
            {
                "name": around,
                "shape": "slab",
                "z_min_um": -fov / 2,
                "z_max_um": fov / 2,
                "density_per_um3": density,
                "motion": [motions[around]],
            }
        )
        regions.append(
            {
                "name": inside,
                "shape": "sphere",
                "center_um": [float(rng.uniform(-fov / 4, fov / 4)), 0.0, float(rng.uniform(-fov / 4, fov / 4))],
                "radius_um": _log_uniform(rng, SPHERE_RADIUS_RANGE),
                "density_per_um3": density,
                "motion": [motions[inside]],
            }
        )
        flow = motions["flow"]
        p, a = math.radians(flow["polar_angle_deg"]), math.radians(flow["azimuth_deg"])
        axis = [math.sin(p) * math.cos(a), math.sin(p) * math.sin(a), math.cos(p)]
        regions.append(
            {
                "name": "flow",
                "shape": "cylinder",
                "center_um": [float(rng.uniform(-fov / 4, fov / 4)), 0.0, float(rng.uniform(-fov / 4, fov / 4))],
                "axis": axis,
                "radius_um": _log_uniform(rng, VESSEL_RADIUS_RANGE),
                "flow_profile": str(rng.choice(("uniform", "poiseuille"))),
                "density_per_um3": density,
                "motion": [flow],
            }
        )
    context = str(rng.choice(CONTEXTS))
    if context == "half":  # static tissue paints over the motions at x < 0
        regions.append(
            {
                "name": "static-tissue",
                "shape": "cylinder",  # its axis along z, its circle covering x < 0 over the field of view
                "center_um": [-fov, 0.0, 0.0],
                "axis": [0.0, 0.0, 1.0],
                "radius_um": fov,
                "density_per_um3": density,
                "motion": [],
            }
        )
    snr = SNR_CHOICES[int(rng.integers(len(SNR_CHOICES)))]
    grid: dict[str, Any] = {"kind": geometry, "n_x": N_PX, "n_z": N_PX, "pitch_x_um": PITCH_UM, "pitch_z_um": PITCH_UM}
    grid.update({"n_y": VOLUME_NY, "pitch_y_um": PITCH_UM} if geometry == "volume" else {"y_um": 0.0})
    name = f"random-{geometry}-{index}"
    d: dict[str, Any] = {
        "name": name,
        "system": [dict(SYSTEM)],
        "protocol": dict(PROTOCOL),
        "grid": grid,
        "region": regions,
        "simulation": {"seed": int(rng.integers(2**31 - 1))},
    }
    if snr is not None:
        d["noise"] = {"snr_db": float(snr)}
    phantoms = [d]
    if context == "under":
        from .grid import _static_dict

        phantoms.append(_static_dict(d, density))
    description = {
        "geometry": geometry,
        "index": int(index),
        "seed": int(seed),
        "structure": structure,
        "context": context,
        "snr_db": snr,
        "density_per_um3": density,
        "motions": motions,
    }
    return phantoms, description


def run_draw(geometry: str, index: int, seed: int = SEED, *, threads: int | None = None, model=None) -> dict[str, Any]:
    """Render, map, classify and score one draw at every window of :data:`POOLS`, with the rules and with the
    model alone: the draw's description and one row per window and decision (every pixel of each motion)."""
    from ..infer import load_model
    from .grid import _classify_rendered

    phantoms, description = draw(geometry, index, seed)
    if model is None:
        model = load_model("signature" if geometry == "volume" else "signature-bscan", threads=threads)
    scored = _classify_rendered(
        phantoms,
        model,
        phantoms[0]["name"],
        int(phantoms[0]["simulation"]["seed"]),
        pools=POOLS,
        decision=None,
        threads=threads,
        abstain_ambiguous=(True, False),
    )
    rows = [
        {
            "pool": r["pool"],
            "rules": r["abstain_ambiguous"],
            "per_class": {
                m: {k: r["all_pixels"]["per_class"][m][k] for k in ("pixels", "coverage", "wrong_share")}
                for m in MOTIONS
            },
            "coverage": r["all_pixels"]["coverage"],
            "wrong_share_max": r["all_pixels"]["wrong_share_max"],
            "seconds": r["seconds"]["total"],
        }
        for r in scored
    ]
    return {**description, "model": model.spec.name, "rows": rows}


def summarize(draws: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per geometry, window and decision: the draws, the share of them whose worst wrong share exceeds each
    of :data:`BOUNDS`, the median coverage, per motion its coverage and wrong share over the pixels of every
    draw that holds it (a motion painted over by static tissue or another region has none), and the :data:`N_WORST` worst draws (index, worst wrong share, the motion it falls on)."""
    out = []
    keys = sorted(
        {(d["geometry"], r["pool"], r["rules"]) for d in draws for r in d["rows"]},
        key=lambda k: (GEOMETRIES.index(k[0]), k[1], not k[2]),
    )
    for geometry, pool, rules in keys:
        rows = [(d, r) for d in draws if d["geometry"] == geometry for r in d["rows"]]
        rows = [(d, r) for d, r in rows if r["pool"] == pool and r["rules"] == rules]
        worst = np.array([r["wrong_share_max"] or 0.0 for _, r in rows], float)
        per_class = {}
        for m in MOTIONS:
            held = [r["per_class"][m] for _, r in rows if r["per_class"][m]["pixels"]]  # the draws holding m
            n = sum(c["pixels"] for c in held)
            per_class[m] = {
                "pixels": int(n),
                "coverage": sum(c["coverage"] * c["pixels"] for c in held) / n if n else None,
                "wrong_share": sum(c["wrong_share"] * c["pixels"] for c in held) / n if n else None,
            }
        order = np.argsort(-worst, kind="stable")[:N_WORST]
        out.append(
            {
                "geometry": geometry,
                "pool": pool,
                "rules": rules,
                "draws": len(rows),
                "over_bound": {f"{b:g}": float(np.mean(worst > b)) for b in BOUNDS},
                "median_coverage": float(np.median([r["coverage"] or 0.0 for _, r in rows])),
                "per_class": per_class,
                "worst": [
                    {
                        "index": rows[i][0]["index"],
                        "wrong_share_max": float(worst[i]),
                        "motion": max(MOTIONS, key=lambda m: rows[i][1]["per_class"][m]["wrong_share"] or 0.0),
                    }
                    for i in order
                    if worst[i] > 0
                ],
            }
        )
    return out


def check_counts(n_bscans: int, n_volumes: int) -> None:
    """``--bscans`` and ``--volumes``: whole numbers of draws, at least one in all; ``ValueError`` naming the
    option otherwise."""
    for name, n in (("--bscans", n_bscans), ("--volumes", n_volumes)):
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            raise ValueError(f"{name} {n!r}: give a whole number of draws, at least 0")
    if n_bscans + n_volumes == 0:
        raise ValueError("--bscans 0 --volumes 0: nothing to draw; give at least one draw")


def run_random(
    n_bscans: int = N_BSCANS,
    n_volumes: int = N_VOLUMES,
    seed: int = SEED,
    *,
    threads: int | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Run the first ``n_bscans`` B-scan draws and ``n_volumes`` volume draws of ``seed``: the results dict that
    :func:`write_random` writes."""
    from tqdm.auto import tqdm

    from torchdoct.runtime.machine import machine_info

    from ..infer import load_model

    check_counts(n_bscans, n_volumes)
    t0 = time.perf_counter()
    jobs = [("bscan", i) for i in range(n_bscans)] + [("volume", i) for i in range(n_volumes)]
    models = {g: load_model("signature" if g == "volume" else "signature-bscan", threads=threads) for g in GEOMETRIES}
    draws = [
        run_draw(g, i, seed, threads=threads, model=models[g])
        for g, i in tqdm(jobs, desc="random phantoms", unit="draw", disable=not progress)
    ]
    return {
        "schema_version": SCHEMA_VERSION,
        "benchmark": "classifier.bench.random_phantoms",
        "prior": {
            "system": SYSTEM,
            "protocol": PROTOCOL,
            "pitch_um": PITCH_UM,
            "n_px": N_PX,
            "volume_ny": VOLUME_NY,
            "density_per_um3": DENSITY_RANGE,
            "diffusion_um2_per_s": DIFFUSION_RANGE,
            "ballistic_um_per_s": BALLISTIC_RANGE,
            "flow_um_per_s": FLOW_RANGE,
            "sphere_radius_um": SPHERE_RADIUS_RANGE,
            "vessel_radius_um": VESSEL_RADIUS_RANGE,
            "layer_min_um": LAYER_MIN_UM,
            "structures": STRUCTURES,
            "contexts": CONTEXTS,
            "snr_db": SNR_CHOICES,
        },
        "seed": seed,
        "bounds": BOUNDS,
        "summary": summarize(draws),
        "draws": draws,
        "seconds": time.perf_counter() - t0,
        "machine": machine_info(),
    }


def describe(d: dict[str, Any]) -> str:
    """One draw in words: structure, context, noise, density and each motion's parameters."""
    parts = []
    for m in MOTIONS:
        p = d["motions"][m]
        if m == "diffusion":
            parts.append(f"D {p['diffusion_um2_per_s']:.3g} µm²/s")
        elif m == "ballistic":
            parts.append(f"ballistic {p['speed_um_per_s']:.3g} µm/s")
        else:
            parts.append(f"flow {p['speed_um_per_s']:.3g} µm/s at {p['polar_angle_deg']:.0f}°/{p['azimuth_deg']:.0f}°")
    noise = "no noise" if d["snr_db"] is None else f"{d['snr_db']:g} dB"
    return f"{d['structure']}, static {d['context']}, {noise}, {d['density_per_um3']:.3g} µm⁻³; " + ", ".join(parts)


def format_summary(res: dict[str, Any]) -> str:
    """The summary as Markdown: one row per geometry, window and decision; then the worst draws."""
    b = [f"{x:g}" for x in res["bounds"]]
    lines = [
        "| geometry | window | decision | draws | median coverage | "
        + " | ".join(f"draws over {x}" for x in b)
        + " | diffusion: coverage / wrong | ballistic: coverage / wrong | flow: coverage / wrong |",
        "|---" * (8 + len(b)) + "|",
    ]
    for s in res["summary"]:
        pc = s["per_class"]
        per = [f"{_fmt(pc[m]['coverage'])} / {_fmt(pc[m]['wrong_share'])}" for m in MOTIONS]
        decision = "rules (default)" if s["rules"] else "model alone"
        over = [_fmt(s["over_bound"][x]) for x in b]
        lines.append(
            "| "
            + " | ".join([s["geometry"], str(s["pool"]), decision, str(s["draws"]), _fmt(s["median_coverage"])])
            + " | "
            + " | ".join(over + per)
            + " |"
        )
    by_key = {(d["geometry"], d["index"]): d for d in res["draws"]}
    worst = [
        (s, w) for s in res["summary"] if s["rules"] for w in s["worst"] if w["wrong_share_max"] > res["bounds"][0]
    ]
    if worst:
        lines += [
            "",
            "| geometry | window | draw | worst wrong share | on | the draw |",
            "|---" * 6 + "|",
        ]
        for s, w in worst:
            d = by_key[(s["geometry"], w["index"])]
            lines.append(
                f"| {s['geometry']} | {s['pool']} | {w['index']} | {_fmt(w['wrong_share_max'])} | {w['motion']} | "
                f"{describe(d)} |"
            )
    return "\n".join(lines) + "\n"


def format_table(res: dict[str, Any]) -> str:
    return (
        f"# Random phantoms (schema {res['schema_version']})\n\n"
        + format_summary(res)
        + f"\nWritten by `{res.get('command', 'python -m classifier.bench.random_phantoms --out DIR')}`"
        + f" in {res['seconds']:.0f} s.\n"
    )


def plot_random(res: dict[str, Any], path: str | Path) -> None:
    """Per geometry and window, each draw's coverage against its worst wrong share, with the rules (filled
    circles) and by the model alone (open squares); the bounds dashed. Okabe-Ito colours, shapes redundant."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchdoct.figures import OKABE_ITO

    geometries = [g for g in GEOMETRIES if any(d["geometry"] == g for d in res["draws"])]
    fig, axes = plt.subplots(
        len(geometries),
        len(POOLS),
        figsize=(4.2 * len(POOLS), 3.6 * len(geometries)),
        squeeze=False,
        constrained_layout=True,
    )
    styles = {
        True: dict(marker="o", color=OKABE_ITO["blue"], label="rules (default)"),
        False: dict(marker="s", facecolors="none", edgecolors=OKABE_ITO["vermillion"], label="model alone"),
    }
    for i, g in enumerate(geometries):
        for j, pool in enumerate(POOLS):
            ax = axes[i][j]
            for rules in (False, True):
                pts = [
                    (r["coverage"], r["wrong_share_max"])
                    for d in res["draws"]
                    if d["geometry"] == g
                    for r in d["rows"]
                    if r["pool"] == pool and r["rules"] == rules
                ]
                if pts:
                    x, y = zip(*pts)
                    ax.scatter(x, y, s=16, **styles[rules])
            for b, ls in zip(res["bounds"], ("--", ":")):
                ax.axhline(b, color="0.3", ls=ls, lw=0.8, label=f"bound {b:g}")
            ax.set_xlim(-0.02, 1.02)
            ax.set_ylim(-0.02, 1.02)
            ax.set_xlabel("coverage (decided share of the motions' pixels)")
            ax.set_ylabel("worst wrong share (of one motion's pixels)")
            ax.set_title(f"{g}, window {pool}×{pool}", fontsize=9)
            if i == 0 and j == 0:
                ax.legend(fontsize=7, loc="upper left")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_random(
    res: dict[str, Any], out_dir: str | Path, *, force: bool = False, stem: str = "random-phantoms"
) -> list[Path]:
    """Write ``STEM.json``, ``STEM.md`` and ``STEM.png`` into ``out_dir`` together (all or none)."""
    from torchdoct.files import output_set

    from .grid import _json_default

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / f"{stem}{s}" for s in OUTPUTS]
    with output_set(paths, force, "--out") as stage:
        stage(paths[0]).write_text(json.dumps(res, separators=(",", ":"), default=_json_default), encoding="utf-8")
        stage(paths[1]).write_text(format_table(res), encoding="utf-8")
        plot_random(res, stage(paths[2]))
    return paths


def _parse_draw(text: str) -> tuple[str, int]:
    geometry, _, index = text.partition(":")
    if geometry not in GEOMETRIES or not index.isdigit():
        raise ValueError(f"--draw {text!r}: give GEOMETRY:INDEX, GEOMETRY one of {', '.join(GEOMETRIES)}")
    return geometry, int(index)


def main(argv: Sequence[str] | None = None) -> int:
    import argparse
    import sys

    from .grid import check_output_dir

    p = argparse.ArgumentParser(
        prog="python -m classifier.bench.random_phantoms",
        description="Phantoms drawn at random from a prior wider than the phantom grid's, classified with and "
        "without the rules and scored; writes random-phantoms.json, .md and .png into --out.",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output directory (created if missing)")
    p.add_argument("--bscans", type=int, default=N_BSCANS, metavar="N", help=f"B-scan draws (default {N_BSCANS})")
    p.add_argument("--volumes", type=int, default=N_VOLUMES, metavar="N", help=f"volume draws (default {N_VOLUMES})")
    p.add_argument("--seed", type=int, default=SEED, help=f"the prior's seed (default {SEED})")
    p.add_argument(
        "--draw",
        metavar="GEOMETRY:INDEX",
        help="write one draw's phantom files (random-GEOMETRY-INDEX.toml, and ...-static.toml for static tissue "
        "under every pixel) into --out instead, to render (torchdoct render) and classify as a user would",
    )
    p.add_argument("--threads", type=int, default=None, metavar="N")
    p.add_argument("--force", action="store_true", help="overwrite existing results")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    try:
        if args.draw is not None:
            return _write_draw(args)
        check_counts(args.bscans, args.volumes)
        out = check_output_dir(args.out, "random-phantoms", OUTPUTS, args.force)
        res = run_random(args.bscans, args.volumes, args.seed, threads=args.threads, progress=not args.no_progress)
        res["command"] = (
            f"python -m classifier.bench.random_phantoms --bscans {args.bscans} --volumes {args.volumes}"
            f" --seed {args.seed} --out DIR"
        )
        for path in write_random(res, out, force=args.force):
            print(f"wrote {path}")
    except (ValueError, OSError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


def phantom_toml(d: dict[str, Any], header: str = "") -> str:
    """A phantom-file dict (:func:`draw`'s) as the TOML file ``torchdoct render`` reads: its plain keys, its tables,
    its arrays of tables, and each region's motions as ``[[region.motion]]`` (a static region has none).
    ``header``: comment lines."""
    from ..features import _toml_value

    lines = [f"# {line}" for line in header.splitlines()]
    lines += [f"{k} = {_toml_value(v)}" for k, v in d.items() if not isinstance(v, (dict, list))]
    for k, v in d.items():
        if isinstance(v, dict):
            lines += ["", f"[{k}]"] + [f"{kk} = {_toml_value(vv)}" for kk, vv in v.items()]
        elif isinstance(v, list):
            for item in v:
                lines += ["", f"[[{k}]]"]
                lines += [f"{kk} = {_toml_value(vv)}" for kk, vv in item.items() if kk != "motion"]
                for motion in item.get("motion", []):
                    lines += ["", f"[[{k}.motion]]"] + [f"{kk} = {_toml_value(vv)}" for kk, vv in motion.items()]
    return "\n".join(lines) + "\n"


def _write_draw(args) -> int:
    from torchdoct.files import output_set

    geometry, index = _parse_draw(args.draw)
    drawn, description = draw(geometry, index, args.seed)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file; give a directory")
    out.mkdir(parents=True, exist_ok=True)
    stem = f"random-{geometry}-{index}"
    names = [f"{stem}.toml"] + ([f"{stem}-static.toml"] if len(drawn) > 1 else [])
    paths = [out / n for n in names]
    header = f"Draw {geometry}:{index} of python -m classifier.bench.random_phantoms --seed {args.seed}: {describe(description)}"
    with output_set(paths, args.force, "--out") as stage:
        for k, (path, d) in enumerate(zip(paths, drawn)):
            note = (
                header
                if k == 0
                else header + "\nThe static tissue under every pixel: render it on the same grid and add its field."
            )
            stage(path).write_text(phantom_toml(d, note), encoding="utf-8")
    for path in paths:
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
