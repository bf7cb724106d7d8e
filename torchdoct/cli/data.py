"""Command line for measured data: ``torchdoct maps`` and ``torchdoct compare`` (their benchmarks:
:mod:`torchdoct.cli.bench`).

Thin layer: parse, call one library function (:func:`torchdoct.measured.maps.compute_maps`,
:func:`torchdoct.measured.compare.compare_samples`), print.
"""

from __future__ import annotations

import argparse
import glob
import math
import struct
import sys
import zipfile
from pathlib import Path

import numpy as np

from .command import Command, parse_floats

__all__ = ["COMMANDS"]


def _maps_arguments(mp) -> None:
    mp.add_argument(
        "input",
        nargs="+",
        help="sequence file: .npy/.npz/.raw/.bin (+ .json sidecar), .h5, .mat (v5, "
        "v7.3), .tif, .ome.tif, a .zarr OME-Zarr folder or a folder of per-frame "
        "TIFFs (docs/formats.md); several: each --out names its file with {stem}",
    )
    mp.add_argument(
        "--resolution",
        action="append",
        default=None,
        metavar="R",
        help="original | axial=UM | lateral=UM | axial=UM,lateral=UM (repeat; default original)",
    )
    mp.add_argument("--metrics", default="liv,ocds,mean_db", help="comma list of liv, ocds, mean_db (default all 3)")
    mp.add_argument("--aliv", action="store_true", help="also compute aLIV and Swiftness (LIV-curve fit)")
    mp.add_argument(
        "--signature",
        action="store_true",
        help="also write the decorrelation-signature channels (torchdoct.sim.signature) that the "
        "classifier's signature model reads",
    )
    mp.add_argument(
        "--speckle",
        action="store_true",
        help="also write the speckle-motion channels (torchdoct.sim.speckle; lagged cross-correlation of "
        "each pixel's window: peak offset, velocity, moving share) at the original resolution",
    )
    mp.add_argument(
        "--no-speckle",
        action="store_true",
        help="with --signature: leave out the speckle-motion channels it adds by default for B-scans "
        "and volumes with a pixel pitch and a uniform frame interval",
    )
    mp.add_argument(
        "--speckle-dynamic",
        action="store_true",
        help="also write the speckle-motion channels of the dynamic field (xcd_*: the complex field less its "
        "temporal mean, which removes static tissue sharing the PSF, so a flow inside it shows its offset; "
        "complex data; docs/concepts/speckle-motion.md §3 (f)); implies --speckle",
    )
    mp.add_argument(
        "--speckle-window",
        type=int,
        default=9,
        metavar="N",
        help="window of the speckle-motion channels, N pixels per axis (odd; default 9)",
    )
    mp.add_argument(
        "--doppler",
        action="store_true",
        help="also write the Doppler phase against a static-tissue reference in the same A-line or B-scan "
        "(doppler_phase_M, rad, complex data; docs/concepts/doppler-reference.md); no reference: "
        "no channel",
    )
    mp.add_argument(
        "--no-doppler",
        action="store_true",
        help="with --signature: leave out the Doppler channel it adds by default for complex data (the "
        "classifier's rules 10 and 11 read it where a static reference exists: without it no volume pixel is "
        "decided random-ballistic)",
    )
    mp.add_argument(
        "--doppler-lags",
        default=None,
        metavar="M[,M..]",
        help="lags of the Doppler channels in frames (default 1; needs --doppler)",
    )
    mp.add_argument(
        "--out",
        action="append",
        required=True,
        metavar="FILE",
        help="output maps file: .npz, .tif (ImageJ hyperstack), .ome.tif (OME-TIFF) or .zarr (OME-Zarr); "
        "repeat to write several",
    )
    mp.add_argument("--force", action="store_true", help="overwrite existing outputs")
    b = mp.add_argument_group("many inputs (torchdoct.cli.mapsbatch)")
    b.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help="inputs computed side by side in N worker processes, one core each (default 1: one after another)",
    )
    b.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="compute the inputs as tasks on an existing Dask distributed cluster (e.g. tcp://host:8786); "
        "the workers read and write the same paths",
    )
    g = mp.add_argument_group("metadata (override or supply the file's)")
    g.add_argument("--axes", default=None, help="stored axis order, e.g. TZX, TYZX, XZT (MATLAB [Z,X,T] in HDF5)")
    g.add_argument("--pitch-um", default=None, help="pixel pitch in µm, e.g. z=1.5,x=2.0[,y=7.8]")
    g.add_argument("--frame-interval-s", type=float, default=None, help="uniform frame interval (s)")
    g.add_argument("--frame-times-s", default=None, help="comma-separated frame times (s)")
    g.add_argument("--wavelength-um", type=float, default=None, help="centre wavelength (µm, vacuum)")
    g.add_argument("--lateral-resolution-um", type=float, default=None, help="original 1/e² lateral width (µm)")
    g.add_argument("--axial-resolution-um", type=float, default=None, help="original axial FWHM in the medium (µm)")
    g.add_argument("--refractive-index", type=float, default=None, help="refractive index n (default 1)")
    g.add_argument("--system-name", default=None, help="name of the OCT system")
    g.add_argument("--dataset", default=None, help="HDF5 dataset / MATLAB variable name")
    g.add_argument(
        "--scale",
        choices=("linear", "db", "complex"),
        default=None,
        help="what the samples are: complex field, linear intensity or dB intensity (converted to "
        "linear); checked against the values (default: complex data are the field, real data linear)",
    )
    g.add_argument(
        "--allow-external-hdf5",
        action="store_true",
        help="read HDF5 external storage, external links and virtual datasets whose data lie in other "
        "files (refused by default: they can make any readable file into data)",
    )
    g.add_argument(
        "--max-memory-gb",
        type=float,
        default=None,
        metavar="GB",
        help="working memory of the maps (slabs and output; GiB): the sequence is streamed through "
        "them in slabs that fit; .npy, raw, uncompressed OME-TIFF, OME-Zarr and TIFF-folder inputs read slab by "
        "slab (docs/formats.md)",
    )
    g.add_argument(
        "--max-input-gb",
        type=float,
        default=None,
        metavar="GB",
        help="largest input array to read (GiB; default 8 or $TORCHDOCT_MAX_INPUT_GB)",
    )
    g.add_argument(
        "--block-raster",
        default=None,
        metavar="B:R:K",
        help="block raster protocol: blocks:repeats:B-scans per block (paper: 8:32:16); a flat "
        "[B*R*K, Z, X] stack in acquisition order is unpacked to [R, B*K, Z, X]",
    )
    g.add_argument(
        "--drop-boundary",
        type=int,
        default=1,
        help="B-scans dropped on each side of block boundaries (default 1; 0 keeps all)",
    )
    a = mp.add_argument_group("metric and reduction options")
    a.add_argument("--ocds-delay-range-s", nargs=2, type=float, default=[0.2048, 1.2288], metavar=("LO", "HI"))
    a.add_argument("--ocds-scale", choices=("db", "linear"), default="db")
    a.add_argument("--ocds-estimator", choices=("pearson", "biased"), default="pearson")
    a.add_argument("--no-aliv-smoothing", action="store_true", help="no 3x3 box smoothing of the LIV curves")
    a.add_argument("--aliv-max-window-s", type=float, default=None, help="longest LIV-curve window (s)")
    a.add_argument(
        "--axial-center",
        default="zero",
        help="axial window centre: zero (simulated data), centroid (measured data with a depth "
        "carrier), or cycles/pixel",
    )
    a.add_argument("--edge-mode", choices=("reflect", "constant", "wrap"), default="reflect")
    a.add_argument(
        "--normalization",
        choices=("power", "peak", "sum"),
        default="power",
        help="filter gain: power keeps the mean intensity (default), peak the PSF peak, sum unit kernel",
    )
    a.add_argument("--device", default=None, help="torch device (default cpu)")
    bp = mp.add_argument_group("bulk-phase correction (complex data; physics.md §12)")
    bp.add_argument(
        "--bulk-phase",
        choices=("weighted-mean", "histogram"),
        default=None,
        help="remove the bulk phase per A-line and consecutive frame pair before the resolution "
        "reduction and the signature: weighted-mean (arg of the summed E_{i+1}E_i* along depth) "
        "or histogram (peak of the intensity-weighted phase-difference histogram; keeps the "
        "Doppler ramp of a flowing layer)",
    )
    bp.add_argument(
        "--bulk-phase-mask",
        default="all",
        metavar="all|median|stable[:C]|DB",
        help="pixels used: all (default), median (the brighter half of each A-line), stable (pixels whose "
        "temporal intensity contrast is <= C, default 0.05: the static tissue; best for samples "
        "with moving scatterers), or a dB threshold on |E_{i+1}E_i*|",
    )
    bp.add_argument(
        "--bulk-phase-rows",
        default=None,
        metavar="Z0:Z1",
        help="depth rows used for the estimate (default all; the correction applies to every row)",
    )
    p = mp.add_argument_group("pseudo-colour PNGs")
    p.add_argument("--png", action="store_true", help="write OUT_metric_resolution.png per channel")
    p.add_argument(
        "--range",
        action="append",
        default=[],
        metavar="METRIC=LO,HI",
        help="colour-scale range of a metric, e.g. liv=0,10 (default 1st-99th percentile)",
    )
    p.add_argument(
        "--db-range",
        nargs=2,
        type=float,
        default=None,
        metavar=("LO", "HI"),
        help="brightness range (dB) (default 5th-99.9th percentile)",
    )
    p.add_argument("--png-y", type=int, default=None, help="B-scan index shown for volumes (default middle)")
    mp.add_argument("--no-progress", action="store_true", help="no progress bar")


def _compare_arguments(cp) -> None:
    cp.add_argument(
        "maps",
        nargs="+",
        metavar="[SAMPLE=]MAPS",
        help="maps files; SAMPLE= groups files of one sample (default: file stem)",
    )
    cp.add_argument(
        "--mask",
        action="append",
        default=None,
        metavar="FILE",
        help="region mask per maps file, in the same order (.npy, .npz, .tif; boolean or 0/1)",
    )
    cp.add_argument("--threshold-db", type=float, default=None, help="region = pixels with mean_db >= this (dB)")
    cp.add_argument(
        "--threshold-resolution",
        default=None,
        help="resolution of the mean_db channel used for the threshold (default: the file's first)",
    )
    cp.add_argument(
        "--config",
        action="append",
        default=None,
        metavar="[WL_UM:]RESOLUTION",
        help="configurations to compare, in order (default: all common ones)",
    )
    cp.add_argument("--metrics", default="liv,ocds", help="comma list of metrics (default liv,ocds)")
    cp.add_argument("--alpha", type=float, default=0.05, help="significance level (default 0.05)")
    cp.add_argument("--out", default=None, help="tests table (.csv)")
    cp.add_argument("--per-sample", default=None, help="per-sample means table (.csv)")
    cp.add_argument("--plot", default=None, help="means ± SD plot (.png, .pdf, .svg)")
    cp.add_argument("--force", action="store_true", help="overwrite existing outputs")
    cp.add_argument("--json", action="store_true", help="print the tests as JSON")
    cp.add_argument(
        "--max-input-gb",
        type=float,
        default=None,
        metavar="GB",
        help="largest maps or mask array to read (GiB; default 8 or $TORCHDOCT_MAX_INPUT_GB)",
    )


# ----------------------------------------------------------------------------------------------
# handlers


def _maps(args: argparse.Namespace) -> int:
    """One input in this process (:func:`maps_one`), or many (:mod:`torchdoct.cli.mapsbatch`)."""
    inputs = args.input if isinstance(args.input, list) else [args.input]
    if len(inputs) == 1 and args.scheduler is None and (args.workers or 1) == 1:
        from .mapsbatch import outputs_of

        args.input, args.out = inputs[0], outputs_of(inputs, list(args.out))[0]
        return maps_one(args)
    from .mapsbatch import run_many

    return run_many(args, maps_task, maps_one)


def maps_task(payload: dict) -> dict:
    """One input of many (:func:`torchdoct.cli.mapsbatch.run_many`): :func:`maps_one` on ``payload``; module-level
    so that worker processes and Dask workers import it."""
    from .mapsbatch import run_task

    return run_task(maps_one, payload)


def maps_one(args: argparse.Namespace) -> int:
    """``torchdoct maps`` on the one input ``args.input``."""
    from ..files import check_out
    from ..measured.guards import set_max_input_gb
    from ..measured.io import MAPS_SUFFIXES, BlockRaster, read_sequence, write_maps
    from ..measured.maps import check_maps_request, compute_maps, write_pngs

    set_max_input_gb(args.max_input_gb)
    outs = []
    for o in args.out:
        if Path(o).suffix == ".zarr" and Path(o).exists():  # a folder: never replaced, even with --force
            raise ValueError(
                f"--out: {o} exists; an OME-Zarr folder is never overwritten: remove it or give another name"
            )
        outs.append(check_out(o, args.force, MAPS_SUFFIXES, what="--out"))
    if len({p.resolve() for p in outs}) != len(outs):
        raise ValueError("--out given twice with the same file")
    metrics = [m.strip() for m in args.metrics.split(",") if m.strip()]
    if args.aliv:
        metrics += [m for m in ("aliv", "swiftness") if m not in metrics]
    ranges = {}
    for r in args.range:
        key, sep, val = r.partition("=")
        if not sep:
            raise ValueError(f"--range must be METRIC=LO,HI (e.g. liv=0,10); got {r!r}")
        ranges[key.strip()] = tuple(parse_floats(val, 2, f"--range {key}"))
    _check_png_options(args, ranges, metrics)  # before anything is read or written
    system = {
        k: v
        for k, v in (
            ("name", args.system_name),
            ("wavelength_um", args.wavelength_um),
            ("lateral_resolution_um", args.lateral_resolution_um),
            ("axial_resolution_um", args.axial_resolution_um),
            ("refractive_index", args.refractive_index),
        )
        if v is not None
    }
    raster = BlockRaster.parse(args.block_raster, args.drop_boundary) if args.block_raster else None
    center: str | float = args.axial_center
    if center not in ("zero", "centroid"):
        center = parse_floats(center, 1, "--axial-center")[0]
    seq = read_sequence(
        args.input,
        axes=args.axes,
        pitch_um=args.pitch_um,
        frame_times_s=parse_floats(args.frame_times_s, None, "--frame-times-s") if args.frame_times_s else None,
        frame_interval_s=args.frame_interval_s,
        system=system or None,
        dataset=args.dataset,
        block_raster=raster,
        allow_external_hdf5=args.allow_external_hdf5,
        scale=args.scale,
        stream=args.max_memory_gb is not None,
    )
    resolutions = args.resolution or ["original"]
    if args.doppler_lags is not None and not args.doppler:
        raise ValueError("--doppler-lags sets the Doppler channels; add --doppler")
    if args.doppler and args.no_doppler:
        raise ValueError("--doppler and --no-doppler contradict each other: give one")
    doppler = None
    if args.signature and not args.no_doppler and seq.is_complex:
        doppler = True  # one flag gives the classifier what it reads: its rule 10 reads the Doppler phase
    if args.doppler:
        doppler = True if args.doppler_lags is None else [_lag(v) for v in args.doppler_lags.split(",") if v.strip()]
    options = dict(
        metrics=metrics,
        signature=args.signature,
        speckle=args.speckle or None,
        doppler=doppler,
        speckle_window=args.speckle_window,
        ocds_delay_range_s=tuple(args.ocds_delay_range_s),
        ocds_scale=args.ocds_scale,
        ocds_estimator=args.ocds_estimator,
        edge_mode=args.edge_mode,
        normalization=args.normalization,
    )
    if args.speckle and args.no_speckle:
        raise ValueError("--speckle and --no-speckle contradict each other: give one")
    if args.signature and not args.speckle and not args.no_speckle:
        # one flag gives a model what it reads: the speckle channels where the sequence allows them
        try:
            check_maps_request(seq, resolutions, **{**options, "speckle": True})
            options["speckle"] = True
        except ValueError as err:
            print(f"note: --signature without the speckle-motion channels: {err}", file=sys.stderr)
    if args.speckle_dynamic:
        if args.no_speckle:
            raise ValueError("--speckle-dynamic and --no-speckle contradict each other: give one")
        from ..sim.speckle import map_speckle_features

        ndim, n_t = len(seq.axes) - 1, len(seq.frame_times_s)
        if ndim in (2, 3):  # other axes: check_maps_request names what the speckle channels need
            options["speckle"] = map_speckle_features(ndim, n_frames=n_t, dynamic=True)
        else:
            options["speckle"] = True
    check_maps_request(seq, resolutions, **options)  # what compute_maps refuses, before the bulk-phase estimate
    if args.png_y is not None:  # the B-scan shown must exist
        n_y = dict(zip(seq.axes, seq.data.shape)).get("Y")
        if n_y is None:
            raise ValueError(f"--png-y: {seq.source} holds B-scans ({seq.axes}), not a volume; drop --png-y")
        if not 0 <= args.png_y < n_y:
            raise ValueError(f"--png-y {args.png_y} is outside 0..{n_y - 1} (the volume's {n_y} B-scans)")
    if args.png:  # check the PNG paths before the work
        from ..measured.maps import METRICS, png_name
        from ..measured.resolution import parse_resolution

        for r in resolutions:
            for m in metrics:
                if m in METRICS:
                    check_out(
                        png_name(outs[0], f"{m}@{parse_resolution(r).label}"), args.force, ".png", what="PNG output"
                    )
    bulk = None
    if args.bulk_phase:
        from ..measured.bulkphase import estimate_bulk_phase

        bulk = estimate_bulk_phase(
            seq,
            args.bulk_phase,
            mask=args.bulk_phase_mask,
            rows=args.bulk_phase_rows,
            device=args.device,
            progress=not args.no_progress,
        )
        info = bulk.meta()
        print(
            f"bulk phase ({bulk.method}, mask {info['mask']}): RMS step {info['step_rms_rad']:.3f} rad, "
            f"{info['pairs_without_signal']} A-line pairs without signal"
        )
    elif args.bulk_phase_mask != "all" or args.bulk_phase_rows is not None:
        raise ValueError("--bulk-phase-mask and --bulk-phase-rows need --bulk-phase METHOD")
    from ..runtime.resources import check_maps

    check_maps(
        seq.source,
        seq.data.shape,
        seq.data.dtype.itemsize,
        complex_samples=seq.is_complex,  # disk space
        n_resolutions=len(resolutions),
        metrics=metrics,
        slab_elements=None,
        out_paths=outs,
    )
    if args.max_memory_gb is not None:  # slabs that fit the budget (the default slab size otherwise)
        from ..runtime.resources import slab_elements_within

        options["slab_elements"] = slab_elements_within(
            args.max_memory_gb,
            seq.data.shape,
            seq.data.dtype.itemsize,
            complex_samples=seq.is_complex,
            n_resolutions=len(resolutions),
            metrics=metrics,
            source=seq.source,
        )
    maps = compute_maps(
        seq,
        resolutions,
        **options,
        aliv_smoothing=not args.no_aliv_smoothing,
        aliv_max_window_s=args.aliv_max_window_s,
        axial_center=center,
        drop_boundary=args.drop_boundary > 0,
        device=args.device,
        bulk_phase=bulk,
        progress=not args.no_progress,
    )
    if args.signature:  # computed in the slab loop, from the same (bulk-corrected, reduced) field
        from ..measured.maps import signature_channels

        note = signature_channels(seq)[1]
        if note:
            print(f"note: {note}")
    dop = maps.meta.get("doppler")
    if dop:  # the reference found, or why there is no channel
        for m, rec in (dop.get("per_lag") or {}).items():
            print(
                f"Doppler reference at lag {m}: {rec['reference_share']:.1%} of the pixels; A-lines with their own "
                f"{rec['alines_own_reference']}, with their B-scan's {rec['alines_bscan_reference']}, without "
                f"{rec['alines_without_reference']} (NaN there)"
            )
        if dop.get("absent"):
            flag = "--doppler" if args.doppler else "--signature (complex data)"
            print(f"note: {flag}: no Doppler channel: {dop['absent']}")
    nonfinite = maps.meta.get("nonfinite")
    if nonfinite:  # masked per pixel (compute_maps): say how many and where
        per = ", ".join(f"{n} at {res}" for res, n in nonfinite["masked_pixels"].items())
        n = nonfinite["samples"]
        print(
            f"note: {seq.source}: {n} sample{'s are' if n != 1 else ' is'} NaN or infinite, masked: a reduction "
            "re-weights the finite samples (valid_weight@… channels: the share of each window on them) and a "
            f"pixel is NaN where that share is below half, or at its own pixel at the original (pixels: {per})"
        )
    shape = "×".join(str(s) for s in maps.maps.shape[1:])
    print(
        f"{seq.source}: {seq.n_frames} frames, {'complex' if seq.is_complex else 'intensity'} "
        f"{list(seq.data.shape)} ({seq.axes}) → {len(maps.channels)} channels [{maps.meta['axes']}] {shape}"
    )
    print(f"{'channel':>34}  {'unit':>5}  {'median':>10}  {'mean':>10}  {'finite':>7}")
    for i, name in enumerate(maps.channels):
        v = maps.maps[i]
        fin = np.isfinite(v)
        med = float(np.median(v[fin])) if fin.any() else math.nan
        mean = float(np.mean(v[fin], dtype=np.float64)) if fin.any() else math.nan
        print(f"{name:>34}  {maps.meta['channels'][i]['unit']:>5}  {med:10.4f}  {mean:10.4f}  {fin.mean():7.1%}")
    for res, n in (maps.meta.get("aliv") or {}).get("flagged_pixels", {}).items():
        print(
            f"aLIV fit on a τ bound at {res}: {n['tau_at_lower_bound']} pixels at the lower, "
            f"{n['tau_at_upper_bound']} at the upper bound (aliv_fit channel; magenta in the PNGs)"
        )
    from ..files import output_set

    png_kw = dict(
        ranges=ranges, db_range=tuple(args.db_range) if args.db_range else None, y_index=args.png_y, force=args.force
    )
    files = list(outs) + (write_pngs(maps, outs[0], check_only=True, **png_kw) if args.png else [])
    # --force replaces the whole earlier set: its PNGs of channels this run does not draw go with it
    earlier = [p for p in _earlier_pngs(outs[0]) if p not in files] if args.force else []
    with output_set(files + earlier, args.force) as stage:  # maps files and PNGs appear together or not at all
        for o in outs:
            write_maps(stage(o), maps, force=args.force)
        if args.png:  # one set of PNGs, named after the first --out
            write_pngs(maps, stage(outs[0]), **png_kw)
    for p in files:
        print(f"wrote {p}")
    for p in earlier:
        print(f"removed {p} (an earlier run's PNG of this output; --force replaces the whole set)")
    return 0


def _lag(text: str) -> int:
    try:
        return int(text.strip())
    except ValueError:
        raise ValueError(f"--doppler-lags: lags are whole numbers of frames, e.g. 1,2,4; got {text!r}") from None


def _earlier_pngs(out: Path) -> list[Path]:
    """PNGs of an earlier ``maps --png`` run named after ``out`` (``STEM_METRIC_RESOLUTION.png``, METRIC a
    DOCT metric or a signature feature): the output set that ``--force`` replaces."""
    from ..measured.maps import METRICS

    found = []
    for p in sorted(out.parent.glob(f"{glob.escape(out.stem)}_*.png")):
        rest = p.stem[len(out.stem) + 1 :]
        metric = rest.rsplit("_", 1)[0] if "_" in rest else ""
        if metric in METRICS or metric.startswith("doppler_phase_") or (metric and _signature_feature(metric)):
            found.append(p)
    return found


def _check_png_options(args: argparse.Namespace, ranges: dict[str, tuple[float, float]], metrics: list[str]) -> None:
    """``--range``, ``--db-range`` and ``--png-y``: refused when they would be ignored or cannot be drawn."""
    given = [
        o
        for o, v in (
            ("--range", bool(args.range)),
            ("--db-range", args.db_range is not None),
            ("--png-y", args.png_y is not None),
        )
        if v
    ]
    if given and not args.png:
        raise ValueError(f"{', '.join(given)} set(s) the PNGs; add --png (or drop {given[0]})")
    from ..measured.maps import METRICS

    valid = [m for m in metrics if m in METRICS]
    for key, (lo, hi) in ranges.items():
        if key not in valid and not (args.signature and _signature_feature(key)):
            raise ValueError(
                f"--range {key}={lo:g},{hi:g}: {key!r} is not a metric of these maps; give one of "
                f"{', '.join(valid)}" + (" or a signature feature (rho_db_1, ...)" if args.signature else "")
            )
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ValueError(f"--range {key}: LO,HI must be finite numbers with LO < HI; got {lo:g},{hi:g}")
    if args.db_range is not None:
        lo, hi = args.db_range
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ValueError(f"--db-range: LO HI must be finite numbers (dB) with LO < HI; got {lo:g} {hi:g}")
    if args.png_y is not None and args.png_y < 0:
        raise ValueError(f"--png-y must be a B-scan index >= 0; got {args.png_y}")


def _signature_feature(name: str) -> bool:
    from ..sim.signature import feature_unit

    try:
        feature_unit(name)
    except (ValueError, KeyError):
        return False
    return True


def _load_mask(path: str) -> np.ndarray:
    from ..files import check_regular_file

    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"mask file {p} does not exist")
    check_regular_file(p, "mask file")
    suf = p.suffix.lower()
    if suf in (".npy", ".npz"):
        try:
            if suf == ".npy":
                from ..measured.guards import check_npy_header, check_npy_size

                check_npy_header(p, "mask ")
                check_npy_size(p, "mask ")
                return np.load(p, allow_pickle=False)
            from ..measured.guards import check_npz_sizes

            check_npz_sizes(p, "mask ")
            with open(p, "rb") as fh, np.load(fh, allow_pickle=False) as z:
                key = "mask" if "mask" in z.files else (z.files[0] if len(z.files) == 1 else None)
                if key is None:
                    raise ValueError(f"{p.name}: store the mask under the key 'mask'")
                return z[key]
        except ValueError as err:
            if "--max-input-gb" in str(err) or "truncated:" in str(err):  # already names the mask and the fix
                raise
            if "allow_pickle" in str(err):
                raise ValueError(
                    f"mask {p.name}: holds an object array, which would need unpickling; refused "
                    "(store a boolean or 0/1 array)"
                ) from None
            raise ValueError(f"mask {p.name}: not a readable {suf} mask ({err})") from None
        except (EOFError, OSError, zipfile.BadZipFile, KeyError) as err:
            raise ValueError(
                f"mask {p.name}: not a readable {suf} file (truncated or corrupt: {type(err).__name__})"
            ) from None
    if suf in (".tif", ".tiff"):
        import tifffile

        from ..measured.guards import TiffDamage, check_tiff_pages

        try:
            with TiffDamage() as damage, tifffile.TiffFile(p) as tf:  # a truncated file: tifffile only logs
                check_tiff_pages(p, tf, "mask ")  # one shape, within the input limit, before reading
                arr = tf.asarray()
                damage.check()
            return arr
        except ValueError as err:
            if "--max-input-gb" in str(err) or "pages of two shapes" in str(err):
                raise
            raise ValueError(
                f"mask {p.name}: not a readable TIFF, truncated or corrupt ({type(err).__name__}: {err})"
            ) from None
        except (tifffile.TiffFileError, OSError, IndexError, KeyError, struct.error) as err:  # a damaged file
            raise ValueError(
                f"mask {p.name}: not a readable TIFF, truncated or corrupt ({type(err).__name__}: {err})"
            ) from None
    raise ValueError(f"mask {p.name}: use .npy, .npz or .tif")


def _compare(args: argparse.Namespace) -> int:
    from ..files import atomic_write, check_out
    from ..measured.compare import compare_samples, plot_comparison, region_mask
    from ..measured.guards import set_max_input_gb
    from ..measured.io import read_maps

    set_max_input_gb(args.max_input_gb)
    out = check_out(args.out, args.force, ".csv", what="--out")
    per_out = check_out(args.per_sample, args.force, ".csv", what="--per-sample")
    plot_out = check_out(args.plot, args.force, (".png", ".pdf", ".svg"), what="--plot")
    if args.mask is not None and len(args.mask) != len(args.maps):
        raise ValueError(f"give one --mask per maps file ({len(args.maps)}); got {len(args.mask)}")
    if args.mask is not None and args.threshold_db is not None:
        raise ValueError("give --mask or --threshold-db, not both")
    named = []
    for spec in args.maps:
        name, sep, path = spec.partition("=")
        named.append((name, path) if sep and name and "/" not in name else (Path(spec).stem, spec))
    from ..measured.guards import max_input_bytes
    from ..runtime.resources import check_compare

    check_compare([path for _, path in named], max_input_bytes())  # memory, before anything is read
    samples: dict[str, list] = {}
    for k, (name, path) in enumerate(named):
        maps = read_maps(path)
        mask = _load_mask(args.mask[k]) if args.mask is not None else None
        try:
            region = region_mask(
                maps, mask=mask, threshold_db=args.threshold_db, threshold_resolution=args.threshold_resolution
            )
        except ValueError as err:  # name the mask file that does not fit its maps
            if mask is None:
                raise
            raise ValueError(f"--mask {args.mask[k]} (for {path}): {err}") from None
        samples.setdefault(name, []).append((maps, region))
    metrics = [m.strip() for m in args.metrics.split(",") if m.strip()]
    if out is not None and len(samples) < 2:
        raise ValueError(
            f"--out: the tests need at least 2 samples; got 1 ({next(iter(samples))}); give more "
            "samples, or drop --out for the one-sample summary (--per-sample writes its means)"
        )
    res = compare_samples(samples, metrics=metrics, configs=args.config, alpha=args.alpha)
    if args.json:
        print(res.tests.to_json(orient="records", indent=2))
    else:
        print(res.format())
    from ..files import output_set

    files = [p for p in (out, per_out, plot_out) if p is not None]
    with output_set(files, args.force) as stage:  # the tables and the plot appear together or not at all
        if out is not None:
            atomic_write(stage(out), lambda tmp: res.tests.to_csv(tmp, index=False))
        if per_out is not None:
            atomic_write(stage(per_out), lambda tmp: res.per_sample.to_csv(tmp, index=False))
        if plot_out is not None:
            plot_comparison(res, stage(plot_out), force=args.force)
    for p in files:
        print(f"wrote {p}")
    return 0


COMMANDS = {
    "maps": Command(
        "DOCT maps (LIV, OCDS, mean dB, aLIV, Swiftness) of an OCT sequence file",
        _maps_arguments,
        _maps,
        "Compute DOCT maps of a complex (or intensity) OCT sequence at one or more "
        "resolutions and write them to .npz, .tif, .ome.tif or .zarr, with optional pseudo-colour "
        "PNGs. Several inputs run one after another, in worker processes (--workers) or on a Dask "
        "cluster (--scheduler).",
    ),
    "compare": Command(
        "per-sample mean LIV/OCDS per configuration and the paper's tests (tests need >= 2 samples)",
        _compare_arguments,
        _compare,
        "Mean DOCT values of several samples' maps per configuration; paired t-test "
        "(2 configurations) or Kruskal-Wallis then pairwise paired t-tests (3+). The "
        "tests need at least 2 samples; one sample gets its means without tests.",
    ),
}
