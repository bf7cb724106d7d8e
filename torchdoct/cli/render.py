"""``torchdoct phantoms`` and ``torchdoct render`` (its benchmark: :mod:`torchdoct.cli.bench`)."""

from __future__ import annotations

from pathlib import Path

from .command import Command

__all__ = ["COMMANDS"]

_SUFFIXES = (".npz", ".npy", ".h5")


def _phantoms_arguments(ph) -> None:
    pass


def _render_arguments(r) -> None:
    r.add_argument("phantom", help="phantom or scene TOML file, or a shipped phantom or scene name")
    r.add_argument(
        "--grid",
        default=None,
        metavar="NZxNX|NYxNZxNX",
        help="pixels per axis (B-scan NZxNX, volume NYxNZxNX); replaces the file's [grid]",
    )
    r.add_argument("--pitch-um", type=float, default=None, help="pixel pitch (µm, all axes) with --grid")
    r.add_argument(
        "--out",
        required=True,
        help="output .npz, .npy or .h5 (with several systems: one file per system, "
        "named STEM-SYSTEM.SUFFIX); .npy/.npz get a .json metadata sidecar",
    )
    r.add_argument("--system", action="append", default=None, help="render only this system (repeatable)")
    r.add_argument("--seed", type=int, default=None)
    r.add_argument("--dtype", choices=("float32", "float64"), default=None)
    r.add_argument("--tolerance", type=float, default=None, help="PSF truncation tolerance (amplitude)")
    r.add_argument("--device", default=None)
    r.add_argument("--no-preview", action="store_true", help="do not write the PNG preview")
    r.add_argument("--force", action="store_true", help="overwrite existing outputs")
    r.add_argument("--no-progress", action="store_true")
    r.add_argument(
        "--max-scatterers",
        type=float,
        default=None,
        metavar="N",
        help="largest expected number of seeded scatterers (default 2e7, about 2.4 GB); checked before the work",
    )


def _phantoms(args) -> int:
    from ..image.phantom import load_phantom, shipped_phantoms

    for name, path in shipped_phantoms().items():
        print(f"{name:>14}: {load_phantom(path).scene.description}")
    return 0


def _grid(spec: str | None, pitch: float | None) -> dict | None:
    if spec is None:
        if pitch is not None:
            raise ValueError("--pitch-um needs --grid NZxNX (or NYxNZxNX)")
        return None
    try:
        n = [int(v) for v in spec.lower().split("x")]
    except ValueError:
        n = []
    if len(n) not in (2, 3) or min(n) < 1:
        raise ValueError(f"--grid must be NZxNX or NYxNZxNX with positive integers; got {spec!r}")
    if pitch is None:
        raise ValueError("--grid needs --pitch-um (pixel pitch in µm)")
    g = {"n_z": n[-2], "n_x": n[-1], "pitch_x_um": pitch, "pitch_z_um": pitch}
    if len(n) == 3:
        g.update(kind="volume", n_y=n[0], pitch_y_um=pitch)
    return g


def _outputs(out: Path, names: list[str]) -> dict[str, Path]:
    if len(names) == 1:
        return {names[0]: out}
    from ..files import safe_name

    for n in names:  # STEM-SYSTEM.SUFFIX: a system name must be a plain file name
        safe_name(n, "system name", "rename the system in the phantom file, or render one system with --system")
    return {n: out.with_name(f"{out.stem}-{n}{out.suffix}") for n in names}


def _render(args) -> int:
    from ..files import atomic_write, check_out, output_set
    from ..image.phantom import load_phantom
    from ..image.render import render, save_preview
    from ..measured.io import write_sequence

    ph = load_phantom(args.phantom, grid=_grid(args.grid, args.pitch_um))
    names = args.system or [s.name for s in ph.scene.systems]
    check_out(args.out, True, _SUFFIXES)  # suffix and directory; existence per file below
    outs = _outputs(Path(args.out), names)
    files = []  # the output set: written whole or not at all (an error, Ctrl-C, SIGTERM)
    for p in outs.values():
        files.append(check_out(p, args.force, _SUFFIXES))
        if p.suffix in (".npy", ".npz"):
            files.append(check_out(p.with_suffix(".json"), args.force, ".json", "metadata sidecar"))
        if p.suffix == ".npy":
            files.append(check_out(p.with_name(p.stem + ".labels.npz"), args.force, ".npz", "labels file"))
        if not args.no_preview:
            files.append(check_out(p.with_suffix(".png"), args.force, ".png", "preview"))
    if len(outs) > 1:  # say it before the work: --out is a pattern here, not the file written
        print(
            f"{len(outs)} systems: one file per system, {Path(args.out).stem}-SYSTEM{Path(args.out).suffix} "
            f"({', '.join(p.name for p in outs.values())}), not {Path(args.out).name}; --system NAME renders one "
            f"system into {Path(args.out).name}",
            flush=True,
        )
    try:
        res = render(
            ph,
            systems=names,
            seed=args.seed,
            dtype=args.dtype,
            device=args.device,
            truncation_tolerance=args.tolerance,
            progress=not args.no_progress,
            max_scatterers=args.max_scatterers,
        )
    except ValueError as err:  # what the phantom asks that the run cannot hold: named with its file
        raise ValueError(f"{args.phantom}: {err}") from None
    print(
        f"rendered {ph.name!r}: {res.phantom.grid.axes} {tuple(res.data.shape[1:])}, "
        f"{len(names)} system(s), seed {res.seed}, {res.elapsed_s:.2f} s"
    )
    print("stages: " + "; ".join(res.work["stages"]))
    for pop, w in res.work["populations"].items():
        print(f"  {pop}: " + ", ".join(f"{k} {v}" for k, v in w.items()))
    with output_set(files, args.force) as stage:
        for n, p in outs.items():
            k = res.system_index(n)
            meta = res.metadata(k)
            if p.suffix == ".npy":  # a .npy holds one array: the ground truth goes beside it
                lab = p.with_name(p.stem + ".labels.npz")
                meta["labels_file"] = lab.name
                atomic_write(stage(lab), lambda tmp: _save_labels(tmp, res))
                write_sequence(stage(p), res.data[k].cpu().numpy(), meta, force=args.force)
            else:
                write_sequence(
                    stage(p),
                    res.data[k].cpu().numpy(),
                    meta,
                    labels=res.labels,
                    label_params=res.label_params,
                    force=args.force,
                )
            if not args.no_preview:
                atomic_write(stage(p.with_suffix(".png")), lambda tmp, k=k: save_preview(res, tmp, k))
    for p in files:
        print(f"wrote {p}")
    return 0


def _save_labels(path: str, res) -> None:
    import numpy as np

    with open(path, "wb") as fh:
        np.savez(fh, labels=res.labels, label_params=res.label_params, regions=res.regions)


COMMANDS = {
    "phantoms": Command("list the shipped phantoms", _phantoms_arguments, _phantoms),
    "render": Command(
        "render a phantom's complex image sequence, labels and a PNG preview", _render_arguments, _render
    ),
}
