"""``torchdoct bench bulk-phase``: the residual phase error of the bulk-phase correction
(:mod:`torchdoct.measured.bulkphase`) against SNR, measured on synthetic A-lines (beside the first-order
prediction :func:`~torchdoct.measured.bulkphase.predicted_residual_rms`) and on a rendered phantom."""

from __future__ import annotations

import math
import time
from collections.abc import Sequence as _Seq
from typing import Any

import numpy as np
import torch

from ..conventions import noise_power, noise_sigma
from ..measured.bulkphase import METHODS, corrected_sequence, estimate_bulk_phase, phase_steps, predicted_residual_rms
from ..measured.io import SequenceData
from ..runtime.machine import machine_info
from ..runtime.resources import check_bench
from ..runtime.threads import one_torch_thread

__all__ = ["residual_rms", "bench_bulk_phase", "bench_bulk_phase_phantom", "format_bench_bulk_phase"]


def _synthetic(n_lines: int, n_z: int, n_frames: int, snr_db: float, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Static circular-Gaussian speckle (unit power) per A-line, white noise at ``snr_db``, and a
    uniform random bulk phase per frame and A-line (0 at the first frame): ``(lines [T, L, Z], φ [T, L])``."""
    g = torch.Generator().manual_seed(int(seed))

    def cn(*shape: int) -> torch.Tensor:
        return torch.complex(
            torch.randn(*shape, generator=g, dtype=torch.float64), torch.randn(*shape, generator=g, dtype=torch.float64)
        ) / math.sqrt(2.0)

    s = cn(n_lines, n_z)
    noise = cn(n_frames, n_lines, n_z) * math.sqrt(noise_power(1.0, float(snr_db)))
    phi = (torch.rand(n_frames, n_lines, generator=g, dtype=torch.float64) * 2 - 1) * math.pi
    phi[0] = 0.0
    lines = (s[None] + noise) * torch.exp(1j * phi)[..., None]
    return lines.to(torch.complex64), phi


def residual_rms(steps: torch.Tensor, phi: torch.Tensor) -> tuple[float, float]:
    """RMS over frames and A-lines of the residual phase about each A-line's frame mean (rad), and its
    standard error over A-lines: ``steps [T−1, L]`` estimated, ``phi [T, L]`` true (``phi[0] = 0``)."""
    est = torch.cat([torch.zeros_like(steps[:1]), steps.cumsum(0)], 0)
    r = torch.angle(torch.exp(1j * (est - phi)))  # wrapped; |r| << π here
    r = r - r.mean(0, keepdim=True)
    per_line = (r * r).mean(0)  # [L]
    ms = float(per_line.mean())
    se_ms = float(per_line.std()) / math.sqrt(per_line.numel())
    return math.sqrt(ms), se_ms / (2.0 * math.sqrt(ms))


@one_torch_thread
def bench_bulk_phase(
    *,
    snr_db: _Seq[float] = (10.0, 20.0, 30.0, 40.0),
    n_z: int = 64,
    frames: int = 32,
    lines: int = 2000,
    methods: _Seq[str] = METHODS,
    seed: int = 0,
) -> dict[str, Any]:
    """Residual phase error of each method against SNR on synthetic A-lines (measured; the first-order
    prediction of :func:`predicted_residual_rms` beside it).

    ``lines`` A-lines of ``n_z`` pixels of static fully developed speckle, white circular Gaussian
    noise at each SNR, a uniform random bulk phase per frame and A-line; mask ``all``. Returns a
    JSON-ready dict with one row per (SNR, method): measured RMS (rad) with its standard error,
    prediction, ratio, seconds.
    """

    # one SNR's A-lines at once: speckle, noise and phasors in complex128, the complex64 lines and the
    # methods' phase differences (about 8 complex128 copies of [T, L, Z])
    check_bench(
        "torchdoct bench bulk-phase",
        8 * 16 * int(frames) * int(lines) * int(n_z),
        f"{frames} frames × {lines} A-lines × {n_z} depths per SNR",
        "give fewer --lines, --depth or --frames",
    )
    rows = []
    for k, snr in enumerate(snr_db):
        x, phi = _synthetic(lines, n_z, frames, snr, seed + k)
        pred = predicted_residual_rms(snr, n_z, frames)
        for m in methods:
            t0 = time.perf_counter()
            steps, _ = phase_steps(x, m)
            dt = time.perf_counter() - t0
            rms, se = residual_rms(steps, phi)
            rows.append(
                {
                    "snr_db": float(snr),
                    "method": m,
                    "residual_rms_rad": rms,
                    "se_rad": se,
                    "predicted_rms_rad": pred,
                    "ratio": rms / pred,
                    "seconds": dt,
                }
            )
    return {
        "benchmark": "bulk-phase",
        "n_z": int(n_z),
        "frames": int(frames),
        "lines": int(lines),
        "seed": int(seed),
        "model": "static fully developed speckle, white circular Gaussian noise, uniform random bulk phase per "
        "frame and A-line; residual = RMS over frames about the A-line's mean, mask all",
        "rows": rows,
        "machine": machine_info(),
    }


@one_torch_thread
def bench_bulk_phase_phantom(
    phantom: str = "vessel-slab",
    *,
    snr_db: _Seq[float] = (20.0, 30.0, 40.0),
    methods: _Seq[str] = METHODS,
    masks: _Seq[str] = ("all", "median", "stable", "stable:0.1"),
    seed: int = 1,
) -> dict[str, Any]:
    """Residual phase error on a rendered phantom with moving regions (measured, never asserted).

    The phantom (a shipped name or a file, :func:`torchdoct.load_phantom`) is rendered once with
    ``seed``; white circular Gaussian noise ``snr_db`` below the mean intensity of its static pixels
    (label ``static``) and a uniform random bulk phase per frame and A-line (0 at the first frame) are
    added; every method × mask estimates it. Per row: the RMS residual over frames about each A-line's
    mean (rad), and the mean change of ``g1_4`` in the static pixels against the field without bulk
    motion, in units of the standard error of that mean (``g1_4_static_z``).
    """
    from ..image.phantom import MOTION_CODES, load_phantom
    from ..image.render import render
    from ..sim.signature import signature

    ph = load_phantom(phantom)
    res = render(ph, seed=int(seed), threads=1)
    field = res.data[0].to(torch.complex128)  # [T, (Y), Z, X]
    if field.ndim != 3:
        raise ValueError(f"phantom {phantom!r} renders a volume; the bulk-phase benchmark takes a B-scan phantom")
    labels = torch.from_numpy(np.asarray(res.labels))
    static = labels == MOTION_CODES["static"]
    if not bool(static.any()):
        raise ValueError(f"phantom {phantom!r} has no static pixels to set the SNR by")
    p_static = float((field.real**2 + field.imag**2).mean(0)[static].mean())
    meta = res.metadata()
    times = list(meta["frame_times_s"])
    n_t, _, n_x = field.shape

    def g1_4(e: torch.Tensor) -> torch.Tensor:
        return signature(e.movedim(0, -1).to(torch.complex64), times, names=("g1_4",))[1][..., 0]

    rows = []
    for k, snr in enumerate(snr_db):
        g = torch.Generator().manual_seed(int(seed) * 1000 + k)
        noise = torch.complex(
            torch.randn(*field.shape, generator=g, dtype=torch.float64),
            torch.randn(*field.shape, generator=g, dtype=torch.float64),
        )
        truth = field + noise * noise_sigma(p_static, float(snr))
        phi = (torch.rand(n_t, n_x, generator=g, dtype=torch.float64) * 2 - 1) * math.pi
        phi[0] = 0.0
        data = (truth * torch.exp(1j * phi)[:, None, :]).to(torch.complex64)
        seq = SequenceData(data=data.numpy(), meta=meta, source=f"{phantom} (rendered)")
        ref = g1_4(truth)[static]
        se = float(ref.std()) / math.sqrt(ref.numel())
        for m in methods:
            for mask in masks:
                t0 = time.perf_counter()
                bp = estimate_bulk_phase(seq, m, mask=mask)
                dt = time.perf_counter() - t0
                r = torch.angle(torch.exp(1j * (torch.from_numpy(bp.phase) - phi)))
                r = r - r.mean(0, keepdim=True)
                corr = torch.from_numpy(corrected_sequence(seq, bp).data)
                dz = float((g1_4(corr)[static] - ref).mean()) / se
                rows.append(
                    {
                        "snr_db": float(snr),
                        "method": m,
                        "mask": bp.meta()["mask"],
                        "residual_rms_rad": float(torch.sqrt((r * r).mean())),
                        "g1_4_static_z": dz,
                        "seconds": dt,
                    }
                )
    return {
        "benchmark": "bulk-phase-phantom",
        "phantom": phantom,
        "seed": int(seed),
        "shape": list(field.shape),
        "model": "rendered phantom + white noise relative to its static pixels' mean intensity + uniform random "
        "bulk phase per frame and A-line; residual = RMS over frames about the A-line's mean",
        "rows": rows,
        "machine": machine_info(),
    }


def format_bench_bulk_phase(res: dict[str, Any]) -> str:
    """The table of :func:`bench_bulk_phase` (and of :func:`bench_bulk_phase_phantom` under ``"phantom"``) as text."""
    out = [
        f"bulk-phase residual, {res['lines']} A-lines × {res['n_z']} depth pixels × {res['frames']} frames",
        f"{'SNR dB':>7}  {'method':>14}  {'residual rad':>13}  {'± SE':>8}  {'predicted':>10}  {'ratio':>6}",
    ]
    for r in res["rows"]:
        out.append(
            f"{r['snr_db']:7.0f}  {r['method']:>14}  {r['residual_rms_rad']:13.5f}  {r['se_rad']:8.5f}  "
            f"{r['predicted_rms_rad']:10.5f}  {r['ratio']:6.3f}"
        )
    ph = res.get("phantom")
    if ph:
        out.append(
            f"rendered phantom {ph['phantom']} {ph['shape']} (seed {ph['seed']}): residual, and the static "
            "pixels' mean g1_4 change in SE"
        )
        out.append(f"{'SNR dB':>7}  {'method':>14}  {'mask':>11}  {'residual rad':>13}  {'g1_4 z':>7}")
        for r in ph["rows"]:
            out.append(
                f"{r['snr_db']:7.0f}  {r['method']:>14}  {r['mask']:>11}  {r['residual_rms_rad']:13.5f}  "
                f"{r['g1_4_static_z']:7.2f}"
            )
    return "\n".join(out)
