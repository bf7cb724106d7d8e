"""The fused float32 kernels (torchdoct.sim.kernel): the compiled library gives the same bits as the
torch reference, the polynomial elementary functions are accurate to a few float32 ulp, the normals of
the walk are standard normal and independent, and a whole simulation is bit-identical on either backend."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats

import torchdoct as td
from torchdoct.sim import kernel

needs_compiled = pytest.mark.skipif(not kernel.compiled(), reason="the compiled kernel was not built")


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


# ---------------------------------------------------------------------------------------------
# accuracy of the elementary functions (reference: float64 libm on the same float32 inputs)


@pytest.mark.parametrize("force_torch", [False, True])
def test_exp_is_accurate_to_two_ulp_and_exact_at_zero(force_torch):
    x = -torch.rand(200_000, generator=_gen(1)) * 80.0
    got = kernel.exp_neg(x, force_torch=force_torch).double()
    ref = torch.exp(x.double())
    assert float(((got - ref).abs() / ref).max()) <= 2 * 2.0**-23
    assert float(kernel.exp_neg(torch.zeros(1), force_torch=force_torch)) == 1.0
    # clamped far below the range used (the callers truncate at ln tol first)
    assert float(kernel.exp_neg(torch.tensor([-1e30]), force_torch=force_torch)) == pytest.approx(
        math.exp(-87), rel=1e-6
    )


@pytest.mark.parametrize("force_torch", [False, True])
def test_sincos_in_turns_is_accurate_and_exact_at_the_quadrants(force_torch):
    t = (torch.rand(200_000, generator=_gen(2)) - 0.5) * 200.0
    sn, cs = kernel.sincos_turns(t, force_torch=force_torch)
    ang = 2.0 * math.pi * t.double()  # the float32 input, exactly
    assert float((sn.double() - torch.sin(ang)).abs().max()) <= 2 * 2.0**-24
    assert float((cs.double() - torch.cos(ang)).abs().max()) <= 2 * 2.0**-24
    q = torch.tensor([0.0, 0.25, 0.5, 0.75, -0.25, 3.0])
    s, c = kernel.sincos_turns(q, force_torch=force_torch)
    assert s.tolist() == [0.0, 1.0, 0.0, -1.0, -1.0, 0.0]
    assert c.tolist() == [1.0, 0.0, -1.0, 0.0, 0.0, 1.0]


@pytest.mark.parametrize("force_torch", [False, True])
def test_log_is_accurate(force_torch):
    u = torch.rand(200_000, generator=_gen(3)) * 0.999 + 2.0**-23
    got = kernel.log_pos(u, force_torch=force_torch).double()
    ref = torch.log(u.double())
    assert float(((got - ref).abs() / ref.abs().clamp(min=1.0)).max()) <= 4 * 2.0**-24
    assert float(kernel.log_pos(torch.ones(1), force_torch=force_torch)) == 0.0


# ---------------------------------------------------------------------------------------------
# the normals of the walk


def test_normals_are_standard_normal_and_independent():
    n = 1_000_001  # odd: the spare of the last pair is dropped
    z = kernel.normals(987654321, 3, 1, n).double().numpy()
    assert z.shape == (n,)
    se = 1.0 / math.sqrt(n)
    assert abs(z.mean()) < 5 * se
    assert abs(z.var() - 1.0) < 5 * math.sqrt(2.0) * se
    assert abs((z**4).mean() - 3.0) < 5 * math.sqrt(96.0) * se
    assert abs((z**3).mean()) < 5 * math.sqrt(15.0) * se
    assert stats.kstest(z, "norm").pvalue > 1e-4
    # tails: P(|z| > 4) = 6.33e-5 (Poisson SE), and nothing beyond the 23-bit Box–Muller bound √(46 ln 2)
    k = int((np.abs(z) > 4.0).sum())
    expect = n * 2 * stats.norm.sf(4.0)
    assert abs(k - expect) < 5 * math.sqrt(expect)
    assert np.abs(z).max() <= math.sqrt(-2.0 * math.log(0.5 * 2.0**-23)) + 1e-6
    # no correlation between neighbours (the two of a pair and consecutive pairs), nor across frames
    z2 = kernel.normals(987654321, 4, 1, n).double().numpy()
    z3 = kernel.normals(987654321, 3, 2, n).double().numpy()
    for a, b in ((z[:-1:2], z[1::2]), (z[:-2], z[2:]), (z, z2), (z, z3)):
        assert abs(np.corrcoef(a, b)[0, 1]) < 5 / math.sqrt(a.size)
    # squares of the pair: Box–Muller's r² = z0² + z1² is exponential with mean 2
    r2 = z[:-1:2] ** 2 + z[1::2] ** 2
    assert stats.kstest(r2, "expon", args=(0, 2.0)).pvalue > 1e-4


def test_normals_depend_only_on_key_frame_axis_and_index():
    a = kernel.normals(5, 7, 0, 1000)
    assert torch.equal(a[:501], kernel.normals(5, 7, 0, 501))  # a prefix is the same
    assert not torch.equal(a, kernel.normals(5, 8, 0, 1000))  # another frame,
    assert not torch.equal(a, kernel.normals(5, 7, 1, 1000))  # another axis,
    assert not torch.equal(a, kernel.normals(6, 7, 0, 1000))  # another key


# ---------------------------------------------------------------------------------------------
# compiled = reference, bit for bit


@needs_compiled
def test_elementary_functions_are_bit_identical_on_both_backends():
    g = _gen(4)
    x = -torch.rand(100_003, generator=g) * 90.0
    assert torch.equal(kernel.exp_neg(x), kernel.exp_neg(x, force_torch=True))
    t = (torch.rand(100_003, generator=g) - 0.5) * 4000.0
    for a, b in zip(kernel.sincos_turns(t), kernel.sincos_turns(t, force_torch=True)):
        assert torch.equal(a, b)
    u = torch.rand(100_003, generator=g) + 2.0**-24
    assert torch.equal(kernel.log_pos(u), kernel.log_pos(u, force_torch=True))
    for M in (1, 5, 40_001):
        cell = kernel.uniform_cell(99, M, (6.0, 5.0, 7.5))
        assert torch.equal(cell, kernel.uniform_cell(99, M, (6.0, 5.0, 7.5), force_torch=True))
        assert (cell.abs() <= torch.tensor([6.0, 5.0, 7.5]).view(3, 1)).all()
    for n in (1, 2, 7, 40_001):
        assert torch.equal(kernel.normals(2**63 + 11, 5, 2, n), kernel.normals(2**63 + 11, 5, 2, n, force_torch=True))


@needs_compiled
def test_walk_is_bit_identical_on_both_backends():
    g = _gen(5)
    counts = torch.randint(0, 40, (9,), generator=g)
    counts[3] = 0  # an empty trial
    M = int(counts.sum())
    pos = ((torch.rand(3, M, generator=g) * 2 - 1) * torch.tensor([6.0, 5.0, 7.0]).view(3, 1)).contiguous()
    args = dict(
        counts=counts,
        key=1234567,
        sigmas=[0.8, 1.3, 0.2, 2.5, 0.9],
        L=(12.0, 10.0, 14.0),
        groups=[(0.1, 0.2), (0.03, 0.25)],
        group_of=[0, 1, 0],
        q_turns=[2.38, 1.53, 2.0],
        log_tol=math.log(1e-3),
    )
    p1, p2 = pos.clone(), pos.clone()
    a = kernel.walk_periodic(p1, **args)
    b = kernel.walk_periodic(p2, **args, force_torch=True)
    assert torch.equal(p1, p2)
    assert torch.equal(a, b)
    assert torch.equal(a[3], torch.zeros_like(a[3]))
    assert (p1.abs() <= torch.tensor([6.0, 5.0, 7.0]).view(3, 1)).all()  # wrapped into the cell


@needs_compiled
def test_straight_paths_are_bit_identical_on_both_backends():
    g = _gen(6)
    n, c, T = 70, 33, 40
    u = lambda: torch.rand(n, c, generator=g)  # noqa: E731
    e, a2 = -7.0 * u(), -3.0 * u() * (u() > 0.1)
    t_star, phi, omega = 8.0 * u() - 1.0, u(), 10.0 * (u() - 0.5)
    times = torch.linspace(0.0, 6.0, T)
    a = kernel.eval_straight(e, a2, t_star, phi, omega, times, math.log(1e-2))
    b = kernel.eval_straight(e, a2, t_star, phi, omega, times, math.log(1e-2), force_torch=True)
    assert torch.equal(a, b)


def _scene() -> td.Scene:
    sys = td.OCTSystem(name="840", wavelength_um=0.84, lateral_resolution_um=4.9, axial_resolution_um=3.8)
    wide = td.OCTSystem(name="840-lat18", wavelength_um=0.84, lateral_resolution_um=18.0, axial_resolution_um=3.8)
    return td.Scene(
        systems=(sys, wide),
        protocol=td.Protocol(n_frames=12, frame_interval_s=0.2048),
        populations=(
            td.Population(density_per_um3=0.03, motion=(td.Diffusion(diffusion_um2_per_s=15.0),)),
            td.Population(density_per_um3=0.02, motion=(td.RandomBallistic(speed_um_per_s=6.0),)),
            td.Population(density_per_um3=0.02, motion=(td.Flow(speed_um_per_s=4.0, polar_angle_deg=45.0),)),
        ),
    )


@needs_compiled
def test_a_simulation_is_bit_identical_on_both_backends(monkeypatch):
    scene = _scene()
    a = td.simulate(scene, trials=70, seed=3, threads=1).signals
    monkeypatch.setenv("TORCHDOCT_KERNEL", "torch")
    kernel._library.cache_clear()
    try:
        assert not kernel.compiled()
        b = td.simulate(scene, trials=70, seed=3, threads=1).signals
    finally:
        monkeypatch.delenv("TORCHDOCT_KERNEL")
        kernel._library.cache_clear()
    assert kernel.compiled()
    assert torch.equal(a, b)


def test_float32_and_float64_walks_share_the_realization():
    """The walk's normals come from (key, frame, index), whatever the dtype: the two runs follow the
    same scatterers and differ only by float32 rounding."""
    scene = td.Scene(
        systems=_scene().systems[:1],
        protocol=td.Protocol(n_frames=8, frame_interval_s=0.2048),
        populations=(td.Population(density_per_um3=0.03, motion=(td.Diffusion(diffusion_um2_per_s=15.0),)),),
    )
    a = td.simulate(scene, trials=64, seed=9, dtype="float32", threads=1).signals.to(torch.complex128)
    b = td.simulate(scene, trials=64, seed=9, dtype="float64", threads=1).signals
    assert float((a - b).abs().max()) <= 1e-4 * float(b.abs().max())


@pytest.mark.slow  # longer than the default suite allows one test (CONTRIBUTING.md, markers)
def test_a_source_checkout_builds_the_library_into_the_cache(tmp_path, monkeypatch):
    """Without an installed extension, the library is built once from _kernel.c into the user cache
    (and gives the same bits); without a compiler there is nothing to build."""
    import ctypes
    import shutil

    monkeypatch.setenv("TORCHDOCT_CACHE", str(tmp_path))
    if shutil.which("cc") is None and shutil.which("gcc") is None:
        pytest.skip("no C compiler")
    path = kernel._build_from_source()
    assert path is not None and path.parent == tmp_path and path.is_file()
    assert kernel._build_from_source() == path  # cached: built once
    lib = ctypes.CDLL(str(path))
    x = -torch.rand(1000, generator=_gen(8)) * 50.0
    out = torch.empty_like(x)
    lib.tdk_exp_neg.argtypes = [ctypes.c_int64, ctypes.c_void_p, ctypes.c_void_p]
    lib.tdk_exp_neg(x.numel(), x.data_ptr(), out.data_ptr())
    assert torch.equal(out, kernel.exp_neg(x, force_torch=True))
    monkeypatch.setenv("CC", str(tmp_path / "no-such-compiler"))
    assert kernel._build_from_source() is None
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # no partial file left behind


def test_setup_py_builds_with_the_kernels_compiler_flags():
    """setup.py (which cannot import torch in an isolated build) keeps its own copy of the flags; the
    installed extension and the source-checkout build must compile alike (bit identity needs -ffp-contract=off)."""
    import ast
    from pathlib import Path

    tree = ast.parse((Path(__file__).resolve().parents[2] / "setup.py").read_text())
    flags = {
        node.targets[0].id: ast.literal_eval(node.value)
        for node in tree.body
        if isinstance(node, ast.Assign)
        and isinstance(node.targets[0], ast.Name)
        and node.targets[0].id in ("CFLAGS", "OPTIONAL_CFLAGS")
    }
    assert tuple(flags["CFLAGS"]) == kernel.CFLAGS and "-ffp-contract=off" in kernel.CFLAGS
    assert tuple(flags["OPTIONAL_CFLAGS"]) == kernel.OPTIONAL_CFLAGS
