"""Packaging: one version, a base install without torch that is enough for ``doct-classify`` on maps,
extras that name what each part needs, and one line (not a traceback) when a command needs an extra."""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
import tomllib
from importlib import metadata
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.version import Version

import classifier
import torchdoct
from torchdoct.runtime.interrupt import EXTRAS

REPO = Path(__file__).resolve().parents[2]
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
PROJECT = PYPROJECT["project"]

#: Run in a subprocess first: every optional module (torchdoct.runtime.interrupt.EXTRAS) fails to import, as
#: on the base install.
BLOCK = f"""
import importlib.abc, sys
BLOCKED = {sorted(EXTRAS)!r}
class _Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
sys.meta_path.insert(0, _Block())
"""


def _run(code: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    return subprocess.run(
        [sys.executable, "-c", BLOCK + code], capture_output=True, text=True, env=env, cwd=cwd, timeout=300
    )


def _norm(name: str) -> str:
    return name.lower().replace("_", "-")


def _closure(requirements: list[str]) -> set[str]:
    """Normalised names of these requirements and of everything they require, extras included: this
    project's extras from pyproject.toml, other distributions' from their installed metadata (a
    distribution that is not installed counts by its name alone)."""
    seen: set[tuple[str, str]] = set()
    todo = [(Requirement(r), "") for r in requirements]
    names: set[str] = set()
    while todo:
        req, extra = todo.pop()
        if req.marker is not None and not req.marker.evaluate({"extra": extra}):
            continue
        name = _norm(req.name)
        for e in ("", *req.extras):
            if (name, e) in seen:
                continue
            seen.add((name, e))
            names.add(name)
            if name == "torchdoct":
                todo += [
                    (Requirement(r), "")
                    for r in (PROJECT["dependencies"] if e == "" else PROJECT["optional-dependencies"][e])
                ]
                continue
            try:
                todo += [(Requirement(r), e) for r in (metadata.requires(req.name) or [])]
            except metadata.PackageNotFoundError:
                pass
    return names


def test_one_version_from_the_metadata():
    assert torchdoct.__version__ == classifier.__version__ == PROJECT["version"]
    Version(PROJECT["version"])  # a PEP 440 version
    written = []  # the version is written once, in pyproject.toml: no package module repeats it
    for path in [*(REPO / "torchdoct").rglob("*.py"), *(REPO / "classifier").rglob("*.py")]:
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Constant) and node.value == PROJECT["version"]:
                written.append(f"{path.relative_to(REPO)}:{node.lineno}")
    assert written == [], written


def test_requirements_and_extras():
    assert PROJECT["requires-python"] == ">=3.11"
    base = {Requirement(r).name for r in PROJECT["dependencies"]}
    assert not base & {"torch", "scipy", "pandas", "pyarrow", "scikit-learn", "onnx", "dask"}, base
    assert {"numpy", "onnxruntime", "tifffile"} <= base
    extras = PROJECT["optional-dependencies"]
    assert {"sim", "train", "dask", "napari", "docs", "dev", "test", "all"} <= set(extras)
    torch_req = [Requirement(r) for r in extras["sim"] if Requirement(r).name == "torch"]
    assert len(torch_req) == 1 and torch_req[0].specifier.contains("2.13.0")  # the README's CPU pin
    assert "torchdoct[all]" in extras["test"]
    # every extra the missing-dependency line names installs that module
    dists = metadata.packages_distributions()
    for module, extra in EXTRAS.items():
        wanted = {_norm(d) for d in dists.get(module, [module])}
        assert wanted & _closure([f"torchdoct[{extra}]"]), (module, extra)
    assert not {"torch", "scipy", "pandas", "scikit-learn", "onnx"} & _closure(PROJECT["dependencies"])


@pytest.fixture(scope="module")
def signature_maps(tmp_path_factory):
    """B-scan maps with signature channels, as the README makes them (a small rendering)."""
    from torchdoct.cli import main

    tmp = tmp_path_factory.mktemp("packaging")
    seq, maps = tmp / "mt.npz", tmp / "mt-maps.npz"
    assert (
        main(
            [
                "render",
                "motion-types",
                "--grid",
                "24x24",
                "--pitch-um",
                "2",
                "--out",
                str(seq),
                "--threads",
                "1",
                "--no-progress",
                "--no-preview",
            ]
        )
        == 0
    )
    assert (
        main(
            [
                "maps",
                str(seq),
                "--resolution",
                "original",
                "--resolution",
                "axial=14",
                "--resolution",
                "lateral=18",
                "--signature",
                "--out",
                str(maps),
                "--threads",
                "1",
                "--no-progress",
            ]
        )
        == 0
    )
    return maps


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_doct_classify_runs_on_the_base_install(signature_maps, tmp_path):
    """doct-classify with the shipped default model, every optional module unimportable: it classifies,
    imports no torch, and every third-party module it loads comes with the base dependencies."""
    code = (
        "before = set(sys.modules)  # the interpreter's start-up (site's .pth hooks) is not doct-classify\n"
        f"from classifier.cli import classify_main\n"
        f"rc = classify_main([{str(signature_maps)!r}, '--out', 'out', '--threads', '1', '--json'])\n"
        "import json\n"
        "print(json.dumps({'rc': rc, 'modules': sorted({m.split('.')[0] for m in set(sys.modules) - before})}))\n"
    )
    out = _run(code, tmp_path)
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["rc"] == 0
    assert {"classes.tif", "probabilities.tif", "overlay.png", "summary.json"} <= {
        p.name for p in (tmp_path / "out").iterdir()
    }
    assert "torch" not in report["modules"]
    dists = metadata.packages_distributions()
    third_party = {m for m in report["modules"] if m in dists and m not in ("torchdoct", "classifier")}
    closure = _closure(PROJECT["dependencies"])
    outside = {m: dists[m] for m in third_party if not {_norm(d) for d in dists[m]} & closure}
    assert outside == {}, f"doct-classify imports modules outside the base install: {outside}"


def test_a_command_that_needs_an_extra_names_it(tmp_path):
    out = _run("from torchdoct.cli import main\nsys.exit(main(['simulate', 'example']))\n", tmp_path)
    assert out.returncode == 1, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "torchdoct[sim]" in lines[0], out.stderr
    assert "torch==2.13.0" in lines[0]
