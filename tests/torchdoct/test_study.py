"""The paper study (torchdoct.study): the shipped study files, a tiny study end to end, the claims report,
the CLI and the notebook (slow).

The tiny study has the paper's four systems and motions but 8 frames, 3 motion values per curve and
64 trials per point.
"""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from _studies import tiny_study_dict, write_tiny_study

from torchdoct.cli import main
from torchdoct.sim.config import SceneError
from torchdoct.study import (
    Z_SIGNIFICANT,
    _crossing,
    _Curve,
    direction_differences,
    load_study,
    paired_differences,
    run_study,
    study_from_dict,
    study_outputs,
    study_sweeps,
)
from torchdoct.study.sweep import cell_seed, run_sweeps

REPO = Path(__file__).resolve().parents[2]
NOTEBOOK = REPO / "notebooks" / "paper_reproduction.ipynb"


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """The tiny study run once, from an empty cache (shared by the tests below)."""
    d = tmp_path_factory.mktemp("study")
    path = write_tiny_study(d)
    return path, run_study(path, d / "out")


# ----------------------------------------------------------------------------------------------------------
# the shipped study files
# ----------------------------------------------------------------------------------------------------------
def test_shipped_paper_study_matches_the_paper_design():
    st = load_study("paper")
    assert st.trials == 500 and st.dtype == "float32" and st.grouping in ("pairs", "all")
    systems = {
        s["name"]: (s["wavelength_um"], s["lateral_resolution_um"], s["axial_resolution_um"])
        for s in st.scene_data["system"]
    }
    assert systems == {
        "840nm-high": (0.84, 4.9, 3.8),
        "1310nm-high": (1.31, 4.9, 3.8),
        "840nm-axial14": (0.84, 4.9, 14.0),
        "840nm-lateral18": (0.84, 18.0, 3.8),
    }
    assert {(c.name, c.reference, c.other) for c in st.comparisons} == {
        ("wavelength", "840nm-high", "1310nm-high"),
        ("axial", "840nm-high", "840nm-axial14"),
        ("lateral", "840nm-high", "840nm-lateral18"),
    }
    assert st.scene_data["population"][0]["density_per_um3"] == 0.055
    assert st.scene_data["protocol"] == {"n_frames": 32, "frame_interval_s": 0.2048}
    assert st.scene_data["analysis"]["ocds_delay_range_s"] == [0.2048, 1.2288]
    kinds = {p.name: (p.kind, p.motion.get("directions"), p.motion.get("polar_angle_deg")) for p in st.parts}
    assert kinds["diffusion"][0] == "diffusion" and kinds["flow"] == ("flow", None, 45.0)
    assert {kinds[n][1] for n in st.direction_parts} == {"isotropic", "uniform-angles"}
    assert kinds[st.figure_parts[1]][1] == "uniform-angles"  # the paper's law in the figures
    for p in st.parts:
        top = 15.0 if p.kind == "diffusion" else 6.0
        assert len(p.values) >= 31 and min(p.values) == 0.0 and max(p.values) == top
        assert sum(v <= 0.1 * top for v in p.values) > len(p.values) / 2  # denser at small values
        assert sum(0 < v <= p.inset_max for v in p.values) >= 8  # the inset is resolved
    assert load_study("paper-reduced").trials < st.trials


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda d: d["study"].update(colour="blue"), r"study: unknown key\(s\) \['colour'\]"),
        (
            lambda d: d["study"]["comparison"][0].update(other="900nm"),
            r"comparison\[0\].other: '900nm' is not a system",
        ),
        (lambda d: d["study"].update(figure_parts=["diffusion", "nope", "flow"]), "'nope' is not a part"),
        (lambda d: d["study"].update(direction_parts=["ballistic", "flow"]), "differ only in directions"),
        (lambda d: d["part"][0].update(parameter="speed_um_per_s"), "is not a key of part"),
        (lambda d: d["part"][0]["motion"].update(diffusion_um2_per_s=-1.0), r"part\[0\].motion"),
        (lambda d: d["part"][0].update(values=[0.0, -1.0]), "values must be numbers >= 0"),
        (lambda d: d["study"].update(grouping="triples"), "grouping"),
        (lambda d: d["scene"]["system"][0].update(wavelength_um=840.0), "micrometres"),
    ],
)
def test_study_file_errors_name_the_key(change, match):
    data = tiny_study_dict()
    change(data)
    with pytest.raises((SceneError, TypeError), match=match):
        study_from_dict(data)


def test_study_sweeps_pairs_and_all():
    st = study_from_dict(tiny_study_dict())
    sw = study_sweeps(st)
    assert len(sw) == len(st.parts) * 3
    for s in sw:
        part, comp = s.name.split("/")
        c = next(c for c in st.comparisons if c.name == comp)
        assert [x.name for x in s.scene.systems] == [c.reference, c.other]
        assert [cell.values["value"] for cell in s.cells] == list(st.part(part).values)
    st_all = study_from_dict(tiny_study_dict(grouping="all"))
    sw_all = study_sweeps(st_all)
    assert [s.name for s in sw_all] == [p.name for p in st.parts]
    assert len(sw_all[0].scene.systems) == 4
    # a cell's seed depends on the motion value only: all comparisons, and both groupings, share it
    seeds = {(s.name.split("/")[0], c.values["value"]): cell_seed(11, c.key) for s in sw for c in s.cells}
    for s in sw_all:
        for c in s.cells:
            assert cell_seed(11, c.key) == seeds[(s.name, c.values["value"])]


# ----------------------------------------------------------------------------------------------------------
# a tiny study end to end
# ----------------------------------------------------------------------------------------------------------
@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_tiny_study_writes_every_output(tiny_run):
    path, r = tiny_run
    out = r.files[0].parent
    assert sorted(r.files) == sorted(study_outputs(r.study, out))
    for f in r.files:
        assert f.is_file() and f.stat().st_size > 0
    for png in out.glob("*.png"):
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    for svg in out.glob("*.svg"):
        assert "<svg" in svg.read_text(encoding="utf-8")[:2000]
    pd.testing.assert_frame_equal(pd.read_parquet(out / "results.parquet"), r.table)
    rec = json.loads((out / "study.json").read_text())
    assert rec["computed"] == len(r.sweep_result.cells) == 4 * 3 * 3 and rec["cached"] == 0
    assert {c["seed"] for c in rec["cells"]} == {c.seed for c in r.sweep_result.cells}


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_paired_differences_are_the_per_trial_differences(tiny_run):
    _, r = tiny_run
    d = r.differences
    assert len(d) == 4 * 3 * 3 * 2  # parts × comparisons × values × metrics
    ok = d["n"] == d["trials"]
    np.testing.assert_allclose(
        d.loc[ok, "diff"], d.loc[ok, "mean_other"] - d.loc[ok, "mean_reference"], rtol=1e-9, atol=1e-9
    )
    row = d[
        (d["part"] == "diffusion") & (d["comparison"] == "axial") & (d["value"] == 0.01) & (d["metric"] == "liv")
    ].iloc[0]
    cell = next(c for c in r.sweep_result.of_sweep("diffusion/axial") if c.cell.values["value"] == 0.01)
    per = cell.metrics["liv"][:, 1].astype(np.float64) - cell.metrics["liv"][:, 0]
    assert row["diff"] == pytest.approx(per.mean(), rel=1e-12)
    assert row["se"] == pytest.approx(per.std(ddof=1) / math.sqrt(per.size), rel=1e-12)
    # the reference system's numbers in the table are the same cell's
    t = r.table
    ref = t[
        (t["sweep"] == "diffusion/axial")
        & (t["value"] == 0.01)
        & (t["metric"] == "liv")
        & (t["system"] == "840nm-high")
    ].iloc[0]
    assert ref["mean"] == pytest.approx(row["mean_reference"], rel=1e-12)


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_zero_motion_rows_are_exactly_zero(tiny_run):
    _, r = tiny_run
    z = r.differences[r.differences["value"] == 0.0]
    assert len(z) == 4 * 3 * 2
    for col in ("mean_reference", "mean_other", "sd_reference", "sd_other", "diff", "se", "z"):
        assert (z[col] == 0).all(), col


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_flow_has_no_wavelength_dependency_within_standard_errors(tiny_run):
    """physics.md §5.3(c): flow intensity statistics do not depend on the wavelength (same PSF)."""
    _, r = tiny_run
    d = r.differences
    f = d[(d["part"] == "flow") & (d["comparison"] == "wavelength") & (d["value"] > 0)]
    assert len(f) == 4
    assert (f["se"] > 0).all()
    assert (f["z"].abs() <= Z_SIGNIFICANT).all(), f[["value", "metric", "diff", "se", "z"]]


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_direction_law_comparison_shares_seeds(tiny_run):
    _, r = tiny_run
    d = r.directions
    assert set(d["system"]) == {"840nm-high", "1310nm-high", "840nm-axial14", "840nm-lateral18"}
    assert (d[d["value"] == 0.0]["diff"] == 0).all()
    t = r.table
    for v in (0.1, 3.0):
        a = t[(t["part"] == "ballistic") & (t["value"] == v)]["seed"].unique()
        b = t[(t["part"] == "ballistic-isotropic") & (t["value"] == v)]["seed"].unique()
        assert len(a) == 1 and list(a) == list(b)
    # recomputing from the sweep result gives the same table
    pd.testing.assert_frame_equal(direction_differences(r.study, r.sweep_result), d)


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_claims_report_quotes_the_tables(tiny_run):
    _, r = tiny_run
    text = (r.files[0].parent / "claims.md").read_text(encoding="utf-8")
    assert text == r.report
    for s in (
        "## Claims",
        "§3.3.1, Fig. 6(a)",
        "§3.3.2, Fig. 7(a)",
        "§3.3.2, Fig. 8(f)",
        "§4.1",
        "§4.2 (P2)",
        "§4.2 (P12, P13)",
        "1.2 µm²/s",
        "isotropic",
        "## Where this run disagrees",
    ):
        assert s in text, s
    rows = [ln for ln in text.splitlines() if re.match(r"^\| \d+ \|", ln)]
    assert len(rows) >= 40
    # the flow wavelength row quotes the largest |z| of the differences table
    d = r.differences
    f = d[(d["part"] == "flow") & (d["comparison"] == "wavelength") & (d["metric"] == "liv") & (d["value"] > 0)]
    i = f["z"].abs().idxmax()
    row = next(ln for ln in rows if "flow: no marked wavelength dependency of LIV" in ln)
    assert f"{-f.loc[i, 'z']:+.1f})" in row and f"v = {f.loc[i, 'value']:.3g} µm/s" in row
    ens = next(ln for ln in rows if "ENS = 5.02" in ln)
    assert "5.018 (paper 5.02)" in ens and "18.488 (paper 18.5)" in ens and ens.endswith("| supported |")


def test_crossing_finder():
    x = np.array([0.0, 0.1, 0.3, 1.0, 2.0, 5.0])
    diff = np.array([0.0, 2.0, 1.5, 0.5, -1.0, -1.5])
    se = np.full(6, 0.25)
    c = _Curve(x, np.zeros(6), diff, diff, se, diff / se)
    cr = _crossing(c)
    assert cr["found"] and cr["x_lo"] == 1.0 and cr["x_hi"] == 2.0 and cr["x"] == pytest.approx(math.sqrt(2.0))
    mean, se_left, z, k = cr["left"]  # pooled over the independent cells left of the split
    assert k == 3 and mean == pytest.approx(4.0 / 3) and se_left == pytest.approx(0.25 * math.sqrt(3) / 3)
    assert cr["right"][3] == 2 and cr["right"][0] == pytest.approx(-1.25)
    # z = 8, 6, 2, −4, −6: the last value positive at z ≥ 2 is x = 1.0, the first negative at z ≤ −2 is 2.0
    assert cr["bracket"] == (1.0, 2.0)
    quiet = _crossing(_Curve(x, np.zeros(6), diff, diff, se * 10, diff / (se * 10)))
    assert not quiet["found"]
    # a flat stretch where single values cannot tell the sign widens the bracket to its ends
    flat = np.array([0.0, 2.0, 0.2, -0.1, 0.1, -1.5])
    cr = _crossing(_Curve(x, np.zeros(6), flat, flat, se, flat / se))
    assert cr["bracket"] == (0.1, 5.0)


@pytest.mark.slow  # an end-to-end command run; the default suite covers its parts
def test_rerun_uses_the_cache_and_refuses_to_overwrite(tiny_run, tmp_path):
    path, r = tiny_run
    out = r.files[0].parent
    with pytest.raises(ValueError, match="pass --force"):
        run_study(path, out)
    again = run_study(path, out, force=True)
    assert again.sweep_result.computed == 0
    pd.testing.assert_frame_equal(again.table, r.table)
    pd.testing.assert_frame_equal(again.differences, r.differences)


def test_grouping_all_runs_every_comparison_from_one_scene(tmp_path):
    data = tiny_study_dict(grouping="all")
    for p in data["part"]:
        p["values"] = p["values"][:2]
    st = study_from_dict(data)
    res = run_sweeps(study_sweeps(st))
    d = paired_differences(st, res)
    assert set(d["comparison"]) == {"wavelength", "axial", "lateral"}
    ref = d[(d["metric"] == "liv") & (d["value"] > 0)].groupby(["part", "value"])["mean_reference"].nunique()
    assert (ref == 1).all()  # one reference curve shared by the three comparisons


@pytest.mark.slow  # an end-to-end command run; the default suite covers its parts
def test_cli_study(tmp_path, capsys):
    path = write_tiny_study(tmp_path)
    out = tmp_path / "out"
    assert (
        main(["study", str(path), "--out", str(out), "--no-progress", "--cache", str(tmp_path / "c"), "--workers", "1"])
        == 0
    )
    text = capsys.readouterr().out
    assert "36 cells (36 computed, 0 from the cache)" in text and f"wrote {out / 'claims.md'}" in text
    assert not (out / "cache").exists() and any((tmp_path / "c").glob("*.npz"))
    assert main(["study", "no-such-study", "--out", str(tmp_path / "x")]) == 2
    assert "paper-reduced" in capsys.readouterr().err


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under five minutes
def test_cli_bench_study(tmp_path, capsys):
    path = write_tiny_study(tmp_path)
    path.write_text(
        path.read_text().replace("[0.0, 0.01, 1.0]", "[0.0, 0.01]").replace("[0.0, 0.1, 3.0]", "[0.0, 0.1]")
    )
    out = tmp_path / "bench.json"
    assert main(["bench", "study", "--study", str(path), "--out", str(out), "--no-progress", "--workers", "1"]) == 0
    res = json.loads(out.read_text())
    assert res["benchmark"] == "study" and res["cells"] == 4 * 3 * 2
    assert res["system_trials"] == res["cells"] * 2 * 64
    assert res["wall_s"] >= res["simulate_s"] > 0
    assert "wall time" in capsys.readouterr().out
    assert main(["bench", "study", "--study", str(path), "--out", str(out)]) == 2


# ----------------------------------------------------------------------------------------------------------
# slow: the reduced study and the notebook
# ----------------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_notebook_runs_top_to_bottom_on_the_reduced_study(tmp_path, monkeypatch):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    out = tmp_path / "paper-reduced"
    monkeypatch.setenv("TORCHDOCT_STUDY", "paper-reduced")
    monkeypatch.setenv("TORCHDOCT_STUDY_OUT", str(out))
    nb = nbformat.read(NOTEBOOK, as_version=4)
    assert all(not c.get("outputs") for c in nb.cells if c.cell_type == "code")  # stored without outputs
    nbclient.NotebookClient(
        nb, timeout=1200, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    ).execute()
    for f in ("results.parquet", "claims.md", "fig6-wavelength.png", "fig7-axial.png", "fig8-lateral.png"):
        assert (out / f).is_file()
    text = "".join(
        str(o.get("text", "")) + json.dumps(o.get("data", {}))
        for c in nb.cells
        if c.cell_type == "code"
        for o in c.get("outputs", [])
    )
    assert "image/png" in text and "Claims" in text
    assert not any(o.get("output_type") == "error" for c in nb.cells for o in c.get("outputs", []))


@pytest.mark.slow
def test_bench_study_groupings(tmp_path, capsys):
    out = tmp_path / "bench.json"
    path = write_tiny_study(tmp_path)
    assert (
        main(
            [
                "bench",
                "study",
                "--study",
                str(path),
                "--groupings",
                "--grouping-trials",
                "64",
                "--out",
                str(out),
                "--no-progress",
                "--workers",
                "2",
            ]
        )
        == 0
    )
    res = json.loads(out.read_text())
    assert {g["part"] for g in res["groupings"]} == {"diffusion", "ballistic", "flow"}
    assert all(g["all_s"] > 0 and g["pairs_s"] > 0 for g in res["groupings"])
    assert "pairs/all" in capsys.readouterr().out


def test_notebook_file_is_valid():
    nbformat = pytest.importorskip("nbformat")
    nb = nbformat.read(NOTEBOOK, as_version=4)
    nbformat.validate(nb)
    src = "\n".join(c.source for c in nb.cells)
    assert "TORCHDOCT_STUDY_OUT" in src and "run_study" in src and "claims.md" in src
    assert os.sep + "work" + os.sep not in src
