"""The accuracy-vs-time notebook runs top to bottom on a reduced measurement."""

from __future__ import annotations

from pathlib import Path

import pytest

NOTEBOOK = Path(__file__).resolve().parents[2] / "notebooks" / "accuracy_vs_time.ipynb"


@pytest.mark.slow
def test_accuracy_vs_time_notebook_runs(tmp_path, monkeypatch):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    monkeypatch.setenv("TORCHDOCT_QUICK", "1")
    monkeypatch.setenv("TORCHDOCT_BENCH_DIR", str(tmp_path / "no-bench"))
    nb = nbformat.read(NOTEBOOK, as_version=4)
    nbclient.NotebookClient(
        nb, timeout=900, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    ).execute()
    assert (tmp_path / "tradeoffs.png").stat().st_size > 1000
    outputs = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", []))
    assert "on the front" in outputs and "Error" not in outputs
