"""Citations of the physics reference point to a file of the repository and to sections it has."""

from __future__ import annotations

import json
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
PHYSICS = REPO / "docs" / "physics.md"
_CITE = re.compile(r"physics\.md\s*((?:[,\s]*§?\s*\d+(?:\.\d+)?(?:\s*[-–]\s*\d+(?:\.\d+)?)?)+)")


def _sections() -> set[str]:
    heads = re.findall(r"(?m)^#{2,3} (\d+(?:\.\d+)?)\.? ", PHYSICS.read_text(encoding="utf-8"))
    return set(heads)


def _cited(text: str) -> list[str]:
    return [n for m in _CITE.finditer(text) for n in re.findall(r"\d+(?:\.\d+)?", m.group(1))]


def test_physics_reference_is_in_the_repository_with_every_cited_section():
    assert PHYSICS.is_file(), "docs/physics.md is cited by the package and must be in the repository"
    have = _sections()
    assert {"1", "2.4", "3", "5.1", "5.3", "5.4", "5.5", "5.7", "10.2", "11"} <= have
    files = [
        p
        for d in ("torchdoct", "classifier")
        for p in sorted((REPO / d).rglob("*"))
        if p.suffix in (".py", ".md", ".toml") and p.is_file()
    ]
    files += [p for p in sorted((REPO / "docs").rglob("*.md")) if "hooks" not in p.parts]  # the site's pages
    missing = {}
    n = 0
    for p in files:
        for sec in _cited(p.read_text(encoding="utf-8")):
            n += 1
            if sec not in have:
                missing.setdefault(str(p.relative_to(REPO)), []).append(sec)
    assert n > 20 and not missing, missing


#: An absolute file-system path (a machine's directories); URLs do not match.
_ABSOLUTE = re.compile(r"(?<![\w:/.)\]²³])/(?:[A-Za-z0-9_.-]+/){2,}")


def test_physics_reference_speaks_only_of_the_project():
    """No absolute file-system path (a machine's directories) in the reference; URLs are fine."""
    text = PHYSICS.read_text(encoding="utf-8")
    assert _ABSOLUTE.search("see /home/user/docs/x.md") and not _ABSOLUTE.search("https://example.org/a/b/")
    assert not _ABSOLUTE.search(text), _ABSOLUTE.findall(text)


def test_recorded_results_name_no_path_of_the_machine_they_ran_on():
    """The recorded runs (benchmarks, floors, reference data, research results, the shipped models' reports) and
    the packages' text files name their commands with the repository's paths or a placeholder (``--out DIR``),
    never the directories of the machine that recorded them."""
    folders = ("docs", "tests/floors", "tests/reference/data", "research/results", "classifier", "torchdoct")
    files = [
        p
        for d in folders
        for p in sorted((REPO / d).rglob("*"))
        if p.suffix in (".json", ".md", ".csv", ".toml", ".txt") and p.is_file()
    ]
    assert len(files) > 100
    found = {str(p.relative_to(REPO)): _ABSOLUTE.findall(p.read_text(encoding="utf-8")) for p in files}
    assert not {k: v for k, v in found.items() if v}


def test_the_legend_cites_the_repository_file(tmp_path):
    """(The READMEs' links are checked by the documentation build: ``docs/hooks/frontpage.py``.)"""
    from types import SimpleNamespace

    from classifier.infer import load_model
    from classifier.outputs import _legend

    model = load_model(None, threads=1)  # a shipped model: its metadata rule cites the reference
    assert "physics.md" in model.rule["definition"]
    res = SimpleNamespace(model=model, classes=model.classes, info={"min_probability": 0.5}, axes="ZX", pitch_um=None)
    legend = json.dumps(_legend(res), ensure_ascii=False)
    assert "docs/physics.md §5.3-5.4" in legend and not re.search(r"(?<!docs/)physics\.md", legend), legend
