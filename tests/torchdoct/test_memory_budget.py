"""The memory budget of every refusal (issue class 2): the smallest of MemAvailable, the address-space
limit RLIMIT_AS and the cgroup memory limit (v1 and v2), and a declared array over it refused as "not
enough memory for the file", naming the budget, what sets it and the fix, not as a truncated file."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from torchdoct.runtime import resources

GIB = 1 << 30


def _proc(tmp_path: Path, cgroup: str, avail_kb: int = 64 * (1 << 20)) -> Path:
    proc = tmp_path / "proc"
    (proc / "self").mkdir(parents=True)
    (proc / "meminfo").write_text(f"MemTotal: 1 kB\nMemAvailable: {avail_kb} kB\n")
    (proc / "self" / "cgroup").write_text(cgroup)
    (proc / "self" / "status").write_text("VmSize: 1000 kB\n")
    return proc


def test_a_cgroup_v2_limit_below_mem_available_sets_the_budget(tmp_path):
    proc = _proc(tmp_path, "0::/job/step\n")
    root = tmp_path / "cg"
    (root / "job" / "step").mkdir(parents=True)
    (root / "job" / "memory.max").write_text(f"{3 * GIB}\n")
    (root / "job" / "memory.current").write_text(f"{GIB}\n")
    (root / "job" / "step" / "memory.max").write_text("max\n")  # no limit of its own: the parent's holds
    budget = resources.memory_budget(proc=str(proc), cgroup_root=str(root))
    assert budget.bytes == 2 * GIB and budget.hard and "cgroup" in budget.source


def test_a_cgroup_v1_limit_counts_and_its_unlimited_value_does_not(tmp_path):
    proc = _proc(tmp_path, "4:memory:/host/path\n3:cpu:/\n")
    root = tmp_path / "cg"
    mem = root / "memory"  # inside a container the mount is the cgroup itself: the host path is absent
    mem.mkdir(parents=True)
    (mem / "memory.limit_in_bytes").write_text(f"{5 * GIB}\n")
    (mem / "memory.usage_in_bytes").write_text(f"{GIB}\n")
    assert resources.memory_budget(proc=str(proc), cgroup_root=str(root)).bytes == 4 * GIB
    (mem / "memory.limit_in_bytes").write_text("9223372036854771712\n")
    budget = resources.memory_budget(proc=str(proc), cgroup_root=str(root))
    assert budget.source.startswith("MemAvailable") and not budget.hard and budget.bytes == 64 * GIB


def _run_limited(code: str, limit_bytes: int) -> subprocess.CompletedProcess:
    pre = f"import resource; resource.setrlimit(resource.RLIMIT_AS, ({limit_bytes}, resource.RLIM_INFINITY))\n"
    return subprocess.run([sys.executable, "-c", pre + code], capture_output=True, text=True, timeout=120)


def test_the_address_space_limit_sets_the_budget():
    out = _run_limited(
        "from torchdoct.runtime.resources import memory_budget\nb = memory_budget()\nprint(b.bytes, b.hard, b.source)",
        3 * GIB,
    )
    assert out.returncode == 0, out.stderr
    n, hard, source = out.stdout.split(" ", 2)
    assert 0 < int(n) < 3 * GIB and hard == "True" and "RLIMIT_AS" in source


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_a_file_over_the_address_space_limit_is_not_enough_memory_not_truncated(tmp_path):
    from numpy.lib import format as npf

    seq = tmp_path / "big.npy"
    shape = (32, 2048, 2048, 2)  # 2 GiB of complex64, a sparse file; the maps' own estimate is under 1 GiB
    with open(seq, "wb") as fh:
        npf.write_array_header_1_0(fh, {"descr": "<c8", "fortran_order": False, "shape": shape})
        fh.truncate(fh.tell() + int(np.prod(shape)) * 8)
    code = (  # the limit: 1.4 GiB above the address space of the loaded command
        "import resource, sys\nimport torchdoct.cli, torchdoct.measured.maps\n"
        "used = next(int(l.split()[1]) * 1024 for l in open('/proc/self/status') if l.startswith('VmSize:'))\n"
        "resource.setrlimit(resource.RLIMIT_AS, (used + int(1.4 * 2**30), resource.RLIM_INFINITY))\n"
        f"sys.exit(torchdoct.cli.main(['maps', {str(seq)!r}, '--axes', 'TYZX', '--pitch-um', 'z=2,x=2,y=2', "
        "'--frame-interval-s', '0.01', '--wavelength-um', '0.84', '--lateral-resolution-um', '4.9', "
        f"'--axial-resolution-um', '3.8', '--out', {str(tmp_path / 'm.npz')!r}]))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    lines = [ln for ln in out.stderr.splitlines() if ln.strip()]
    assert out.returncode == 2 and len(lines) == 1, out.stderr
    line = lines[0]
    for part in ("big.npy", "not enough memory for the file", "memory budget", "RLIMIT_AS", "crop", "chunked"):
        assert part in line, (part, line)
    assert "truncated" not in line and not (tmp_path / "m.npz").exists()


def test_an_explicit_input_limit_overrides_mem_available_only(monkeypatch):
    from torchdoct.measured import guards

    monkeypatch.setattr(
        resources, "memory_budget", lambda: resources.MemoryBudget(GIB, "MemAvailable of the machine", False)
    )
    with pytest.raises(resources.MemoryLimitError, match="--max-input-gb GB reads it anyway"):
        guards.check_declared_size("x.npy", (2, GIB), 1)
    guards.set_max_input_gb(4.0)
    try:
        assert guards.check_declared_size("x.npy", (2, GIB), 1) == 2 * GIB
        monkeypatch.setattr(
            resources, "memory_budget", lambda: resources.MemoryBudget(GIB, "the address-space limit RLIMIT_AS", True)
        )
        with pytest.raises(resources.MemoryLimitError, match="RLIMIT_AS.*raise that limit"):
            guards.check_declared_size("x.npy", (2, GIB), 1)
    finally:
        guards.set_max_input_gb(None)
