"""Learning curve of the signature classifier (``python -m research.learning_curve``), on tiny sizes.

The tests that run the study (simulation of 12 draws, two trainings) are
``slow``; the prefix property, the refusals and the option errors are checked fast on their own.
"""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from classifier.dataset import make_dataset
from research.learning_curve import draw_prefix, main

TINY = ["--sizes", "3,6", "--draws-test", "3", "--draws-validation", "3", "--max-epochs", "3", "--gb-pixels", "500"]


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """One tiny run (3 and 6 training draws, 3 test and 3 validation draws), its output and its cache."""
    d = tmp_path_factory.mktemp("learning-curve")
    cache = d / "cache"
    out = d / "curve.json"
    rc = main(["--out", str(out), "--cache", str(cache), *TINY])
    return rc, out, cache


def test_prefix_of_a_split_is_the_smaller_split(tmp_path):
    big = make_dataset("signature", split="train", draws=6, replicates=1, cache_dir=tmp_path)
    small = make_dataset("signature", split="train", draws=3, replicates=1, cache_dir=tmp_path)
    assert not big.meta["from_cache"] and not small.meta["from_cache"]  # two simulations, not one reused
    pre = draw_prefix(big, 3)
    assert 0 < len(pre) < len(big) and pre.meta["draws"] == 3
    for k, v in small.arrays().items():  # same first samples, in the same order
        np.testing.assert_array_equal(getattr(pre, k), v, err_msg=k)
    np.testing.assert_array_equal(pre.x_ref, small.x_ref)
    np.testing.assert_array_equal(pre.x, big.x[: len(pre)])
    assert set(np.unique(big.draw[len(pre) :])) == {3, 4, 5}


def test_refuses_existing_outputs_before_any_work(tmp_path, capsys):
    for suffix in (".json", ".md", ".png"):
        d = tmp_path / suffix[1:]
        d.mkdir()
        (d / f"curve{suffix}").write_bytes(b"mine")
        assert main(["--out", str(d / "curve.json"), *TINY]) == 2
        msg = capsys.readouterr().out.strip()
        assert msg.startswith("error:") and f"curve{suffix} exists" in msg and "\n" not in msg
        assert [p.name for p in d.iterdir()] == [f"curve{suffix}"] and (d / f"curve{suffix}").read_bytes() == b"mine"
    assert main(["--out", str(tmp_path / "curve.txt"), *TINY]) == 2
    assert "must end in .json" in capsys.readouterr().out
    assert main(["--out", str(tmp_path / "missing" / "curve.json"), *TINY]) == 2
    assert "does not exist" in capsys.readouterr().out


@pytest.mark.slow
def test_nested_sizes_are_prefixes_of_one_split(tiny_run):
    rc, out, cache = tiny_run
    assert rc == 0
    big = make_dataset("signature", split="train", draws=6, cache_dir=cache)  # the run's training split
    assert big.meta["from_cache"]
    small = make_dataset("signature", split="train", draws=3, cache_dir=cache)  # simulated on its own
    assert not small.meta["from_cache"]
    pre = draw_prefix(big, 3)
    assert len(pre) == len(small) and 0 < len(pre) < len(big)
    for k, v in small.arrays().items():  # same first samples: the 3-draw split is the 6-draw split's head
        np.testing.assert_array_equal(getattr(pre, k), v, err_msg=k)
    np.testing.assert_array_equal(pre.x_ref, small.x_ref)
    np.testing.assert_array_equal(pre.x, big.x[: len(pre)])
    rows = json.loads(out.read_text())["rows"]
    assert [r["draws"] for r in rows] == [3, 6] and rows[0]["samples"] == len(small) and rows[1]["samples"] == len(big)


@pytest.mark.slow
def test_outputs_exist_with_finite_numbers(tiny_run):
    rc, out, _ = tiny_run
    assert rc == 0
    for suffix in (".md", ".png"):
        assert out.with_suffix(suffix).stat().st_size > 0
    res = json.loads(out.read_text(), parse_constant=lambda c: pytest.fail(f"non-JSON number {c} in {out}"))
    for row in res["rows"]:
        assert row["network"]["training_s"] > 0 and row["network"]["epochs"] >= 1
        for model in ("network", "gradient_boosting"):
            for pool in ("1", "25"):
                m = row[model][pool]
                for key in ("coverage_identifiable", "ece"):
                    assert math.isfinite(m[key]) and 0.0 <= m[key] <= 1.0, (model, pool, key)
                    assert math.isfinite(m[key + "_se"]) and m[key + "_se"] >= 0.0, (model, pool, key)
        for pool in ("1", "25"):
            assert math.isfinite(row["network"][pool]["median_abs_log10_error"])
    assert set(res["flattening"]) == {"1", "25"}
    md = out.with_suffix(".md").read_text()
    assert re.search(r"^\| 6 \| \d+ / \d+ / \d+ \| 25 \| ", md, re.M) and "Between the two largest training sizes" in md
    assert "cap of 3 epochs ended the training at 3, 6 draws" in md  # 3 epochs < patience 15: always the cap


@pytest.mark.slow
def test_second_run_refuses_to_overwrite(tiny_run, capsys):
    rc, out, cache = tiny_run
    before = {s: out.with_suffix(s).read_bytes() for s in (".json", ".md", ".png")}
    assert main(["--out", str(out), "--cache", str(cache), *TINY]) == 2
    msg = capsys.readouterr().out.strip()
    assert msg.startswith("error:") and "exists" in msg and "\n" not in msg
    assert {s: out.with_suffix(s).read_bytes() for s in before} == before


@pytest.mark.parametrize(
    "args, words",
    [
        (["--sizes", "6,3"], "increase"),
        (["--sizes", "2,6"], ">= 3"),
        (["--sizes", "3,6", "--draws-max", "4"], "--draws-max"),
        (["--gb-pixels", "-1"], "--gb-pixels"),
    ],
)
def test_bad_options_are_one_line_errors(tmp_path, capsys, args, words):
    assert main(["--out", str(tmp_path / "c.json"), *args]) == 2
    msg = capsys.readouterr().out.strip()
    assert msg.startswith("error:") and words in msg and not list(tmp_path.iterdir())
