"""The documentation's numbers come from results files, and those files hold what the code computes.

The site (``mkdocs.yml``, ``docs/``) renders every measured figure at build time from a JSON results file
(``docs/hooks/results.py``); these tests check that every table a page asks for exists and renders, that
the results files have the schema the renderers read, and that the recorded files agree with the physics
and with the code (a seeded example run is reproduced bit for bit, the validation table's theory column is
the closed form's value and every row is within the stated |z| bound). No test reads the README: the
documentation build checks that it is a front page (``docs/hooks/frontpage.py``), tested here on made-up text.
"""

from __future__ import annotations

import json
import math
import re
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
HOOKS = REPO / "docs" / "hooks"
sys.path.insert(0, str(HOOKS))

import cli_ref  # noqa: E402
import frontpage  # noqa: E402
import models  # noqa: E402
import results  # noqa: E402

MARKER = re.compile(r"^<!-- render: ([\w-]+) -->$", re.M)


def _pages() -> list[Path]:
    return sorted(p for p in (REPO / "docs").rglob("*.md") if "hooks" not in p.parts)


def test_every_results_table_a_page_asks_for_renders_from_its_file():
    asked = {m for p in _pages() for m in MARKER.findall(p.read_text(encoding="utf-8"))}
    assert asked, "no page renders a results table"
    assert asked <= set(results.RENDERERS), asked - set(results.RENDERERS)
    for name in sorted(asked):
        md = results.render(REPO, name)
        assert "Written by `" in md and "|---" in md, name


def test_an_unknown_results_table_or_a_missing_file_is_an_error(tmp_path):
    with pytest.raises(KeyError, match="unknown results table"):
        results.render(REPO, "no-such-table")
    with pytest.raises(results.MissingResult, match="bench-simulate.json"):
        results.render(tmp_path, "bench-simulate")


def test_number_formatting_keeps_significant_figures_and_marks_missing_values():
    assert results.num(0.8148669996) == "0.815"
    assert results.num(797.0689) == "797"
    assert results.num(3077138.34) == "3.08e+06"
    assert results.num(None) == "n/a" and results.num(float("nan")) == "n/a"
    assert results.pm(0.74003, 0.02268) == "0.74 ± 0.023"


#: float32 machine epsilon (the simulator's default dtype).
FLOAT32_EPS = 2.0**-23


def test_the_recorded_example_run_is_what_the_simulator_gives_for_its_seed():
    """``docs/results/simulate-example.json`` = ``torchdoct simulate example --json``, reproduced here."""
    td = pytest.importorskip("torchdoct")
    recorded = json.loads((REPO / "docs" / "results" / "simulate-example.json").read_text(encoding="utf-8"))
    scene = td.load_scene("example")
    assert set(recorded) == {s.name for s in scene.systems}
    summary = td.simulate(scene, threads=1).summary()
    for system, metrics in recorded.items():
        for metric in ("liv", "ocds"):
            rec, now = metrics[metric], summary[system][metric]
            assert rec["n"] == now["n"]
            assert math.isclose(rec["se"], rec["sd"] / math.sqrt(rec["n"]), rel_tol=1e-9)
            # bit for bit on one machine whatever the threads or chunks (tests/torchdoct/test_threads.py); another
            # CPU's vector log/exp may round a float32 trial value differently in its last places, which moves
            # a mean over the trials by at most a few float32 epsilons
            tol = 4 * FLOAT32_EPS
            assert math.isclose(rec["mean"], now["mean"], rel_tol=tol), (system, metric, rec["mean"], now["mean"])
            assert math.isclose(rec["sd"], now["sd"], rel_tol=tol), (system, metric, rec["sd"], now["sd"])
    # the paper's small-motion finding, resolved: the shorter wavelength decorrelates faster (higher LIV)
    a, b = recorded["840nm-high"]["liv"], recorded["1310nm-high"]["liv"]
    assert (a["mean"] - b["mean"]) / math.hypot(a["se"], b["se"]) > 2


def test_the_recorded_validation_table_is_within_its_z_bound_of_the_closed_forms():
    np = pytest.importorskip("numpy")
    th = pytest.importorskip("torchdoct.sim.theory")
    import torchdoct as td

    d = json.loads((REPO / "docs" / "results" / "validation-table.json").read_text(encoding="utf-8"))
    assert d["command"].startswith("python notebooks/validation_table.py")
    sys.path.insert(0, str(REPO / "notebooks"))
    try:
        import validation_table as vt
    finally:
        sys.path.remove(str(REPO / "notebooks"))
    assert [r["motion"] for r in d["rows"]] == [row[0] for row in vt.ROWS]
    for rec, (name, motion, system, lag) in zip(d["rows"], vt.ROWS):
        assert rec["max_abs_z"] <= 4.0, rec  # the suite's bound on |z| against the Monte Carlo SE
        g, _ = (complex(np.atleast_1d(x)[0]) for x in th.g1_and_j(motion, system, np.array([lag * vt.DT])))
        assert math.isclose(rec["g1_theory_re"], g.real, abs_tol=1e-12), name
        assert abs(rec["g1_re"] - g.real) <= 4 * rec["g1_se_re"], name
        assert isinstance(system, td.OCTSystem)


def test_the_recorded_quick_training_report_has_the_schema_the_docs_read():
    r = json.loads((REPO / "docs" / "results" / "quick-single-acquisition.json").read_text(encoding="utf-8"))
    assert r["data"]["draws"] == {"train": 90, "validation": 24, "test": 36}  # the --quick splits
    t, se = r["test"]["network"]["1"], r["standard_errors"]["1"]
    for key in ("coverage_identifiable", "accuracy_identifiable", "balanced_accuracy_identifiable", "ece"):
        assert 0 <= t[key] <= 1 and se[key] > 0, key
    # balanced accuracy over three classes is at least chance for a trained model's decided pixels
    assert t["balanced_accuracy_identifiable"] > 1 / 3


@pytest.mark.parametrize("name", models.shipped(REPO))
def test_every_shipped_model_has_a_card_from_its_report(name):
    r = json.loads((REPO / models.MODEL_DIR / f"{name}.json").read_text(encoding="utf-8"))
    assert r["spec"]["name"] == name
    for pool, m in r["test"]["network"].items():
        assert 0 <= m["coverage_identifiable"] <= 1 and 0 <= m["balanced_accuracy_identifiable"] <= 1, pool
    curve = r["coverage_curve"]["1"]
    cov = [c["coverage_identifiable"] for c in sorted(curve, key=lambda c: c["min_probability"])]
    assert cov == sorted(cov, reverse=True), "a higher --min-probability cannot decide more pixels"
    card = models.card(REPO, name)
    for heading in (
        "## Specification",
        "## Training data",
        "## When it abstains",
        "## Results on its own test split",
        "## Results on the phantom grid",
        "## Results on independent data",
        "## Limits",
    ):
        assert heading in card, heading


def test_the_cli_reference_lists_every_option_of_every_parser():
    import argparse

    for name, (_, parser) in cli_ref._parsers().items():
        page = cli_ref.page(name)
        stack = [parser]
        while stack:
            p = stack.pop()
            for a in p._actions:
                if isinstance(a, argparse._SubParsersAction):
                    stack += list(a.choices.values())
                elif a.option_strings and not isinstance(a, argparse._HelpAction):
                    assert f"`{a.option_strings[-1]}`" in page, (name, p.prog, a.option_strings)


def test_the_site_build_refuses_a_readme_that_is_not_a_front_page(tmp_path):
    """The front-page policy is checked by the docs build (``docs/hooks/site.py``), on made-up READMEs here."""
    (tmp_path / "pic.png").write_bytes(b"")
    good = "\n".join(["# x", "![a picture](pic.png)", *frontpage.FRONT_PAGE_COMMANDS, "see the benchmarks page"])
    assert frontpage.problems(good, tmp_path) == []
    assert any("lines" in p for p in frontpage.problems(good + "\n" * frontpage.README_MAX_LINES, tmp_path))
    assert any("picture" in p for p in frontpage.problems(good.replace("pic.png", "gone.png"), tmp_path))
    assert any("missing" in p for p in frontpage.problems(good.replace("pytest", "unittest"), tmp_path))
    figures = frontpage.problems(good + "\nit takes 3.5 s and scores 0.871", tmp_path)
    assert any("3.5 s" in p and "0.871" in p for p in figures), figures


def test_the_site_build_refuses_a_link_to_a_missing_file(tmp_path):
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "physics.md").write_text("# Physics")
    sub = tmp_path / "pkg"
    sub.mkdir()
    text = "[p](../docs/physics.md) [s](../docs/physics.md#5-x) [w](https://example.org/a) [a](#top) [gone](physics.md)"
    assert frontpage.broken_links(text, sub) == ["physics.md"]


def test_the_recorded_bulk_phase_run_agrees_with_the_first_order_prediction():
    """``notebooks/bench/bench-bulk-phase.json`` (physics.md §12 renders it): on static speckle the weighted mean
    is within 4 standard errors of :func:`~torchdoct.measured.bulkphase.predicted_residual_rms` at every SNR; on
    the phantom the stable mask leaves the static tissue's g1_4 within 1 SE of its value without bulk motion and
    a smaller residual than every pixel does (§12.3)."""
    d = json.loads((REPO / "notebooks" / "bench" / "bench-bulk-phase.json").read_text(encoding="utf-8"))
    assert d["benchmark"] == "bulk-phase" and d["n_z"] > 1 and d["machine"]
    wm = [r for r in d["rows"] if r["method"] == "weighted-mean"]
    assert {r["snr_db"] for r in wm} == {r["snr_db"] for r in d["rows"]}
    for r in wm:
        assert abs(r["residual_rms_rad"] - r["predicted_rms_rad"]) <= 4 * r["se_rad"], r
    rows = d["phantom"]["rows"]
    for r in rows:
        if r["mask"].startswith("stable"):
            assert abs(r["g1_4_static_z"]) < 1, r
            every = next(a for a in rows if (a["snr_db"], a["method"], a["mask"]) == (r["snr_db"], r["method"], "all"))
            assert r["residual_rms_rad"] < every["residual_rms_rad"], (r, every)


def test_a_grid_rows_coverage_ceiling_leaves_out_only_the_motions_its_data_cannot_decide():
    """Random-ballistic motion counts in volumes with static tissue only; flow across a static-free B-scan's
    plane not at all; every other motion's pixels count in full."""

    def cell(geometry, context, polar, azimuth, pixels=(10, 20, 30)):
        per = {m: {"pixels": n} for m, n in zip(("diffusion", "ballistic", "flow"), pixels)}
        return {
            "geometry": geometry,
            "context": context,
            "pool": 5,
            "polar_deg": polar,
            "azimuth_deg": azimuth,
            "per_class": per,
        }

    grid = {
        "cells": [
            cell("bscan", "none", 10.0, 0.0),
            cell("bscan", "none", 80.0, 90.0),
            cell("bscan", "background", 80.0, 90.0),
            cell("volume", "none", 80.0, 90.0),
            cell("volume", "background", 10.0, 0.0),
        ]
    }
    assert results._coverage_ceiling(grid, "bscan", "none", 5) == (10 + 30 + 10) / 120
    assert results._coverage_ceiling(grid, "bscan", "background", 5) == 40 / 60
    assert results._coverage_ceiling(grid, "volume", "none", 5) == 40 / 60
    assert results._coverage_ceiling(grid, "volume", "background", 5) == 1.0
