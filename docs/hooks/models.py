"""Model cards, one per shipped model (``classifier/data/*.onnx``), rendered from the model's training report
(the JSON that ``doct-train`` writes beside the ONNX file), its conformal calibration where it has one
(``python -m classifier.calibrate``), the recorded runs of the phantom grid that used it
(``python -m classifier.bench.grid``, ``docs/benchmarks/grid-*.json``) and, where it exists, the report of the
same model on independent data (``python -m tests.reference.evaluate_models --model NAME --out DIR``)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from results import RESULT_DIRS, num, pm, table

MODEL_DIR = "classifier/data"
#: The recorded runs of the phantom grid (``python -m classifier.bench.grid --stem grid-NAME --out DIR``).
GRID_DIR = "docs/benchmarks"

_USE = {
    "single-acquisition": "volume maps (`TYZX`) at `original`, `axial=14`, `lateral=18` without `--signature`",
    "single-acquisition-bscan": "B-scan maps (`TZX`) at `original`, `axial=14`, `lateral=18` without `--signature`",
    "signature": "volume maps computed with `--signature`",
    "signature-bscan": "B-scan maps computed with `--signature`",
    "signature-bscan-field": "B-scan maps computed with `--signature` and `--bulk-phase` (reads the field's |g1|)",
    "signature-aline": "maps computed with `--signature` at `original` and `axial=14` only: one A-line's time series "
    "(no lateral reduction is possible), or any maps without a lateral-reduced channel",
    "two-wavelength": "the LIV/OCDS maps of both bands of a dual-band (840 / 1310 nm) acquisition",
    "two-wavelength-signature": "the signature maps of both bands of a dual-band acquisition",
}


def shipped(root: Path) -> list[str]:
    return sorted(p.stem for p in (root / MODEL_DIR).glob("*.onnx"))


def _independent(root: Path, name: str) -> tuple[dict[str, Any], str] | None:
    for d in RESULT_DIRS:
        p = root / d / f"{name}-independent.json"
        if p.is_file():
            return json.loads(p.read_text(encoding="utf-8")), p.relative_to(root).as_posix()
    return None


def _independent_sets(e: dict[str, Any]) -> list[str]:
    """The prediction sets of ``doct-classify`` on the independent data (``conformal`` of each pool), when the
    report holds them: per pool and motion the share decided, decided as another motion and whose set misses it,
    alone and after rule 1."""
    rows = [
        [
            pool,
            name,
            num(q["decided"]),
            num(q["wrong_share"]),
            num(q["set_miss_share"]),
            num(c["rule_1"][name]["decided"]),
            num(c["rule_1"][name]["wrong_share"]),
        ]
        for pool, v in e["results"].items()
        if (c := v.get("conformal"))
        for name, q in c["per_class"].items()
    ]
    if not rows:
        return []
    alpha = next(v["conformal"]["alpha"] for v in e["results"].values() if v.get("conformal"))
    return [
        f"`doct-classify`'s prediction sets at α = {alpha:g} on the same pixels (identifiable ones), alone "
        "(`--decide-ballistic`) and after rule 1 of the [abstention rules](../abstention.md) (a `ballistic` set "
        "becomes `ballistic-or-flow`, as for one pixel's time series). These data are not drawn like the "
        "calibration set, so the guarantee does not cover them: the set-miss share shows what it is worth here.",
        "",
        table(
            [
                "pool",
                "motion",
                "decided",
                "decided as another",
                "set misses it",
                "rule 1: decided",
                "rule 1: as another",
            ],
            rows,
        ),
        "",
    ]


def _spec_table(spec: dict[str, Any]) -> str:
    rows = [
        [
            c["name"],
            num(c["wavelength_um"] * 1000, 4),
            num(c["lateral_resolution_um"]),
            num(c.get("lateral_resolution_y_um", c["lateral_resolution_um"])),
            num(c["axial_resolution_um"]),
        ]
        for c in spec["configuration"]
    ]
    return table(
        ["configuration", "wavelength (nm)", "lateral 1/e² width x (µm)", "lateral width y (µm)", "axial FWHM (µm)"],
        rows,
    )


def _prior_table(prior: dict[str, Any]) -> str:
    unit = {
        "diffusion_um2_per_s": "D (µm²/s)",
        "speed_um_per_s": "random-ballistic speed (µm/s)",
        "flow_speed_um_per_s": "flow speed (µm/s)",
        "flow_polar_angle_deg": "flow polar angle (°)",
        "density_per_um3": "density (µm⁻³)",
        "snr_db": "SNR (dB)",
        "static_fraction": "static fraction",
    }
    rows = []
    for k, v in prior.items():
        label = unit.get(k, k.replace("_", " "))
        val = (
            f"{num(v[0])} – {num(v[1])}"
            if isinstance(v, list) and len(v) == 2
            else num(v)
            if isinstance(v, (int, float))
            else str(v)
        )
        rows.append([label, val])
    return table(["prior", "range or value"], rows)


def _pools(test: dict[str, Any], se: dict[str, Any]) -> str:
    rows = []
    for pool, m in test.items():
        s = se.get(pool, {})
        rows.append(
            [
                pool,
                pm(m.get("coverage_identifiable"), s.get("coverage_identifiable")),
                pm(m.get("balanced_accuracy_identifiable"), s.get("balanced_accuracy_identifiable")),
                pm(m.get("accuracy_identifiable"), s.get("accuracy_identifiable")),
                pm(m.get("ece"), s.get("ece")),
                num(m.get("indeterminate_fraction")),
            ]
        )
    return table(
        [
            "pool (pixels)",
            "coverage (identifiable)",
            "balanced accuracy (decided)",
            "accuracy (decided)",
            "ECE",
            "indeterminate share (all)",
        ],
        rows,
    )


def _baselines(test: dict[str, Any], timing: dict[str, Any]) -> str:
    rows = []
    for name, pools in test.items():
        m = pools.get("1") if isinstance(pools, dict) else None
        if not m:
            continue
        t = timing.get(name, {})
        rows.append(
            [
                name,
                num(m.get("coverage_identifiable")),
                num(m.get("balanced_accuracy_identifiable")),
                num(m.get("ece")),
                num(t.get("train_s")),
                num(t.get("inference_us_per_sample")),
            ]
        )
    for name, t in timing.items():
        if name not in test:
            rows.append([name, "", "", "", num(t.get("train_s")), num(t.get("inference_us_per_sample"))])
    return table(
        ["model (pool 1)", "coverage", "balanced accuracy", "ECE", "training (s)", "inference (µs/sample)"], rows
    )


def _coverage_curve(curve: list[dict[str, Any]]) -> str:
    rows = [
        [
            num(r["min_probability"]),
            num(r["coverage_identifiable"]),
            num(r["balanced_accuracy_identifiable"]),
            num(r.get("non_identifiable_decided")),
        ]
        for r in curve
    ]
    return table(
        ["`--min-probability`", "coverage (identifiable)", "balanced accuracy", "non-identifiable pixels decided"], rows
    )


def _flow_bands(fb: dict[str, Any]) -> str:
    rows = [[band, num(v["samples"]), num(v["coverage"]), num(v["recall"])] for band, v in fb["polar_bands"].items()]
    return table(["flow polar band (°)", "pixels", "coverage", "recall"], rows)


def _magnitude(mag: dict[str, Any]) -> str:
    rows = [
        [pool, num(m["median_abs_log10_error"]), num(m["coverage_68"]), num(m["coverage_95"])]
        for pool, m in mag.items()
    ]
    return table(["pool", "median \\|log10 error\\|", "in 68 % interval", "in 95 % interval"], rows)


def _calibration(root: Path, name: str) -> list[str]:
    p = root / MODEL_DIR / f"{name}.calibration.json"
    if not p.is_file():
        return ["This model has no conformal calibration beside it, so `doct-classify` applies the rule above."]
    c = json.loads(p.read_text(encoding="utf-8"))
    return [
        f"**Default decision: conformal prediction sets.** The model is calibrated beside its ONNX file "
        f"(`{p.relative_to(root).as_posix()}`, written by `{c['command']}`): `doct-classify` answers, per pixel, "
        f"the set of classes the {c.get('mode', 'conformal')} calibration keeps at `--alpha` (default "
        f"{num(c['default_alpha'])}). {c['guarantee']} A set of two motions is answered as such (for example "
        "`ballistic-or-flow`), and where the physics cannot tell the motions apart the answer is a set too "
        "([Abstention](../abstention.md)); `--decision rule` applies the rule above instead, "
        "`--decide-ballistic` keeps the model's own ballistic decisions.",
        "",
        f"On its calibration samples at α = {num(c['default_alpha'])}, per pool size (the model alone, "
        "without the rules of the abstention page):",
        "",
        *_calibration_table(c),
    ]


def _calibration_table(c: dict[str, Any]) -> list[str]:
    """Per calibrated pool size, at the default α: samples, mean set size, share of samples whose set holds
    their class, share decided (a set of one class other than indeterminate)."""
    key = f"{c['default_alpha']:g}"
    rows = [
        [
            str(p["pool_pixels"]),
            str(p["samples"]),
            num(p["set_sizes"][key]["mean_set_size"]),
            num(p["set_sizes"][key]["in_sample_coverage"], 3),
            num(p["set_sizes"][key]["decided"], 3),
        ]
        for p in c["pools"]
        if key in p.get("set_sizes", {})
    ]
    return [table(["pool pixels", "samples", "mean set size", "set holds the class", "decided"], rows)]


def _grid_runs(root: Path) -> list[tuple[Path, dict[str, Any]]]:
    paths = sorted((root / GRID_DIR).glob("grid-*.json"), key=lambda p: (p.stem != "grid-default", p.stem))
    runs = [(p, json.loads(p.read_text(encoding="utf-8"))) for p in paths]
    return [(p, d) for p, d in runs if d.get("benchmark") == "phantom-grid"]


def _grid(root: Path, name: str) -> list[str]:
    """The recorded phantom-grid runs of this model: per run and window, its cells summarised as the grid
    summarises a run (``classifier.bench.grid.summarize``)."""
    from classifier.bench.grid import summarize

    rows, used = [], set()
    for p, d in _grid_runs(root):
        used.update(d.get("models", {}).values())
        cells = [c for c in d["cells"] if c.get("model") == name]
        if not cells:
            continue
        decision = d.get("decision", "")
        if d.get("abstain_ambiguous"):
            decision += " + the ambiguity rules"
        if d.get("abstain_ambiguous") is False or "--decide-ballistic" in d.get("command", ""):
            decision += ", `--decide-ballistic`"
        geometry = ", ".join(sorted({c["geometry"] for c in cells}))
        for pool, s in summarize(cells).items():
            rows.append(
                [
                    f"[`{p.stem}`](../benchmarks/{p.stem}.md)",
                    decision,
                    geometry,
                    pool,
                    s["cells"],
                    num(s["mean_coverage"]),
                    num(s["min_coverage"]),
                    num(s["mean_balanced_accuracy"]),
                    num(s["worst_wrong_share"]),
                    s["cells_over_10pct_wrong"],
                ]
            )
    if not rows:
        models = ", ".join(f"`{m}`" for m in sorted(used)) or "no model"
        return [
            f"No recorded run of the [phantom grid](../benchmarks/grid.md) uses this model (the recorded runs "
            f"use {models}: the models `doct-classify` picks for signature maps).",
            "",
        ]
    return [
        "Phantoms built from the model's system, rendered, mapped and classified end to end, scored against "
        "the rendered labels ([the phantom grid](../benchmarks/grid.md); each run's file gives every cell and "
        "its `command`):",
        "",
        table(
            [
                "run",
                "decision",
                "geometry",
                "window (`--pool`)",
                "cells",
                "mean coverage",
                "lowest coverage",
                "mean balanced accuracy",
                "worst wrong share",
                "cells over 10 % wrong",
            ],
            rows,
        ),
        "",
    ]


def card(root: Path, name: str) -> str:
    rp = root / MODEL_DIR / f"{name}.json"
    r = json.loads(rp.read_text(encoding="utf-8"))
    spec, cfg, rule = r["spec"], r["config"], r["rule"]
    report = rp.relative_to(root).as_posix()
    retrain = "doct-train --out DIR" if name == "single-acquisition" else f"doct-train --spec {name} --out DIR"
    out = [
        f"# Model card: `{name}`",
        "",
        f"{spec['description']}.",
        "",
        f"**Used for:** {_USE.get(name, 'maps whose channels match the configurations below')}; `doct-classify` "
        "picks it by matching every feature to a maps channel by its optics.",
        "",
        f"**Files:** `{MODEL_DIR}/{name}.onnx` (the model), `{report}` (this card's source: the training report), "
        f"`{MODEL_DIR}/{name}.md` (the report as text). **Retrain:** `{retrain}` (seed {r['seed']}; classifier "
        f"{r['classifier_version']}, torchdoct {r['torchdoct_version']}, torch {r['torch_version']}).",
        "",
        "## Specification",
        "",
        f"{len(r['feature_names'])} features: {', '.join(f'`{m}`' for m in spec['metrics'])} at each configuration; "
        f"{spec['protocol']['n_frames']} frames {num(spec['protocol']['frame_interval_s'], 4)} s apart, refractive index "
        f"{num(spec['refractive_index'])}; classes {', '.join(r['classes'])}.",
        "",
        _spec_table(spec),
        "",
        "## Training data",
        "",
        f"Simulated by `torchdoct` ({cfg['truncation']} PSF truncation at {num(cfg['truncation_tolerance'])}): "
        f"{cfg['draws_train']} / {cfg['draws_validation']} / {cfg['draws_test']} draws (train / validation / test) "
        f"× {cfg['replicates']} replicates × {cfg['trials_per_draw']} trials; network {' × '.join(map(str, cfg['hidden']))} "
        f"hidden units. Each draw samples the prior below:",
        "",
        _prior_table(r["prior"]),
        "",
        "## When it abstains",
        "",
        f"The rule: {rule['definition']} The default `--min-probability` is "
        f"{num(rule['min_probability'])} and the identifiability threshold ε = {num(rule.get('epsilon'))}.",
        "",
        "Trading coverage for accuracy on the own test split (pool 1):",
        "",
        _coverage_curve(r["coverage_curve"]["1"]),
        "",
        *_calibration(root, name),
        "",
        "## Results on its own test split",
        "",
        "Coverage and accuracies over the identifiable test pixels (± bootstrap SE over draws):",
        "",
        _pools(r["test"]["network"], r.get("standard_errors", {})),
        "",
    ]
    out += ["Against baselines trained on the same data:", "", _baselines(r["test"], r.get("timing", {})), ""]
    if r.get("flow_bands", {}).get("1"):
        out += ["Flow recall by polar angle (pool 1):", "", _flow_bands(r["flow_bands"]["1"]), ""]
    if r.get("magnitude"):
        out += [
            "Motion magnitude (log10 D or v) on the pixels decided with the right type:",
            "",
            _magnitude(r["magnitude"]),
            "",
        ]
    if r.get("shifted_prior"):
        sp = r["shifted_prior"]
        out += [
            "On a shifted prior (a test set drawn from a prior the model was not trained on):",
            "",
            _pools(sp["test"], {}),
            "",
        ]
    out += ["## Results on the phantom grid", "", *_grid(root, name)]
    ind = _independent(root, name)
    out += ["## Results on independent data", ""]
    limits: list[str] = []
    if ind:
        e, ep = ind
        out += [
            f"An independent brute-force simulator (sharing no code with the kernel) on a prior the model was not "
            f"trained on: {e['prior']['text']}. {e['draws']} draws; ± bootstrap SE over draws.",
            "",
            table(
                ["pool", "coverage", "balanced accuracy", "ECE"],
                [
                    [
                        pool,
                        pm(v["metrics"]["coverage_identifiable"], v["standard_errors"].get("coverage_identifiable")),
                        pm(
                            v["metrics"]["balanced_accuracy_identifiable"],
                            v["standard_errors"].get("balanced_accuracy_identifiable"),
                        ),
                        pm(v["metrics"]["ece"], v["standard_errors"].get("ece")),
                    ]
                    for pool, v in e["results"].items()
                ],
            ),
            "",
            *_independent_sets(e),
            "Goals:",
            "",
            table(
                ["target", "value", "goal", "met"],
                [[t["what"], num(t["value"]), t["goal"], "yes" if t["met"] else "**no**"] for t in e["targets"]],
            ),
            "",
            f"*Written by `python -m tests.reference.evaluate_models --model {name} --out DIR` into `{ep}`.*",
            "",
        ]
        limits += [
            f"{t['what']}: {num(t['value'])} against the goal {t['goal']} (independent data)."
            for t in e["targets"]
            if not t["met"]
        ]
    else:
        out += [
            f"No independent evaluation is stored for this model; `python -m tests.reference.evaluate_models "
            f"--model {name} --out DIR` writes one.",
            "",
        ]
    out += [
        "## Limits",
        "",
        "- Trained for one protocol and one set of optics (the configurations above); maps of another system are "
        "refused, naming `doct-train --like MAPS` ([Your own system](../tutorials/own-system.md)).",
        "- Outside the prior's ranges the model was not trained; the magnitude head's intervals hold only inside them.",
        *[f"- {x}" for x in limits],
        "",
        f"*Rendered at build time from `{report}`{', `' + ind[1] + '`' if ind else ''} and the phantom grid's "
        f"recorded runs (`{GRID_DIR}/grid-*.json`).*",
        "",
    ]
    return "\n".join(out)


def index(root: Path) -> str:
    rows = []
    for name in shipped(root):
        r = json.loads((root / MODEL_DIR / f"{name}.json").read_text(encoding="utf-8"))
        m = r["test"]["network"].get("1", {})
        rows.append(
            [
                f"[`{name}`]({name}.md)",
                _USE.get(name, ""),
                len(r["feature_names"]),
                num(m.get("coverage_identifiable")),
                num(m.get("balanced_accuracy_identifiable")),
            ]
        )
    return "\n".join(
        [
            "# Shipped models",
            "",
            "One card per model in `classifier/data/`, rendered at build time from its training report, its "
            "calibration, the phantom grid's recorded runs and its report on independent data: the training "
            "data, the prior, when it abstains, its results and its limits. "
            "`doct-classify MAPS --out DIR` picks the model whose features match the maps' channels.",
            "",
            table(["model", "for", "features", "coverage (own test, pool 1)", "balanced accuracy"], rows),
            "",
        ]
    )
