"""``torchdoct bench cog``: loading a COG clone (with CuPy absent), the motion mapping to COG's SI
parameters, the per-cell table, and the errors for a missing clone."""

from __future__ import annotations

import json
import math
import textwrap

import pytest

from torchdoct.bench import cog
from torchdoct.cli import main
from torchdoct.sim.config import Diffusion, Flow, RandomBallistic

#: A stand-in with COG's point-simulator interface (the benchmark reads nothing else of it). It imports
#: cupy at the top, as COG's module does.
FAKE = textwrap.dedent("""
    import numpy as np
    import cupy as cp

    class numerical0dParameters:
        def __init__(self, totalTime, res, waveLength):
            self.totalTime, self.res, self.waveLength = totalTime, np.array(res), waveLength

    class scattererPositions:
        calls = []
        def __init__(self, scatterDensity, numFieldParam, motion, motionParam, r=1.0):
            scattererPositions.calls.append((motion, motionParam, tuple(numFieldParam.res), numFieldParam.waveLength))
            self.numScatter = 1000
            self.scatterArray = np.random.rand(3, self.numScatter) * 1e-5
        def velocitiesSet(self):
            pass
        def positionsUpdate(self, dt):
            self.scatterArray += 1e-8 * np.random.normal(size=self.scatterArray.shape)

    class complexOctPixel:
        def __init__(self, num0dParam):
            self.num0dParam = num0dParam
        def generate(self, sp):
            z = sp.scatterArray[2]
            self.complexOctPixel = np.sum(np.exp(1j * 4 * np.pi / self.num0dParam.waveLength * z))
""")


def test_motions_map_to_cog_si_parameters():
    name, p = cog._cog_motion(Diffusion(diffusion_um2_per_s=15.0))
    assert name == "diffusion" and float(p[0]) == pytest.approx(15e-12)
    assert cog._cog_motion(RandomBallistic(speed_um_per_s=6.0)) == ("randomBallistic", pytest.approx(6e-6))
    name, p = cog._cog_motion(Flow(speed_um_per_s=6.0, polar_angle_deg=45.0))
    assert name == "flow" and p == pytest.approx([6e-6, math.pi / 4, 0.0])


def test_bench_cog_times_every_paper_cell(tmp_path):
    (tmp_path / "doctSimulator.py").write_text(FAKE)
    out = tmp_path / "bench-cog.json"
    assert (
        main(
            [
                "bench",
                "cog",
                "--cog",
                str(tmp_path),
                "--cog-trials",
                "1",
                "--trials",
                "64",
                "--repeats",
                "1",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    res = json.loads(out.read_text())
    assert len(res["cells"]) == 12
    assert {r["system"] for r in res["cells"]} == {"840nm-high", "1310nm-high", "840nm-axial14", "840nm-lateral18"}
    for r in res["cells"]:
        assert r["cog_scatterers"] == 1000 and r["cog_ms_per_trial"] > 0 and r["torchdoct_ms_per_trial"] > 0
        assert r["ratio"] == pytest.approx(r["cog_ms_per_trial"] / r["torchdoct_ms_per_trial"])
    ratios = [r["ratio"] for r in res["cells"]]
    assert res["geometric_mean_ratio"] == pytest.approx(math.exp(sum(map(math.log, ratios)) / 12))


def test_bench_cog_refuses_a_folder_without_the_simulator(tmp_path, capsys):
    assert main(["bench", "cog", "--cog", str(tmp_path), "--out", str(tmp_path / "x.json")]) == 2
    err = capsys.readouterr().err
    assert "doctSimulator.py" in err and "clone" in err
    assert not (tmp_path / "x.json").exists()
