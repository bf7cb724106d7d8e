"""Console scripts ``doct-train`` and ``doct-classify``: parse, call one library function, print.

``doct-train`` = :func:`classifier.train.train_to_files` (:func:`classifier.train.train`,
:func:`classifier.export.export_onnx`, :func:`classifier.report.write_report`); ``doct-classify`` = :func:`classifier.infer.classify_maps` +
:func:`classifier.infer.write_classification`. ``doct-classify`` never imports torch.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from torchdoct.runtime import interrupt as _interrupt

__all__ = ["build_train_parser", "build_classify_parser", "train_main", "classify_main"]

#: ``doct-train --quick``: small splits for a first run (a rough model: to see the outputs).
QUICK = {
    "draws_train": 90,
    "draws_validation": 24,
    "draws_test": 36,
    "trials_per_draw": 64,
    "replicates": 4,
    "max_epochs": 100,
}
#: Parameter draws of the calibration split ``doct-train`` simulates after training (the default of
#: ``python -m classifier.calibrate``, which calibrated the shipped models), and with ``--quick``.
CALIBRATION_DRAWS = 240
QUICK_CALIBRATION_DRAWS = 60
#: The files the calibration adds beside the model (:func:`classifier.calibrate.write_calibration_files`).
_CALIBRATION_SUFFIXES = (".calibration.json", ".reliability.png")

_ERRORS = (ValueError, TypeError, FileNotFoundError)  # bad input: exit code 2 (torchdoct.cli.EXIT_CODES)


def _run(fn, args) -> int:
    """Exit codes of every command: 2 bad input, 1 the system refused a read or write (one line)."""
    try:
        return fn(args)
    except _ERRORS as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # the reader of the output went away: the entry point ends quietly
        raise
    except OSError as err:  # permissions, disk full
        print(f"error: {err}", file=sys.stderr)
        return 1


def build_train_parser() -> argparse.ArgumentParser:
    from .train import TrainConfig

    d = TrainConfig()
    p = argparse.ArgumentParser(
        prog="doct-train",
        description="Simulate labelled DOCT features, train the motion-type classifier, export ONNX and a report. "
        "Without options it reproduces the shipped single-acquisition model.",
    )
    p.add_argument("--out", required=True, help="output directory: SPEC.onnx, SPEC.json/.md/.png (report)")
    p.add_argument(
        "--spec",
        default=None,
        help=f"feature spec: a shipped name ('single-acquisition', 'signature', "
        f"'signature-bscan', ...; default {d.spec!r}) or a TOML file",
    )
    p.add_argument(
        "--like",
        nargs="+",
        metavar="MAPS",
        default=None,
        help="train for the system of these maps (from `torchdoct maps`): the spec from their metadata "
        "(resolutions, wavelength, frame times, refractive index, reduction axes, signature "
        "features) and a prior scaled to that system; writes SPEC.spec.toml and SPEC.prior.toml "
        "beside the model",
    )
    p.add_argument(
        "--prior",
        default=None,
        metavar="TOML",
        help="training prior (a SPEC.prior.toml written by --like, or your own: the fields of "
        "classifier.prior.Prior); default: the shipped prior, or with --like the scaled one",
    )
    p.add_argument(
        "--dry-run",
        action="store_true",
        help="print the spec, the prior, the recipe, the expected time and the cache key, then stop",
    )
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument(
        "--quick",
        action="store_true",
        help=f"small splits for a first run, a rough model in a fraction of the full time ({_quick_text()}); "
        "a smoke test of the whole recipe, far less accurate than the shipped model; "
        "size options given as well win",
    )
    p.add_argument(
        "--draws-train", type=int, default=None, help=f"parameter draws in the training split (default {d.draws_train})"
    )
    p.add_argument("--draws-validation", type=int, default=None, help=f"(default {d.draws_validation})")
    p.add_argument("--draws-test", type=int, default=None, help=f"(default {d.draws_test})")
    p.add_argument("--trials-per-draw", type=int, default=None, help=f"(default {d.trials_per_draw})")
    p.add_argument(
        "--replicates",
        type=int,
        default=None,
        help=f"(static fraction, SNR) settings per simulated draw (default {d.replicates})",
    )
    p.add_argument("--max-epochs", type=int, default=None, help=f"(default {d.max_epochs})")
    p.add_argument(
        "--min-probability",
        type=float,
        default=d.min_probability,
        help="indeterminate below this top-class probability",
    )
    p.add_argument("--no-baselines", action="store_true", help="skip the scikit-learn baselines")
    p.add_argument(
        "--calibration-draws",
        type=int,
        default=None,
        metavar="N",
        help=f"parameter draws of the split that calibrates the model's conformal prediction sets "
        f"after training (default {CALIBRATION_DRAWS}, with --quick {QUICK_CALIBRATION_DRAWS}; 0: none, and "
        "doct-classify decides by the model's argmax rule): SPEC.calibration.json and SPEC.reliability.png "
        "beside the model, as python -m classifier.calibrate writes them (docs/abstention.md)",
    )
    p.add_argument("--cache", default=None, help="dataset cache directory (default ~/.cache/torchdoct/classifier)")
    p.add_argument("--no-cache", action="store_true", help="neither read nor write the dataset cache")
    p.add_argument(
        "--threads",
        type=int,
        default=None,
        metavar="N",
        help="cores to use for the simulation (default: the usable cores); one torch thread each",
    )
    p.add_argument("--force", action="store_true", help="overwrite existing outputs")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (as TQDM_DISABLE=1)")
    return p


def _quick_text() -> str:
    q = QUICK
    return (
        f"draws {q['draws_train']}/{q['draws_validation']}/{q['draws_test']}, {q['replicates']} replicates, "
        f"at most {q['max_epochs']} epochs"
    )


@_interrupt.entry_point  # Ctrl-C/SIGTERM: one line, exit 130/143 (torchdoct.runtime.interrupt)
def train_main(argv: Sequence[str] | None = None) -> int:
    """``doct-train``: returns the exit code (0 done, 2 bad input, 1 other failure)."""
    args = build_train_parser().parse_args(argv)
    _interrupt.silence_progress(args)
    return _run(_train, args)


def _train(args: argparse.Namespace) -> int:
    from torchdoct.files import check_out, output_set, safe_name

    from .features import load_spec
    from .train import TrainConfig

    if args.like and args.spec:
        raise ValueError("--like and --spec exclude each other: --like derives the spec from the maps")
    notes: list[str] = []
    if args.like:
        from torchdoct.measured.mapsfile import read_maps

        from .matching import spec_from_maps

        spec, notes = spec_from_maps([read_maps(p) for p in args.like])
        spec_key: object = spec
    else:
        spec_key = str(args.spec or TrainConfig().spec)
        spec = load_spec(spec_key)
    safe_name(
        spec.name,
        f"feature spec name (the outputs are SPEC.onnx, ...; in {args.spec or 'the maps'})",
        "give the spec a plain name",
    )
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file; give a directory")
    if args.cache is not None and not args.no_cache and Path(args.cache).exists() and not Path(args.cache).is_dir():
        raise ValueError(f"--cache {args.cache} is a file; give a directory (or --no-cache)")
    calibration_draws = _calibration_draws(args)
    # the calibration files belong to the set even when not written: an earlier model's are removed with it
    suffixes = (".onnx", ".json", ".md", ".png") + ((".spec.toml", ".prior.toml") if args.like else ())
    suffixes += _CALIBRATION_SUFFIXES
    paths = {s: out / f"{spec.name}{s}" for s in suffixes}
    written = [p for s, p in paths.items() if calibration_draws or s not in _CALIBRATION_SUFFIXES]
    if out.is_dir() and not args.dry_run:
        for p in paths.values():
            check_out(p, args.force, p.suffix, f"--out {out}")  # the last suffix: .toml of .spec.toml
    from torchdoct.runtime.threads import set_default_threads

    set_default_threads(args.threads)  # simulation threads (torchdoct.runtime.threads); ValueError names the fix
    from torchdoct.runtime.threads import limit_process_threads

    limit_process_threads()  # one torch/BLAS thread per worker: no stalls beside other busy processes
    base = QUICK if args.quick else {k: getattr(TrainConfig.for_spec(spec_key), k) for k in QUICK}
    sizes = {k: base[k] if getattr(args, k) is None else getattr(args, k) for k in QUICK}  # explicit sizes win
    try:
        cfg = TrainConfig.for_spec(
            spec_key, seed=args.seed, min_probability=args.min_probability, baselines=not args.no_baselines, **sizes
        )
    except (TypeError, ValueError) as err:
        raise type(err)(_as_typed(str(err))) from None
    prior, ranges = _prior(args, spec, cfg)
    if args.like or args.prior or args.dry_run:
        _print_plan(args, spec, prior, ranges, cfg, notes, paths, calibration_draws)
    if args.dry_run:
        return 0
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    order = [  # the model last
        s for s in (".json", ".md", ".png", ".spec.toml", ".prior.toml", *_CALIBRATION_SUFFIXES, ".onnx") if s in paths
    ]
    try:
        with output_set([paths[s] for s in order], args.force, f"--out {out}") as stage:  # all files or none
            line = _train_into(args, cfg, {s: stage(p) for s, p in paths.items()}, spec=spec, prior=prior)
            if args.like:
                _write_like_files(
                    spec, prior, ranges, args, {s: stage(paths[s]) for s in (".spec.toml", ".prior.toml")}
                )
            if calibration_draws:
                line += "\n" + _calibrate_into(args, calibration_draws, {s: stage(p) for s, p in paths.items()})
    finally:
        if created and out.exists() and not any(out.iterdir()):
            out.rmdir()
    print(f"wrote {', '.join(str(p) for p in written)}")
    print(line)
    if args.like:
        print(f"classify: doct-classify {' '.join(args.like)} --model {paths['.onnx']} --out DIR")
    return 0


def _prior(args: argparse.Namespace, spec, cfg):
    """The training prior and, with ``--like``, the identifiable ranges it was scaled from."""
    from .own_system import prior_for_spec
    from .train import default_prior

    if args.prior:
        return _read_prior(args.prior), None
    if args.like:
        return prior_for_spec(spec, default_prior(cfg))
    return None, None


def _read_prior(path: str):
    """A prior TOML file (the fields of :class:`classifier.prior.Prior`), errors naming the file."""
    import tomllib

    from torchdoct.files import check_nesting, read_capped, toml_loads

    from .prior import Prior

    p = Path(path)
    try:
        raw = read_capped(p, "--prior")
    except FileNotFoundError:
        raise FileNotFoundError(f"--prior {path}: no such file") from None
    try:
        check_nesting(raw, p.name, toml=True)
        data = toml_loads(raw.decode("utf-8"))
        return Prior.from_dict(data)
    except tomllib.TOMLDecodeError as err:
        raise ValueError(f"--prior {p.name}: not valid TOML: {err}") from None
    except UnicodeDecodeError:
        raise ValueError(f"--prior {p.name}: not a TOML text file") from None
    except (TypeError, ValueError) as err:
        raise ValueError(f"--prior {p.name}: {err}") from None


_RANGE_UNITS = {"diffusion": "D, µm²/s", "ballistic": "v, µm/s", "flow": "v, µm/s"}


def _print_plan(args, spec, prior, ranges, cfg, notes, paths, calibration_draws: int = 0) -> None:
    """What will be trained, printed before the work: spec, prior, recipe, expected time, cache key."""
    from .calibrate import CALIBRATION_TRIALS
    from .dataset import dataset_key, default_cache_dir
    from .features import toml_text
    from .own_system import estimate_seconds
    from .prior import CLASSES
    from .train import default_prior

    prior = prior or default_prior(cfg)
    print(
        f"spec {spec.name}: {spec.n_features} features ({len(spec.metrics)} × {len(spec.configurations)} "
        f"configurations), {spec.n_frames} frames {spec.frame_interval_s:g} s apart, n = {spec.refractive_index:g}"
    )
    print(toml_text(spec.to_dict()).rstrip().replace("\n", "\n    ").join(("    ", "")))
    for note in notes:
        print(f"note: {note}")
    print(
        "prior (log-uniform magnitudes"
        + (", the identifiable range widened by half a decade each side):" if ranges else "):")
    )
    for label, name in enumerate(CLASSES):
        lo, hi = prior.magnitude_range(label)
        ident = f" (identifiable {ranges[name][0]:.3g}-{ranges[name][1]:.3g}" if ranges else ""
        if ranges and f"{name}_simulated_max" in ranges:
            ident += (
                f"; simulated up to {ranges[name + '_simulated_max'][0]:.3g}: a faster one sweeps more than "
                "1e4 scatterers per simulated pixel, classify it with care"
            )
        ident += ")" if ranges else ""
        print(f"    {name:>9} ({_RANGE_UNITS[name]}): {lo:.3g}-{hi:.3g}{ident}")
    print(
        f"    density {prior.density_per_um3[0]:.3g}-{prior.density_per_um3[1]:.3g} µm⁻³, SNR "
        f"{prior.snr_db[0]:g}-{prior.snr_db[1]:g} dB (p = {prior.noise_probability:g}), static fraction "
        f"{prior.static_fraction[0]:g}-{prior.static_fraction[1]:g} (p = {prior.static_probability:g}), flow "
        f"polar angle {prior.flow_polar_law}"
        + (
            f", residual bulk phase step {prior.bulk_residual_step_rad[1]:g} rad"
            if prior.bulk_residual_step_rad[1] > 0
            else ""
        )
        + (
            f", a static edge {prior.static_edge_distance[0]:g}-{prior.static_edge_distance[1]:g} PSF SDs away "
            f"(p = {prior.static_edge_probability:g}; each configuration its own static share)"
            if prior.static_edge_probability > 0
            else ""
        )
    )
    print(
        f"recipe: draws {cfg.draws_train}/{cfg.draws_validation}/{cfg.draws_test} (train/validation/test) × "
        f"{cfg.replicates} replicates × {cfg.trials_per_draw} trials, at most {cfg.max_epochs} epochs, "
        f"seed {cfg.seed}, PSF {cfg.truncation} at {cfg.truncation_tolerance:g}"
    )
    if calibration_draws:
        print(
            f"calibration: {calibration_draws} draws from the prior at the calibration seed, after training "
            "(SPEC.calibration.json: doct-classify's conformal sets; --calibration-draws 0 skips it)"
        )
    est = estimate_seconds(
        spec,
        prior,
        cfg,
        pilot_draws=3 if args.quick else 6,
        threads=args.threads,
        calibration_draws=calibration_draws,
        calibration_trials=CALIBRATION_TRIALS,
    )
    print(
        f"expected time: about {est['total_s'] / 60:.1f} min (simulation {est['simulation_s'] / 60:.1f} min: "
        f"{est['draws']} draws at {est['pilot_s_per_draw']:.2f} s each on the cores, from a pilot of the first "
        f"draws; the network's fit at most {est['fit_s'] / 60:.1f} min"
        + (
            f"; the scikit-learn baselines {est['baselines_s'] / 60:.1f} min, --no-baselines skips them"
            if est["baselines_s"]
            else ""
        )
        + (f"; the calibration {est['calibration_s'] / 60:.1f} min" if est["calibration_s"] else "")
        + ")"
    )
    if not args.no_cache:
        key, _ = dataset_key(
            spec,
            prior,
            cfg.seed,
            "train",
            cfg.draws_train,
            cfg.trials_per_draw,
            cfg.replicates,
            cfg.truncation_tolerance,
            truncation=cfg.truncation,
        )
        print(f"cache: {args.cache or default_cache_dir()} (training split key {key[:16]}; a rerun reuses it)")
    if args.like:
        extra = "".join(f" --{k.replace('_', '-')} {getattr(args, k)}" for k in QUICK if getattr(args, k) is not None)
        print(
            f"the same model again: doct-train --spec {paths['.spec.toml']} --prior {paths['.prior.toml']} --out "
            f"{args.out} --seed {cfg.seed}" + (" --quick" if args.quick else "") + extra
        )


def _calibration_draws(args: argparse.Namespace) -> int:
    """Draws of the calibration split of this run: ``--calibration-draws``, else the default (every model
    is calibrated, as the shipped ones are, so that ``doct-classify`` decides by its conformal sets)."""
    if args.calibration_draws is not None:
        if args.calibration_draws < 0:
            raise ValueError(f"--calibration-draws {args.calibration_draws}: give 0 (no calibration) or more draws")
        return int(args.calibration_draws)
    return QUICK_CALIBRATION_DRAWS if args.quick else CALIBRATION_DRAWS


def _calibrate_into(args: argparse.Namespace, draws: int, paths: dict[str, Path]) -> str:
    """Calibrate the model just written at ``paths[".onnx"]`` (its report beside it) on a split of
    ``draws`` draws from its training prior at the calibration seed (:func:`classifier.calibrate.calibrate`)
    and write the record and the reliability diagram; returns the summary line."""
    from .calibrate import calibrate, write_calibration_files
    from .conformal import DEFAULT_ALPHA

    cal = calibrate(
        str(paths[".onnx"]),
        draws=draws,
        cache_dir=args.cache,
        use_cache=not args.no_cache,
        progress=not args.no_progress,
    )
    write_calibration_files(cal, paths[".calibration.json"], paths[".reliability.png"])
    pool = min(cal["pools"], key=lambda p: p["pool_pixels"])
    sizes = pool["set_sizes"][f"{DEFAULT_ALPHA:g}"]
    return (
        f"calibrated: {pool['samples']} samples per pool size ({draws} draws); at alpha {DEFAULT_ALPHA:g} and one "
        f"pixel the sets hold their class in {sizes['in_sample_coverage']:.3f} of the samples and decide "
        f"{sizes['decided']:.3f} of them; doct-classify uses the sets (docs/abstention.md)"
    )


def _write_like_files(spec, prior, ranges, args, paths) -> None:
    """SPEC.spec.toml and SPEC.prior.toml of a ``--like`` run (``doct-train --spec ... --prior ...`` retrains it)."""
    from .features import toml_text

    sources = ", ".join(Path(p).name for p in args.like)
    paths[".spec.toml"].write_text(
        toml_text(spec.to_dict(), f"Feature spec derived by doct-train --like from {sources}."), encoding="utf-8"
    )
    ranges = ranges or {}
    header = (
        f"Training prior of {spec.name}, scaled to its system (classifier.own_system.prior_for_spec): magnitude "
        "ranges = identifiable ranges\n(closed forms) widened by half a decade, speeds capped where a "
        "simulated pixel would hold too many scatterers.\nIdentifiable: "
        + "; ".join(f"{k} {v[0]:.3g}-{v[1]:.3g}" for k, v in ranges.items() if len(v) == 2)
        + "".join(
            f"; {k.split('_')[0]} simulated up to {v[0]:.3g} µm/s"
            for k, v in ranges.items()
            if k.endswith("_simulated_max")
        )
    )
    paths[".prior.toml"].write_text(toml_text(prior.to_dict(), header), encoding="utf-8")


def _train_into(args: argparse.Namespace, cfg, paths: dict[str, Path], *, spec=None, prior=None) -> str:
    """Train, export and write the report into ``paths`` (:func:`classifier.train.train_to_files`);
    returns the summary line."""
    from .report import training_summary
    from .train import train_to_files

    if not args.no_cache:  # should the run be interrupted (torchdoct.runtime.interrupt)
        from .dataset import default_cache_dir

        _interrupt.note(
            kept=f"the data splits simulated so far, in the cache {args.cache or default_cache_dir()}",
            resume="rerun the same command: those splits come from the cache",
        )
    res = train_to_files(
        cfg,
        paths,
        prior=prior,
        spec=spec,
        cache_dir=args.cache,
        use_cache=not args.no_cache,
        progress=not args.no_progress,
    )
    return training_summary(res.report)


def _as_typed(message: str) -> str:
    """A :class:`~classifier.train.TrainConfig` error with its fields named as the user types them
    (``TrainConfig.draws_train`` -> ``--draws-train``; a field no option sets: the training recipe's)."""
    import re

    options = {a.dest: a.option_strings[0] for a in build_train_parser()._actions if a.option_strings}
    text = re.sub(
        r"TrainConfig\.(\w+)", lambda m: options.get(m.group(1), f"the training recipe's {m.group(1)}"), message
    )
    return re.sub(r"\b[a-z0-9]+(?:_[a-z0-9]+)+\b", lambda m: options.get(m.group(0), m.group(0)), text)


def build_classify_parser() -> argparse.ArgumentParser:
    from .infer import DEFAULT_BACKGROUND_DB, DEFAULT_POOL

    p = argparse.ArgumentParser(
        prog="doct-classify",
        description="Classify every pixel of DOCT maps (from `torchdoct maps`) as diffusion, random-ballistic "
        "motion, flow or indeterminate. Writes classes.tif (+ legend.json), probabilities.tif, "
        "overlay.png and summary.json into --out.",
    )
    p.add_argument("maps", nargs="+", help="maps file(s) (.npz or .tif); several files are combined channel by channel")
    p.add_argument(
        "--model",
        default=None,
        help="ONNX model file or shipped model name (default: the shipped signature model whose features "
        "the maps hold, two-wavelength-signature for both bands, else single-acquisition)",
    )
    p.add_argument("--out", required=True, help="output directory (created if missing)")
    p.add_argument(
        "--pool", type=int, default=DEFAULT_POOL, help="average features over N x N (z, x) neighbourhoods first"
    )
    p.add_argument(
        "--background-db",
        default=DEFAULT_BACKGROUND_DB,
        help="mask pixels whose mean dB intensity is below this; 'auto' = 99th percentile - 30 dB; 'none'",
    )
    p.add_argument(
        "--decision",
        choices=("conformal", "rule"),
        default=None,
        help="conformal (the default for a model with a calibration file beside it): the prediction set "
        "of each pixel at error level --alpha; a single class is a decision, two classes a set "
        "label such as ballistic-or-flow, all three indeterminate (docs/abstention.md). rule: the "
        "model's argmax with its indeterminate class and --min-probability",
    )
    p.add_argument(
        "--alpha",
        type=float,
        default=None,
        help="error level of the conformal sets (default 0.1): on data like the calibration set, a set "
        "holds the true class with probability at least 1 - alpha; larger alpha: smaller sets, "
        "more pixels decided",
    )
    p.add_argument(
        "--min-probability",
        type=float,
        default=None,
        help="with --decision rule: override the model's threshold below which a pixel is indeterminate "
        "(higher: fewer pixels decided, more of them right; the model's report tabulates the trade-off)",
    )
    p.add_argument(
        "--decide-ballistic",
        action="store_true",
        help="keep the model's decisions; by default a ballistic or diffusion decision is flow where the "
        "speckle pattern moved coherently, and a ballistic one ballistic-or-flow where the physics "
        "cannot exclude flow (every other B-scan pixel; a volume's pixels that have not decorrelated "
        "or decorrelated before the shortest lag), and a ballistic or diffusion one its set with flow "
        "where the pattern's offset moved off the centre or grew with the lag; a flow decision that only the "
        "coarse configurations found, beside another region, and a decision fewer than half of its box "
        "(the coarsest PSF's footprint) share are indeterminate; docs/abstention.md)",
    )
    p.add_argument(
        "--ignore-refractive-index",
        action="store_true",
        help="accept maps whose system refractive index differs from the model's",
    )
    p.add_argument(
        "--threads",
        type=int,
        default=None,
        metavar="N",
        help="cores to use: chunks of pixels side by side, one onnxruntime thread each (default: "
        "$TORCHDOCT_THREADS, else the usable cores); results do not depend on N",
    )
    p.add_argument("--force", action="store_true", help="overwrite existing outputs")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument(
        "--max-input-gb",
        type=float,
        default=None,
        metavar="GB",
        help="largest maps array to read (GiB; default 8 or $TORCHDOCT_MAX_INPUT_GB)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar (as TQDM_DISABLE=1)")
    return p


@_interrupt.entry_point  # Ctrl-C/SIGTERM: one line, exit 130/143 (torchdoct.runtime.interrupt)
def classify_main(argv: Sequence[str] | None = None) -> int:
    """``doct-classify``: returns the exit code (0 done, 2 bad input, 1 other failure)."""
    args = build_classify_parser().parse_args(argv)
    _interrupt.silence_progress(args)
    return _run(_classify, args)


def _classify(args: argparse.Namespace) -> int:
    from . import infer

    bg = args.background_db
    if bg not in ("auto", "none"):
        try:
            bg = float(bg)
        except ValueError:
            raise ValueError(f"--background-db must be 'auto', 'none' or a number in dB; got {bg!r}") from None
    from torchdoct.measured.guards import set_max_input_gb

    from .outputs import check_outputs

    set_max_input_gb(args.max_input_gb)  # the readers' limit on one declared array
    check_outputs(args.out, args.force)  # before the work: --out a file, or an earlier run's files without --force
    from torchdoct.measured.guards import max_input_bytes
    from torchdoct.runtime.resources import check_classify

    check_classify("doct-classify", args.maps, max_input_bytes())  # memory, before anything is read
    try:
        res = infer.classify_maps(
            args.maps,
            args.model,
            pool=args.pool,
            background_db=bg,
            min_probability=args.min_probability,
            ignore_refractive_index=args.ignore_refractive_index,
            threads=args.threads,
            decision=args.decision,
            alpha=args.alpha,
            abstain_ambiguous=not args.decide_ballistic,
        )
    except ValueError as err:
        raise ValueError(_signature_hint(str(err))) from None
    written = infer.write_classification(res, args.out, force=args.force)
    counts = res.counts()
    if args.json:
        print(json.dumps({"counts": counts, "info": res.info, "written": [str(p) for p in written]}, indent=1))
    else:
        total = max(res.info["classified"], 1)
        print(
            f"model {res.model.path.name} ({res.model.metadata['spec']['name']}), pool {res.info['pool']}: "
            f"{res.info['classified']} of {res.info['pixels']} pixels classified "
            f"({res.info['background_pixels']} background, {res.info['nan_pixels']} NaN"
            + (
                f", {res.info['out_of_range_pixels']} with a feature outside its physical range: masked"
                if res.info.get("out_of_range_pixels")
                else ""
            )
            + ")"
        )
        conf = res.info.get("conformal")
        if conf:
            print(f"  decision: conformal prediction sets at alpha {conf['alpha']:g} (docs/abstention.md)")
        amb = res.info.get("ambiguity")
        if amb and amb["changed_pixels"].get("coherent_motion"):
            print(
                f"  flow where the speckle pattern moved coherently: {amb['changed_pixels']['coherent_motion']} pixels "
                "decided as a direction-symmetric motion (--decide-ballistic keeps the model's decisions)"
            )
        ch = amb["changed_pixels"] if amb else {}
        if ch and ch["bscan_plane"] + ch.get("sheared_flow", 0) + ch["slow_decorrelation"] + ch.get(
            "fast_decorrelation", 0
        ):
            print(
                f"  ballistic-or-flow where flow cannot be excluded: {ch['bscan_plane']} pixels of maps that cannot "
                f"see the pattern move along {', '.join(amb.get('unseen_axes') or ['y'])} (flow along it), "
                f"{ch.get('sheared_flow', 0)} without a phase reference (a sheared flow), "
                f"{ch['slow_decorrelation']} not decorrelated, "
                f"{ch.get('fast_decorrelation', 0)} decorrelated before the first lag "
                "(--decide-ballistic keeps the model's decisions)"
            )
        if ch.get("translation"):
            print(
                f"  flow where the held speckle pattern moved along a line: {ch['translation']} ballistic decisions "
                "or sets (--decide-ballistic keeps the model's decisions)"
            )
        if ch.get("doppler_drift"):
            print(
                f"  flow where the Doppler phase against the static reference drifted: {ch['doppler_drift']} "
                f"pixels decided as a direction-symmetric motion (box {amb['doppler_window_px']} px per axis; "
                "--decide-ballistic keeps the model's decisions)"
            )
        if ch.get("offset_moved"):
            print(
                f"  a set with flow where the pattern's offset moved: {ch['offset_moved']} ballistic or diffusion "
                "decisions (--decide-ballistic keeps the model's decisions)"
            )
        if ch.get("borrowed_flow"):
            print(
                f"  indeterminate where only the coarse configurations saw flow: {ch['borrowed_flow']} flow decisions "
                "that neither the pattern's motion nor the Doppler phase founds, at a region's border (box "
                + " × ".join(f"{n} {a}" for a, n in res.info["ambiguity"]["footprint_window_px"].items())
                + " px; --decide-ballistic keeps the model's decisions)"
            )
        if ch.get("mixed_footprint"):
            print(
                f"  indeterminate where a coarser configuration decayed faster than the finest: "
                f"{ch['mixed_footprint']} flow decisions that neither the pattern's motion nor the Doppler phase founds "
                "(--decide-ballistic keeps the model's decisions)"
            )
        if ch.get("unshared"):
            print(
                f"  indeterminate where few neighbours share the decision: {ch['unshared']} pixels (box "
                + " × ".join(f"{n} {a}" for a, n in res.info["ambiguity"]["consensus_window_px"].items())
                + " px; --decide-ballistic keeps the model's decisions)"
            )
        if ch.get("contradicted"):
            print(
                f"  indeterminate where the finest footprint holds another motion: {ch['contradicted']} pixels (box "
                + " × ".join(f"{n} {a}" for a, n in res.info["ambiguity"]["fine_window_px"].items())
                + " px; --decide-ballistic keeps the model's decisions)"
            )
        if ch.get("mixed_shape"):
            print(
                f"  indeterminate where a coarser configuration's decay shape is faster over the finest footprint: "
                f"{ch['mixed_shape']} diffusion decisions (--decide-ballistic keeps the model's decisions)"
            )
        for c in res.label_names:
            print(f"  {c:>22}: {counts[c]:>9} ({counts[c] / total:6.1%})")
        print(f"  {res.info['pixels_per_s']:.3g} pixels/s; wrote {', '.join(p.name for p in written)} to {args.out}")
        for note in ([res.info["model_choice"]] if res.info.get("model_choice") else []) + res.info.get("notes", []):
            print(f"note: {note}")
    return 0


def _signature_hint(message: str) -> str:
    """A missing model feature that is a decorrelation-signature channel: name the option that writes it
    (``torchdoct maps ... --signature``)."""
    import re

    m = re.search(r"maps lack the model feature '([^'@]+)@", message)
    if m is None or m.group(1) in ("liv", "ocds", "mean_db", "aliv", "swiftness") or "--signature" in message:
        return message
    return (
        f"{message}. The model reads decorrelation-signature channels ({m.group(1)}, ...), which "
        "`torchdoct maps` writes only with --signature: compute the maps again with `torchdoct maps DATA "
        "--resolution ... --signature --out MAPS`, or classify with the LIV/OCDS model (--model "
        "single-acquisition-bscan for B-scans, single-acquisition for volumes)"
    )


if __name__ == "__main__":  # pragma: no cover
    sys.exit(classify_main())
