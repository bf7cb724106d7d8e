"""Fused float32 kernels of the point simulator: a compiled library and its bit-identical torch reference.

Two kernels carry almost all the work of the paper's cells: the random walk on the periodic cell
(pure diffusion) and the evaluation of straight paths (random-ballistic motion and flow). Each is
written twice, as the same sequence of IEEE-754 float32 operations:

* in C (``_kernel.c``, compiled when the package is installed; imported from a source checkout, it is
  built once with the system's C compiler into the user cache, ``~/.cache/torchdoct`` or
  ``$TORCHDOCT_CACHE``): one pass over each scatterer and frame, nothing stored in between;
* in torch (this module): the reference, used when the compiled library is absent
  (``TORCHDOCT_KERNEL=torch`` forces it; 20-40 times slower), and by the tests, which check that both
  give the same bits.

What makes the two agree to the last bit:

* the elementary functions are polynomials with fixed float32 constants, not the platform's
  ``exp``/``sin``/``cos`` (whose last bits differ between libraries and CPUs): ``exp`` by
  ``2^k·P₇(r)``, ``sin``/``cos`` of ``2π·t`` with ``t`` in turns (quadrant reduction, Taylor
  polynomials of degree 9/10), ``log`` by the ``atanh`` series; accuracy about 2 ulp (tested);
* no fused multiply-add and no reassociation: the library is built with ``-ffp-contract=off``; the
  torch code never uses ``addcmul`` or ``alpha``;
* each field term ``amp·cos`` / ``amp·sin`` is quantized to 2⁻³⁰ and summed in 64-bit integers,
  which is exact, so the order of the sum (vector lanes, trial layout) cannot change a bit.
  The quantization error (≤ 2⁻³¹ per term, 5·10⁻¹⁰) is far below float32's resolution of the sum.

Random numbers: the normals of the walk at frame ``f`` along axis ``c`` come from SplitMix64
(Steele, Lea & Flood 2014) at index ``f·2³² + c·2³⁰ + p`` of a 64-bit key drawn from the block's
generator, two per index by Box–Muller (``u₁`` with 23 bits, so |z| ≤ 5.8; P(|z| > 5.8) ≈ 7·10⁻⁹
under a true normal); the paths of random-ballistic motion and flow take 24-bit uniforms from
SplitMix64 at (stream, trial, slot, component). Any number can be recomputed from its counter alone,
so no draw depends on how many others are made, on the chunk or on the thread.

Phases are in turns (``q = 2n/λ`` turns per µm of depth: the paper's ``2kn``/2π).

PSF: the exponent is ``−a_lat·(x² + ry·y²) − a_ax·z²`` with ``a_lat = 1/(2s_x²)``, ``ry = s_x²/s_y²``
and ``a_ax = 1/(2s_z²)``; ``ry = 1`` (the isotropic lateral PSF) gives the same bits as ``x² + y²``.
Truncation: amplitudes are 0 below ``log_tol``; with the taper (:func:`taper_constants`) the amplitude
above it is multiplied by the window :func:`taper_weights` of the exponent (physics.md §5.9).

Kept whole (over 800 lines): each kernel is written twice, in C and in torch, as the same float32
operation sequence; keeping both references beside the loader and the shared polynomial helpers is what
lets a reader check them against each other line by line.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
import warnings
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

__all__ = [
    "compiled",
    "backend",
    "exp_neg",
    "sincos_turns",
    "log_pos",
    "normals",
    "walk_periodic",
    "eval_straight",
    "uniforms24",
    "uniform_cell",
    "drift_paths",
    "path_fields",
    "sums_to_field",
    "QUANT_SCALE",
    "taper_weights",
    "taper_constants",
]

_F32 = torch.float32
#: Field terms are quantized to 2^-30 before the exact integer sum.
QUANT_SCALE = 2.0**30
_h = float.fromhex  # the C source writes the same constants as hex literals
_RINT_MAGIC = 12582912.0  # 1.5·2^23
_EXP_FLOOR = -87.0
_LOG2E, _LN2_HI, _LN2_LO = _h("0x1.715476p+0"), _h("0x1.62e4p-1"), _h("0x1.7f7d1cp-20")
_EXP_C = (
    _h("0x1.a01a02p-13"),
    _h("0x1.6c16c2p-10"),
    _h("0x1.111112p-7"),
    _h("0x1.555556p-5"),
    _h("0x1.555556p-3"),
    0.5,
    1.0,
    1.0,
)
_TWO_PI = _h("0x1.921fb6p+2")
_SIN_C = (_h("0x1.71de3ap-19"), -_h("0x1.a01a02p-13"), _h("0x1.111112p-7"), -_h("0x1.555556p-3"))
_COS_C = (-_h("0x1.27e4fcp-22"), _h("0x1.a01a02p-16"), -_h("0x1.6c16c2p-10"), _h("0x1.555556p-5"), -0.5)
_LOG_C = (_h("0x1.c71c72p-4"), _h("0x1.24924ap-3"), _h("0x1.99999ap-3"), _h("0x1.555556p-2"))
_LN2, _SQRT2 = _h("0x1.62e43p-1"), _h("0x1.6a09e6p+0")
_M64 = (1 << 64) - 1


# ---------------------------------------------------------------------------------------------
# the compiled library


#: Compiler flags of the library (setup.py uses the same): every multiply and add a separate IEEE
#: operation, as in the torch reference.
CFLAGS = ("-O3", "-ffp-contract=off", "-fno-math-errno", "-fno-trapping-math", "-std=c11")
#: Tried first: GCC then ends vector loops with masked vectors instead of scalar iterations.
OPTIONAL_CFLAGS = ("--param=vect-partial-vector-usage=2",)


def _cache_dir() -> Path:
    base = os.environ.get("TORCHDOCT_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "torchdoct"
    )
    return Path(base)


def _build_from_source() -> Path | None:
    """The library built from ``_kernel.c`` with the system's C compiler into the user cache (once per
    source and compiler; written to a temporary name and renamed, so concurrent processes are safe).
    Used when the package was not built by ``pip install`` (a source checkout on ``sys.path``)."""
    src = Path(__file__).with_name("_kernel.c")
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if cc is None or not src.is_file():
        return None
    flags = [*CFLAGS, "-DTORCHDOCT_NO_PYTHON", "-shared", "-fPIC"]
    digest = hashlib.sha256(src.read_bytes() + " ".join([cc, *flags, *OPTIONAL_CFLAGS]).encode()).hexdigest()[:16]
    out = _cache_dir() / f"kernel-{digest}.so"
    if out.is_file():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=out.parent)
    os.close(fd)
    for extra in (list(OPTIONAL_CFLAGS), []):
        try:
            subprocess.run(
                [cc, *flags, *extra, str(src), "-o", tmp, "-lm"], check=True, capture_output=True, timeout=300
            )
            os.replace(tmp, out)
            return out
        except (OSError, subprocess.SubprocessError):
            continue
    Path(tmp).unlink(missing_ok=True)
    return None


@lru_cache(maxsize=1)
def _library():
    """The compiled library (ctypes): the installed extension, else one built from source into the
    user cache; None (the torch reference) when neither exists or ``TORCHDOCT_KERNEL=torch``."""
    if os.environ.get("TORCHDOCT_KERNEL", "").strip().lower() == "torch":
        return None
    from importlib.util import find_spec

    spec = find_spec("torchdoct.sim._kernel")
    path = spec.origin if spec is not None and spec.origin else None
    lib = None
    for candidate in ([path] if path else []) + ["build"]:
        try:
            if candidate == "build":
                candidate = _build_from_source()
                if candidate is None:
                    break
            lib = ctypes.CDLL(str(candidate))
            break
        except OSError:
            continue
    if lib is None:
        warnings.warn(
            "torchdoct's compiled kernel is not available (no built extension and no C compiler to "
            "build it); the torch reference gives the same numbers, 20-40 times more slowly. Install "
            "a C compiler (gcc or clang) and reinstall (`pip install .`) to build it.",
            RuntimeWarning,
            stacklevel=3,
        )
        return None
    p, i64, i32, u64, f32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int32, ctypes.c_uint64, ctypes.c_float
    lib.tdk_exp_neg.argtypes = [i64, p, p]
    lib.tdk_sincos_turns.argtypes = [i64, p, p, p]
    lib.tdk_log_pos.argtypes = [i64, p, p]
    lib.tdk_normals.argtypes = [u64, i64, i32, i64, p]
    lib.tdk_walk_periodic.argtypes = [i64, i32, p, p, u64, i32, p, p, p, i32, p, p, p, i32, p, p, f32, f32, f32, p]
    lib.tdk_walk_periodic.restype = ctypes.c_int
    lib.tdk_eval_straight.argtypes = [i32, i64, p, p, p, p, p, i32, p, f32, f32, f32, p]
    lib.tdk_taper.argtypes = [i64, p, f32, f32, p]
    f64 = ctypes.c_double
    lib.tdk_drift_paths.argtypes = [i32, p, p, p, p, p, i32, p, p, f64, f64, i64, i64, p, p, p, p]
    lib.tdk_drift_paths.restype = ctypes.c_int
    lib.tdk_path_fields.argtypes = [i32, i64, p, p, p, i64, i64, i32, p, p, p, p, i32, p, f32, f32, f32, p]
    lib.tdk_path_fields.restype = ctypes.c_int
    lib.tdk_uniform_cell.argtypes = [u64, i64, p, p]
    lib.tdk_uniform_cell.restype = None
    for name in ("tdk_exp_neg", "tdk_sincos_turns", "tdk_log_pos", "tdk_normals", "tdk_eval_straight", "tdk_taper"):
        getattr(lib, name).restype = None
    return lib


def compiled() -> bool:
    """Whether the compiled kernel is in use (else the torch reference, with the same results)."""
    return _library() is not None


def backend() -> str:
    """``"compiled"`` or ``"torch"``: which implementation computes (the numbers are the same)."""
    return "compiled" if compiled() else "torch"


def _use_c(force_torch: bool):
    return None if force_torch else _library()


def _f32(x: torch.Tensor) -> torch.Tensor:
    return x.detach().to(device="cpu", dtype=_F32).contiguous()


def _ptr(x: torch.Tensor) -> int:
    return x.data_ptr()


def _c_elementwise(fn, x: torch.Tensor, n_out: int) -> tuple[torch.Tensor, ...]:
    """``fn(n, x, out…)`` of the library on a contiguous float32 ``x``: the ``n_out`` outputs."""
    outs = tuple(torch.empty_like(x) for _ in range(n_out))
    fn(x.numel(), _ptr(x), *(_ptr(o) for o in outs))
    return outs


# ---------------------------------------------------------------------------------------------
# the reference in torch (float32, CPU): every line is one IEEE operation of the C code


def _sqrt(x: torch.Tensor) -> torch.Tensor:
    """Correctly rounded square root (torch's vectorized ``sqrt`` may miss by one ulp; NumPy's is the
    IEEE operation, as in the C code)."""
    return torch.from_numpy(np.sqrt(x.contiguous().numpy()))


def _rint(x: torch.Tensor) -> torch.Tensor:
    return (x + _RINT_MAGIC) - _RINT_MAGIC


def _horner(x: torch.Tensor, coef: tuple[float, ...]) -> torch.Tensor:
    p = torch.full_like(x, coef[0])
    for c in coef[1:]:
        p = p * x + c
    return p


def exp_neg(x: torch.Tensor, *, force_torch: bool = False) -> torch.Tensor:
    """``exp(x)`` for ``x ≤ 0`` (float32; clamped at −87): ``x = k·ln2 + r``, Taylor polynomial of degree 7."""
    x = _f32(x)
    lib = _use_c(force_torch)
    if lib is not None:
        return _c_elementwise(lib.tdk_exp_neg, x, 1)[0]
    x = torch.clamp(x, min=_EXP_FLOOR)
    k = _rint(x * _LOG2E)
    r = (x - k * _LN2_HI) - k * _LN2_LO
    scale = ((k.to(torch.int32) + 127) << 23).view(_F32)
    return _horner(r, _EXP_C) * scale


def sincos_turns(t: torch.Tensor, *, force_torch: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """``(sin 2πt, cos 2πt)`` for ``t`` in turns (float32, |t| < 2²⁰)."""
    t = _f32(t)
    lib = _use_c(force_torch)
    if lib is not None:
        sin, cos = _c_elementwise(lib.tdk_sincos_turns, t, 2)
        return sin, cos
    n = _rint(t * 4.0)
    a = (t - n * 0.25) * _TWO_PI
    a2 = a * a
    s = _horner(a2, _SIN_C) * a2
    s = s * a
    s = s + a
    c = _horner(a2, _COS_C) * a2 + 1.0
    q = n.to(torch.int32) & 3
    sn = torch.where(q == 0, s, torch.where(q == 1, c, torch.where(q == 2, -s, -c)))
    cs = torch.where(q == 0, c, torch.where(q == 1, -s, torch.where(q == 2, -c, s)))
    return sn, cs


def log_pos(u: torch.Tensor, *, force_torch: bool = False) -> torch.Tensor:
    """``log(u)`` for normal positive float32 ``u`` (the ``atanh`` series of ``m ∈ [√½, √2)``)."""
    u = _f32(u)
    lib = _use_c(force_torch)
    if lib is not None:
        return _c_elementwise(lib.tdk_log_pos, u, 1)[0]
    b = u.view(torch.int32)
    e = ((b >> 23) & 0xFF) - 127
    m = ((b & 0x7FFFFF) | 0x3F800000).view(_F32)
    big = m > _SQRT2
    m = torch.where(big, m * 0.5, m)
    e = torch.where(big, e + 1, e)
    f = m - 1.0
    s = f / (f + 2.0)
    s2 = s * s
    t = _horner(s2, _LOG_C) * s2
    t = t * s
    t = t + s
    return e.to(_F32) * _LN2 + t * 2.0


def taper_constants(log_tol: float, taper: bool) -> tuple[float, float]:
    """The float32 constants ``(e0, tk)`` of the taper window at tolerance ``e^log_tol``: ``e0 = a·ln tol``
    and ``tk = 1/((1 − a)·ln tol)``, ``a`` = :data:`torchdoct.conventions.TAPER_START`; ``(0, 0)`` (no
    taper: the hard truncation) when ``taper`` is false."""
    if not taper:
        return 0.0, 0.0
    from ..conventions import TAPER_START

    return (float(np.float32(TAPER_START * log_tol)), float(np.float32(1.0 / ((1.0 - TAPER_START) * log_tol))))


def taper_weights(ex: torch.Tensor, e0: float, tk: float, *, force_torch: bool = False) -> torch.Tensor:
    """The taper window (float32) of exponents ``ex`` between ``ln tol`` and 0: 1 for ``ex ≥ e0``, else
    ``1 − t³·(10 − 15t + 6t²)`` with ``t = min((ex − e0)·tk, 1)`` (constants from :func:`taper_constants`;
    :func:`torchdoct.conventions.taper_window` in float32)."""
    ex = _f32(ex)
    lib = _use_c(force_torch)
    if lib is not None:
        out = torch.empty_like(ex)
        lib.tdk_taper(ex.numel(), _ptr(ex), e0, tk, _ptr(out))
        return out
    t = (ex - e0) * tk
    t = torch.where(t < 1.0, t, torch.ones_like(t))
    t3 = (t * t) * t
    p = t * 6.0
    p = p - 15.0
    p = p * t
    p = p + 10.0
    w = 1.0 - t3 * p
    return torch.where(ex >= e0, torch.ones_like(w), w)


def _splitmix64(key: int, index: np.ndarray) -> np.ndarray:
    """SplitMix64's output at ``index`` (uint64 array) of the stream of ``key``."""
    with np.errstate(over="ignore"):
        z = np.uint64(key & _M64) + index * np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        return z ^ (z >> np.uint64(31))


def normals(key: int, frame: int, comp: int, n: int, *, force_torch: bool = False) -> torch.Tensor:
    """The standard normals (float32) of scatterers ``0 … n−1`` for ``(frame, comp)`` in the stream of
    ``key``: scatterer ``i`` takes the first (even ``i``) or second (odd ``i``) normal of pair ``i // 2``,
    Box–Muller on SplitMix64 at index ``frame·2³² + comp·2³⁰ + pair``."""
    lib = _use_c(force_torch)
    if lib is not None:
        out = torch.empty(n, dtype=_F32)
        lib.tdk_normals(key & _M64, frame, comp, n, _ptr(out))
        return out
    pairs = (n + 1) // 2
    base = (np.uint64(frame) << np.uint64(32)) | (np.uint64(comp) << np.uint64(30))
    h = _splitmix64(key, base + np.arange(pairs, dtype=np.uint64))
    u1 = (torch.from_numpy((h >> np.uint64(41)).astype(np.int32)).to(_F32) + 0.5) * 2.0**-23
    u2 = torch.from_numpy((h & np.uint64(0xFFFFFF)).astype(np.int32)).to(_F32) * 2.0**-24
    r = _sqrt(log_pos(u1, force_torch=True) * -2.0)
    sn, cs = sincos_turns(u2, force_torch=True)
    return torch.stack([r * cs, r * sn], dim=1).reshape(-1)[:n]


def _block_normals(key: int, frame: int, M: int, *, force_torch: bool = False) -> torch.Tensor:
    """The walk's normals [3, M] of a block's scatterers at ``frame`` (as :func:`walk_periodic` draws them)."""
    return torch.stack([normals(key, frame, c, M, force_torch=force_torch) for c in range(3)])


def _quantize(v: torch.Tensor) -> torch.Tensor:
    y = v * QUANT_SCALE
    return torch.where(y.abs() < 4194304.0, _rint(y), y).to(torch.int32).to(torch.int64)


def sums_to_field(acc: torch.Tensor) -> torch.Tensor:
    """Exact integer sums ``[..., 2]`` (units of 2⁻³⁰) → complex64 field."""
    v = (acc.to(torch.float64) * (1.0 / QUANT_SCALE)).to(_F32)
    return torch.complex(v[..., 0], v[..., 1])


# ---------------------------------------------------------------------------------------------
# the two kernels


def walk_periodic(
    pos: torch.Tensor,
    counts: torch.Tensor,
    key: int,
    sigmas: list[float],
    L: tuple[float, ...],
    groups: list[tuple[float, ...]],
    group_of: list[int],
    q_turns: list[float],
    log_tol: float,
    *,
    taper: bool = False,
    force_torch: bool = False,
) -> torch.Tensor:
    """Pure diffusion on the periodic cell for one block of trials, float32 (physics.md §5.1).

    ``pos`` [3, M] (µm, component-major; updated in place): the scatterers of the block, laid out
    trial after trial (``counts`` [trials] each). Frame ``f ≥ 1`` moves scatterer ``i`` by
    ``sigmas[f−1]·z`` along axis ``c`` (``z`` = :func:`normals` of ``(key, f, c)`` at ``i``), then wraps
    it back into the cell ``|x_c| ≤ L_c/2``. For each PSF group ``(a_lat, a_ax[, ry]) = (1/(2s_x²),
    1/(2s_z²)[, s_x²/s_y²])`` (``ry`` 1 when left out) the amplitude is ``exp(−a_lat·(x² + ry·y²) − a_ax·z²)``,
    0 where the exponent is below ``log_tol``, times the window :func:`taper_weights` of the exponent if ``taper``;
    system ``s`` (group ``group_of[s]``) adds ``amp·e^{i·2π·q_turns[s]·z}``.
    Returns the exact sums [trials, S, T, 2] (int64, units of 2⁻³⁰; :func:`sums_to_field`).
    """
    M = pos.shape[1]
    nt = counts.numel()
    S, G, T = len(q_turns), len(groups), len(sigmas) + 1
    ry = [float(g[2]) if len(g) > 2 else 1.0 for g in groups]
    e0, tk = taper_constants(log_tol, taper)
    lib = _use_c(force_torch)
    if lib is not None:
        assert pos.dtype == _F32 and pos.is_contiguous() and pos.device.type == "cpu"
        cnt = counts.to(device="cpu", dtype=torch.int64).contiguous()
        acc = torch.empty(nt, S, T, 2, dtype=torch.int64)
        arr = lambda v, dt=_F32: torch.tensor(v, dtype=dt)  # noqa: E731
        sg, Lt, iLt = arr(sigmas or [0.0]), arr(list(L)), arr([1.0 / x for x in L])
        al, az, ryt = arr([g[0] for g in groups]), arr([g[1] for g in groups]), arr(ry)
        go, qt = arr(group_of, torch.int32), arr(q_turns)
        rc = lib.tdk_walk_periodic(
            M,
            nt,
            _ptr(cnt),
            _ptr(pos),
            key & _M64,
            T,
            _ptr(sg),
            _ptr(Lt),
            _ptr(iLt),
            G,
            _ptr(al),
            _ptr(az),
            _ptr(ryt),
            S,
            _ptr(go),
            _ptr(qt),
            log_tol,
            e0,
            tk,
            _ptr(acc),
        )
        if rc != 0:
            raise MemoryError(f"the periodic walk could not allocate scratch memory for {M} scatterers")
        return acc
    seg = torch.repeat_interleave(torch.arange(nt), counts.to("cpu"), output_size=M)
    acc = torch.zeros(nt, S, T, 2, dtype=torch.int64)
    Lv = torch.tensor(L, dtype=_F32).view(3, 1)
    iLv = torch.tensor([1.0 / x for x in L], dtype=_F32).view(3, 1)
    log_tol32 = float(np.float32(log_tol))
    for f in range(T):
        if f > 0:
            z = _block_normals(key, f, M, force_torch=True)
            v = pos + z * float(np.float32(sigmas[f - 1]))
            w = _rint(v * iLv)
            pos.copy_(v - w * Lv)
        px, py, pz = pos
        for g, grp in enumerate(groups):
            al32, az32, ry32 = float(np.float32(grp[0])), float(np.float32(grp[1])), float(np.float32(ry[g]))
            r2 = px * px + py * py if ry32 == 1.0 else px * px + (py * py) * ry32
            ex = r2 * (-al32) - (pz * pz) * az32
            amp = exp_neg(ex, force_torch=True)
            if tk != 0.0:
                amp = amp * taper_weights(ex, e0, tk, force_torch=True)
            amp = torch.where(ex >= log_tol32, amp, torch.zeros_like(ex))
            for s in range(S):
                if group_of[s] != g:
                    continue
                sn, cs = sincos_turns(pz * float(np.float32(q_turns[s])), force_torch=True)
                acc[:, s, f, 0].index_add_(0, seg, _quantize(amp * cs))
                acc[:, s, f, 1].index_add_(0, seg, _quantize(amp * sn))
    return acc


def eval_straight(
    e: torch.Tensor,
    a2: torch.Tensor,
    t_star: torch.Tensor,
    phi_turns: torch.Tensor,
    omega_turns: torch.Tensor,
    times: torch.Tensor,
    log_tol: float,
    *,
    taper: bool = False,
    force_torch: bool = False,
) -> torch.Tensor:
    """Straight paths, float32 (physics.md §5.1): for each trial (row) and path (column) of the
    [N, C] coefficients, the PSF exponent ``e + a2·τ²`` and the phase ``φ + ω·τ`` (turns) at
    ``τ = t − t*``; the path adds ``exp(exponent)·e^{i·2π·phase}`` (times the window :func:`taper_weights` of
    the exponent if ``taper``) at the frames where the exponent is at least ``log_tol``. Returns the
    exact sums [N, T, 2] (int64, units of 2⁻³⁰)."""
    e, a2, t_star, phi_turns, omega_turns, tt = (_f32(x) for x in (e, a2, t_star, phi_turns, omega_turns, times))
    N, C = e.shape
    T = tt.numel()
    log_tol32 = float(np.float32(log_tol))
    e0, tk = taper_constants(log_tol, taper)
    lib = _use_c(force_torch)
    if lib is not None:
        acc = torch.empty(N, T, 2, dtype=torch.int64)
        lib.tdk_eval_straight(
            N,
            C,
            _ptr(e),
            _ptr(a2),
            _ptr(t_star),
            _ptr(phi_turns),
            _ptr(omega_turns),
            T,
            _ptr(tt),
            log_tol32,
            e0,
            tk,
            _ptr(acc),
        )
        return acc
    acc = torch.zeros(N, T, 2, dtype=torch.int64)
    rows = max(1, (1 << 20) // max(1, C * T))
    for r0 in range(0, N, rows):
        sl = slice(r0, r0 + rows)
        tau = tt.view(1, 1, T) - t_star[sl, :, None]
        ex = (tau * tau) * a2[sl, :, None] + e[sl, :, None]
        keep = (ex >= log_tol32) & (e[sl, :, None] >= log_tol32)
        amp = exp_neg(ex, force_torch=True)
        if tk != 0.0:
            amp = amp * taper_weights(ex, e0, tk, force_torch=True)
        amp = torch.where(keep, amp, torch.zeros_like(ex))
        sn, cs = sincos_turns(tau * omega_turns[sl, :, None] + phi_turns[sl, :, None], force_torch=True)
        acc[sl, :, 0] = _quantize(amp * cs).sum(1)
        acc[sl, :, 1] = _quantize(amp * sn).sum(1)
    return acc


# ---------------------------------------------------------------------------------------------
# straight paths: drawn from their own counter-based uniforms, then evaluated

_FAR = 1.0e6
_F64 = torch.float64
_THIRD32 = _h("0x1.555556p-2")


def uniforms24(keys: np.ndarray, stream: int, trial: np.ndarray, slot: np.ndarray, comp: int) -> torch.Tensor:
    """Uniforms on [0, 1) with 24 bits (float32): SplitMix64 of ``keys`` at the counter
    ``stream·2⁵⁶ + trial·2⁴⁸ + slot·2⁸ + comp`` (arrays broadcast; ``trial`` is the trial within its
    block of 64)."""
    idx = (
        (np.uint64(stream) << np.uint64(56))
        | (trial.astype(np.uint64) << np.uint64(48))
        | (slot.astype(np.uint64) << np.uint64(8))
        | np.uint64(comp)
    )
    with np.errstate(over="ignore"):
        z = keys.astype(np.uint64) + idx * np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    return torch.from_numpy((z >> np.uint64(40)).astype(np.int32)).to(_F32) * 2.0**-24


def uniform_cell(key: int, M: int, half: tuple[float, float, float], *, force_torch: bool = False) -> torch.Tensor:
    """Positions [3, M] (float32, µm) uniform in the cell ``|x_c| ≤ half[c]``: ``(2u − 1)·half[c]`` with
    ``u`` = :func:`uniforms24` of ``key`` at (stream 6, axis c, scatterer i)."""
    lib = _use_c(force_torch)
    if lib is not None:
        out = torch.empty(3, M, dtype=_F32)
        h = torch.tensor(half, dtype=_F32)
        lib.tdk_uniform_cell(key & _M64, M, _ptr(h), _ptr(out))
        return out
    kb = np.array([[key & _M64]], dtype=np.uint64)
    u = uniforms24(kb, 6, np.arange(3)[:, None], np.arange(M)[None, :], 0)
    return (u * 2.0 - 1.0) * torch.tensor(half, dtype=_F32).view(3, 1)


def _direction(law: int, u0: torch.Tensor, u1: torch.Tensor) -> tuple[torch.Tensor, ...]:
    if law == 0:
        mu = 2.0 * u0.double() - 1.0
    else:
        mu = sincos_turns(u0 * 0.5, force_torch=True)[1].double()
    st2 = 1.0 - mu * mu
    st = _sqrt(torch.where(st2 > 0.0, st2, torch.zeros_like(st2)))
    sp, cp = sincos_turns(u1, force_torch=True)
    return st * cp.double(), st * sp.double(), mu


def _velocity(ctx, stream: int, slot: np.ndarray) -> list[torch.Tensor]:
    keys, tb, flow, ballistic = ctx
    v = [torch.full(np.broadcast_shapes(tb.shape, slot.shape), float(f), dtype=_F64) for f in flow]
    for k, (speed, law) in enumerate(ballistic):
        d = _direction(law, uniforms24(keys, stream, tb, slot, 2 * k), uniforms24(keys, stream, tb, slot, 2 * k + 1))
        v = [v[i] + speed * d[i] for i in range(3)]
    return v


def _cbrt_unit(u: torch.Tensor) -> torch.Tensor:
    y = exp_neg(
        log_pos(torch.where(u == 0.0, torch.ones_like(u), u), force_torch=True) * _THIRD32, force_torch=True
    ).double()
    ud = u.double()
    for _ in range(2):
        y2 = y * y
        y = y - (y2 * y - ud) / (y2 * 3.0)
    return torch.where(u == 0.0, torch.zeros_like(y), y)


def drift_paths(
    keys: list[int],
    n0: torch.Tensor,
    n_prop: torch.Tensor,
    H: tuple[float, float, float],
    flow: tuple[float, float, float],
    ballistic: list[tuple[float, int]],
    w_max: float,
    T: float,
    E: int,
    *,
    force_torch: bool = False,
):
    """Straight paths of a population for trials ``N = 64·len(keys)`` (physics.md §5.1, sampler in
    :mod:`torchdoct.sim.plan`): ``n0`` initial paths uniform in the ellipsoid of half-axes ``H`` (µm) at
    ``t = 0``, and the entrants among ``n_prop`` proposals (velocity kept with probability
    ``|v/H|/w_max``, entering through the ellipsoid's surface at a time uniform on [0, T] s).
    Velocities: ``flow`` + Σ ``speed·direction`` over ``ballistic`` = [(speed µm/s, law 0 isotropic /
    1 uniform angles)]. Every number comes from :func:`uniforms24` of the block's key at (stream,
    trial, slot, component), so no draw depends on another trial or on the counts.

    Returns ``p``, ``v`` [3, N, C] (float64, µm and µm/s; unused slots far away and still), ``t_ref``
    [N, C] (s) and the count per trial; C is the largest count. Raises ``OverflowError`` with the trial
    when the accepted entrants exceed ``E``."""
    N = n0.numel()
    n0c = n0.to("cpu", torch.int64).contiguous()
    npc = n_prop.to("cpu", torch.int64).contiguous()
    lib = _use_c(force_torch)
    if lib is not None:
        cap = int(n0c.max()) + (min(E, int(npc.max())) if N else 0)
        cap = max(cap, 1)
        p = torch.empty(3, N, cap, dtype=_F64)
        v = torch.empty(3, N, cap, dtype=_F64)
        t_ref = torch.empty(N, cap, dtype=_F64)
        count = torch.empty(N, dtype=torch.int64)
        ku = torch.tensor(np.array(keys, dtype=np.uint64).view(np.int64))
        speeds = torch.tensor([b[0] for b in ballistic] or [0.0], dtype=_F64)
        laws = torch.tensor([b[1] for b in ballistic] or [0], dtype=torch.int32)
        Ht, ft = torch.tensor(H, dtype=_F64), torch.tensor(flow, dtype=_F64)
        rc = lib.tdk_drift_paths(
            N,
            _ptr(ku),
            _ptr(n0c),
            _ptr(npc),
            _ptr(Ht),
            _ptr(ft),
            len(ballistic),
            _ptr(speeds),
            _ptr(laws),
            float(w_max),
            float(T),
            int(E),
            cap,
            _ptr(p),
            _ptr(v),
            _ptr(t_ref),
            _ptr(count),
        )
        if rc < 0:
            raise MemoryError(
                f"the straight-path sampler could not allocate scratch memory for {int(npc.max())} proposals"
            )
        if rc > 0:
            raise OverflowError(rc - 1)
        C = max(1, int(count.max()))
        return p[:, :, :C], v[:, :, :C], t_ref[:, :C], count
    kb = np.repeat(np.array(keys, dtype=np.uint64), 64)[:N, None]
    tb = (np.arange(N) % 64)[:, None]
    ctx = (kb, tb, flow, ballistic)
    # initial paths
    m0 = max(1, int(n0c.max()))
    j = np.arange(m0)[None, :]
    valid0 = torch.arange(m0)[None, :] < n0c[:, None]
    dx = _direction(0, uniforms24(kb, 1, tb, j, 0), uniforms24(kb, 1, tb, j, 1))
    r = _cbrt_unit(uniforms24(kb, 1, tb, j, 2))
    p0 = [torch.where(valid0, (dx[i] * r) * H[i], torch.full_like(r, _FAR)) for i in range(3)]
    v0 = [torch.where(valid0, x, torch.zeros_like(x)) for x in _velocity(ctx, 2, j)]
    # entrants
    mp = max(1, int(npc.max()))
    j = np.arange(mp)[None, :]
    vel = _velocity(ctx, 3, j)
    w = [vel[i] / H[i] for i in range(3)]
    wn = _sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    accept = (uniforms24(kb, 4, tb, j, 0).double() * w_max < wn) & (torch.arange(mp)[None, :] < npc[:, None])
    n_acc = accept.sum(1)
    if N and int(n_acc.max()) > E:
        raise OverflowError(int(torch.nonzero(n_acc > E)[0, 0]))
    nx, ny, nz = (x / wn for x in w)
    sgn = torch.where(nz >= 0.0, 1.0, -1.0).to(_F64)
    a = -1.0 / (sgn + nz)
    bb = nx * ny * a
    e1 = (1.0 + sgn * nx * nx * a, sgn * bb, -sgn * nx)
    e2 = (bb, sgn + ny * ny * a, -ny)
    g0, g1, g2 = (uniforms24(kb, 5, tb, j, c) for c in range(3))
    rad, depth = _sqrt(g0.double()), _sqrt(1.0 - g0.double())
    s, c = sincos_turns(g1, force_torch=True)
    c1, c2 = rad * c.double(), rad * s.double()
    pe = [((c1 * e1[i] + c2 * e2[i]) - depth * (nx, ny, nz)[i]) * H[i] for i in range(3)]
    te = g2.double() * T
    count = n0c + n_acc
    C = max(1, int(count.max()))
    p = torch.full((3, N, C), _FAR, dtype=_F64)
    v = torch.zeros(3, N, C, dtype=_F64)
    t_ref = torch.zeros(N, C, dtype=_F64)
    slots = torch.arange(C)[None, :]
    first = slots < n0c[:, None]
    later = (slots >= n0c[:, None]) & (slots < count[:, None])
    for i in range(3):
        p[i].masked_scatter_(first, p0[i].masked_select(valid0))
        v[i].masked_scatter_(first, v0[i].masked_select(valid0))
        p[i].masked_scatter_(later, pe[i].masked_select(accept))
        v[i].masked_scatter_(later, vel[i].masked_select(accept))
    t_ref.masked_scatter_(later, te.masked_select(accept))
    return p, v, t_ref, count


def _norm_w(al: float, az: float, ry: float, x, y, z, xx, yy, zz):
    return -(al * (x * xx + (y * yy) * ry)) - az * (z * zz)


def path_fields(
    p: torch.Tensor,
    v: torch.Tensor,
    t_ref: torch.Tensor,
    q_turns: list[float],
    a_lat: list[float],
    a_ax: list[float],
    times: torch.Tensor,
    log_tol: float,
    *,
    ry: list[float] | None = None,
    taper: bool = False,
    force_torch: bool = False,
) -> torch.Tensor:
    """Fields of straight paths ``p + v·(t − t_ref)`` ([3, N, C] float64, µm, µm/s; [N, C] s) for the
    systems ``(q_turns, a_lat, a_ax, ry)`` (2n/λ in turns per µm, 1/(2s_x²), 1/(2s_z²), s_x²/s_y²; ``ry``
    all 1 when ``None``), physics.md §5.1.

    Per path, in float64: the PSF exponent about the closest approach ``t* = t_ref + shift``,
    ``e* = −a_lat·(x*² + ry·y*²) − a_ax·z*²`` and ``a2 = −a_lat·(v_x² + ry·v_y²) − a_ax·v_z²``, the phase
    ``φ* = frac(q·z*)`` and ``ω = q·v_z`` (turns, turns/s); slots at ``x ≥ 5·10⁵ µm`` stand still.
    Rounded to float32, they go through :func:`eval_straight` (with the taper if ``taper``). Returns
    exact sums [N, S, T, 2]."""
    N, C = t_ref.shape
    S = len(q_turns)
    tt = _f32(times)
    T = tt.numel()
    ry = [1.0] * S if ry is None else [float(r) for r in ry]
    e0, tk = taper_constants(log_tol, taper)
    lib = _use_c(force_torch)
    if lib is not None:
        p, v, t_ref = (x.to("cpu", _F64) for x in (p, v, t_ref))
        # slices of a [3, N, cap] buffer are read in place: one layout for p and v, unit stride in the slots
        if not (p.stride() == v.stride() and p.stride(2) == 1 and t_ref.stride() == (p.stride(1), 1)):
            p, v, t_ref = p.contiguous(), v.contiguous(), t_ref.contiguous()
        acc = torch.empty(N, S, T, 2, dtype=torch.int64)
        qa, la, za, ra = (torch.tensor(x, dtype=_F64) for x in (q_turns, a_lat, a_ax, ry))
        rc = lib.tdk_path_fields(
            N,
            C,
            _ptr(p),
            _ptr(v),
            _ptr(t_ref),
            p.stride(0),
            p.stride(1),
            S,
            _ptr(qa),
            _ptr(la),
            _ptr(za),
            _ptr(ra),
            T,
            _ptr(tt),
            float(np.float32(log_tol)),
            e0,
            tk,
            _ptr(acc),
        )
        if rc != 0:
            raise MemoryError(f"the straight-path evaluation could not allocate scratch memory for {C} paths")
        return acc
    px, py, pz = p
    moving = px < 0.5 * _FAR
    vx, vy, vz = (torch.where(moving, x, torch.zeros_like(x)) for x in v)
    out = torch.empty(N, S, T, 2, dtype=torch.int64)
    for s in range(S):
        al, az, yr, qs = float(a_lat[s]), float(a_ax[s]), ry[s], float(q_turns[s])
        a2 = _norm_w(al, az, yr, vx, vy, vz, vx, vy, vz)
        num = _norm_w(al, az, yr, px, py, pz, vx, vy, vz)
        shift = torch.where(a2 != 0.0, -(num / torch.where(a2 != 0.0, a2, torch.ones_like(a2))), torch.zeros_like(a2))
        rx, ryy, rz = px + vx * shift, py + vy * shift, pz + vz * shift
        x = rz * qs
        out[:, s] = eval_straight(
            _norm_w(al, az, yr, rx, ryy, rz, rx, ryy, rz),
            a2,
            t_ref + shift,
            x - torch.floor(x),
            vz * qs,
            tt,
            log_tol,
            taper=taper,
            force_torch=True,
        )
    return out
