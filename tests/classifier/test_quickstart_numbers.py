"""The quick start of ``classifier/README.md`` reproduces: ``doct-train --quick`` from an empty cache gives
exactly the coverage and balanced accuracy the README states (the run is seed-fixed and deterministic: the
same ONNX file byte for byte), and its CPU time stays near the documented figure."""

from __future__ import annotations

import json
import re
import resource
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[2] / "classifier" / "README.md"


def _documented() -> dict[str, float]:
    text = " ".join(README.read_text(encoding="utf-8").split())
    m = re.search(r"identifiable: coverage (\d\.\d+), accuracy (\d\.\d+), balanced (\d\.\d+); ECE (\d\.\d+)", text)
    assert m, "classifier/README.md no longer states the --quick summary line"
    cpu = re.search(r"doct-train --quick --no-cache --out first/`, twice, on 2 cores beside other processes\): "
                    r"(\d+) s of CPU time", text)
    assert cpu, "classifier/README.md no longer states the --quick CPU time"
    return {"coverage_identifiable": float(m.group(1)), "accuracy_identifiable": float(m.group(2)),
            "balanced_accuracy_identifiable": float(m.group(3)), "ece": float(m.group(4)),
            "cpu_s": float(cpu.group(1))}


def test_the_readme_states_the_quick_figures():
    doc = _documented()
    assert 0 < doc["coverage_identifiable"] < 1 and 0 < doc["balanced_accuracy_identifiable"] < 1


@pytest.mark.slow
def test_doct_train_quick_reproduces_the_readme(tmp_path, capsys):
    from classifier.cli import train_main

    doc = _documented()

    def cpu_s() -> float:  # this process and its (finished) worker processes
        return sum(u.ru_utime + u.ru_stime for u in (resource.getrusage(resource.RUSAGE_SELF),
                                                     resource.getrusage(resource.RUSAGE_CHILDREN)))

    before = cpu_s()
    assert train_main(["--quick", "--no-cache", "--no-progress", "--out", str(tmp_path / "first")]) == 0
    report = json.loads((tmp_path / "first" / "single-acquisition.json").read_text())
    test = report["test"]["network"]["1"]
    for key in ("coverage_identifiable", "accuracy_identifiable", "balanced_accuracy_identifiable", "ece"):
        assert round(test[key], 3) == doc[key], (key, test[key], doc[key])  # deterministic: exact to 3 digits
    cpu = cpu_s() - before
    # CPU time varies with the machine (not the numbers): within a factor of 2.5 of the documented figure
    assert cpu < 2.5 * doc["cpu_s"], (cpu, doc["cpu_s"])
