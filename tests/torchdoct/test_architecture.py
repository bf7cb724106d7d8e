"""The architecture's rules (docs/architecture.md), checked on the source: no import circle between the
project's modules (at import time, and with the imports inside functions only through the documented
upward ones), one owner of the maps format and of the channel-optics match, no module loaded by its file
path, torch-free imports where the torch-free paths need them, long modules say why they are whole, and
the research modules (research/, outside the packages) off the product path, using public names only."""

from __future__ import annotations

import ast
import functools
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
PACKAGES = ("torchdoct", "classifier")
#: The research scripts: a top-level folder outside the installed packages.
RESEARCH = "research"


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in (*PACKAGES, RESEARCH):
        for path in sorted((REPO / pkg).rglob("*.py")):
            parts = list(path.relative_to(REPO).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


MODULES = _modules()


@functools.cache
def _tree(path: Path) -> ast.Module:
    """The syntax tree of ``path``, parsed once for all the checks (they only read it)."""
    return ast.parse(path.read_text(encoding="utf-8"))


def _module_level_imports(name: str, path: Path) -> set[str]:
    """Project modules imported by the statements that run at import time (not inside functions or
    classes' methods)."""
    tree = _tree(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()

    def visit(nodes):
        for node in nodes:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                continue
            if isinstance(node, ast.ClassDef):
                visit([n for n in node.body if not isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))])
                continue
            if isinstance(node, ast.Import):
                for alias in node.names:
                    found.add(alias.name)
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")
                    base = base[: len(base) - (node.level - 1)]
                    mod = ".".join(base + ([node.module] if node.module else []))
                else:
                    mod = node.module or ""
                for alias in node.names:
                    sub = f"{mod}.{alias.name}"
                    found.add(sub if sub in MODULES else mod)
            for field in ("body", "orelse", "finalbody", "handlers"):
                visit(getattr(node, field, []) or [])

    visit(tree.body)
    return {m for m in found if m in MODULES and m != name}


def _first_circle(graph: dict[str, set[str]]) -> list[str] | None:
    """A circle of the directed ``graph`` (depth-first, nodes in sorted order), or None."""
    state: dict[str, int] = {}  # 1 on the current path, 2 done
    stack: list[str] = []

    def walk(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt) :] + [nxt]
            if nxt not in state:
                found = walk(nxt)
                if found:
                    return found
        stack.pop()
        state[node] = 2
        return None

    for name in sorted(graph):
        if name not in state:
            found = walk(name)
            if found:
                return found
    return None


def test_no_import_circle_between_the_project_modules():
    graph = {name: _module_level_imports(name, path) for name, path in MODULES.items()}
    cycle = _first_circle(graph)
    if cycle:
        pytest.fail("import circle: " + " -> ".join(cycle))
    # the checker sees the edges it should: a known module-level import
    assert "torchdoct.measured.mapsfile" in graph["torchdoct.measured.io"]
    assert "torchdoct.optics" in graph["classifier.features"]


#: Modules that load a file by its path, and why: none of the project's own files.
LOADS_BY_PATH = {
    "torchdoct.bench.cog": "the user's clone of the external COG simulator (torchdoct bench cog --cog DIR)"
}


def test_torchdoct_never_imports_classifier():
    """At any level (functions included): the commands reach the classifier through entry points
    (torchdoct/cli/extensions.py), and classifier/bench/tradeoffs/plan.py reads no command-line parser."""
    for name, path in MODULES.items():
        tree = _tree(path)
        mods = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        mods |= {n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and not n.level}
        if name.startswith("torchdoct"):
            assert not any(m == "classifier" or m.startswith("classifier.") for m in mods), name
    plan = _tree(REPO / "classifier/bench/tradeoffs/plan.py")
    assert not any(isinstance(n, ast.ImportFrom) and (n.module or "").endswith("cli") for n in ast.walk(plan))


def test_the_classifier_fills_the_command_table():
    from importlib.metadata import entry_points

    from torchdoct.cli import extensions

    bench = {e.name: e.value for e in entry_points(group=extensions.BENCH)}
    parts = {e.name: e.value for e in entry_points(group=extensions.TRADEOFFS)}
    assert bench.get("classify") == "classifier.bench.classify"
    assert parts.get("classifier") == "classifier.bench.tradeoffs.part"
    part = extensions.load(extensions.TRADEOFFS, "classifier", command="test")
    assert all(callable(getattr(part, f)) for f in ("compute", "format_table", "plot"))
    with pytest.raises(ValueError, match="entry-point group"):
        extensions.load(extensions.BENCH, "no-such-part", command="torchdoct bench no-such-part")


def test_no_module_loads_a_project_file_by_path():
    loaders = {
        name
        for name, path in MODULES.items()
        if any(w in path.read_text(encoding="utf-8") for w in ("spec_from_file_location", "SourceFileLoader"))
    }
    assert loaders == set(LOADS_BY_PATH)


def _classes_and_functions():
    for name, path in MODULES.items():
        tree = _tree(path)
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef):
                yield name, node, [n for n in node.body if isinstance(n, ast.FunctionDef)]


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under five minutes
def test_one_maps_class_and_one_channel_optics_match():
    maps = [name for name, cls, _ in _classes_and_functions() if cls.name == "Maps"]
    assert maps == ["torchdoct.measured.mapsfile"]
    matches = {
        (name, cls.name): fn for name, cls, fns in _classes_and_functions() for fn in fns if fn.name == "matches"
    }
    assert set(matches) == {("torchdoct.optics", "ChannelOptics"), ("classifier.features", "Configuration")}
    # the spec's configuration delegates to the one match
    assert "self.optics.matches(" in ast.unparse(matches[("classifier.features", "Configuration")])
    funcs = {n.name for path in MODULES.values() for n in ast.walk(_tree(path)) if isinstance(n, ast.FunctionDef)}
    assert "_channel_matches" not in funcs


def _run(code: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)


@pytest.mark.parametrize(
    "code",
    [
        "import classifier; classifier.classify_maps; classifier.read_maps; classifier.load_model",
        "import torchdoct; import torchdoct.measured.io, torchdoct.optics, torchdoct.conventions, torchdoct.runtime.threads",
    ],
)
def test_torch_free_imports(code):
    out = _run(
        code + "\nimport sys\nbad = sorted(m for m in sys.modules if m == 'torch' or m.startswith('torch.'))\n"
        "assert not bad, bad\nprint('ok')\n"
    )
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


def test_import_torchdoct_is_lazy_but_complete():
    out = _run(
        "import sys, torchdoct\nassert 'torch' not in sys.modules\n"
        "assert callable(torchdoct.simulate) and 'torch' in sys.modules\n"
        "assert torchdoct.sim.simulate.simulate is torchdoct.simulate\nprint('ok')\n"
    )
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


def test_long_modules_say_why_they_are_whole():
    missing = []
    for name, path in MODULES.items():
        text = path.read_text(encoding="utf-8")
        if text.count("\n") > 800:
            doc = ast.get_docstring(ast.parse(text)) or ""
            if "kept whole" not in doc.lower():
                missing.append(f"{name} ({text.count(chr(10))} lines)")
    assert not missing, "over 800 lines without a 'Kept whole' reason at the top: " + ", ".join(missing)


def _all_imports(name: str, path: Path) -> dict[str, bool]:
    """Project modules imported anywhere in the module (functions included) → True when one of those
    imports runs at import time."""
    top = _module_level_imports(name, path)
    tree = _tree(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                mod = ".".join(base[: len(base) - (node.level - 1)] + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            found.update(f"{mod}.{a.name}" if f"{mod}.{a.name}" in MODULES else mod for a in node.names)
    out = {}
    for mod in found:
        while mod and mod not in MODULES:  # ``import torchdoct.sim.theory as t`` names the module
            mod = mod.rpartition(".")[0]
        if mod and mod != name:
            out[mod] = mod in top
    return out


def test_no_import_circle_counting_the_imports_inside_functions():
    """Counting the imports inside functions too (run only when the function is called), no module reaches
    itself: every import points down the import order of docs/architecture.md."""
    graph = {name: set(_all_imports(name, path)) for name, path in MODULES.items()}
    cycle = _first_circle(graph)
    if cycle:
        pytest.fail("import circle (imports inside functions included): " + " -> ".join(cycle))
    # the checker sees function-level edges: the benchmark's machine record, imported inside a function
    assert "torchdoct.runtime.machine" in graph["classifier.bench.classify"]
    # the original circle of the classifier's benchmark: torchdoct reaches classifier through entry points
    assert not any(
        b.startswith("classifier") for a, targets in graph.items() if a.startswith("torchdoct") for b in targets
    )


def test_research_modules_stay_off_the_product_path():
    """No module outside research imports it (the benchmark reaches the trade-offs part through
    the entry-point table), and the research modules use only public names of classifier and torchdoct."""
    research = {name for name in MODULES if name == RESEARCH or name.startswith(RESEARCH + ".")}
    assert {
        "research.ablation",
        "research.g1fit",
        "research.learning_curve",
        "research.spill",
        "research.systems",
        "research.translation",
    } <= research
    for name, path in MODULES.items():
        if name not in research:
            bad = sorted(m for m in _all_imports(name, path) if m in research)
            assert not bad, f"{name} (product path) imports {bad}"
    for name in sorted(research):
        tree = _tree(MODULES[name])
        package = name if MODULES[name].name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(tree):
            if not isinstance(node, ast.ImportFrom):
                continue
            if node.level:
                base = package.split(".")
                mod = ".".join(base[: len(base) - (node.level - 1)] + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod.split(".")[0] not in PACKAGES or mod == RESEARCH or mod.startswith(RESEARCH + "."):
                continue
            assert not any(part.startswith("_") for part in mod.split(".")), f"{name} imports private module {mod}"
            private = [a.name for a in node.names if a.name.startswith("_") and a.name != "__version__"]
            assert not private, f"{name} imports private names {private} from {mod}"


def test_torchdoct_keeps_at_most_six_modules_beside_its_stage_packages():
    """The top of torchdoct/ is the ground floor (conventions, optics, files, figures); the rest lives in
    stage packages (runtime/ holds the process's ground floor: threads, interrupt, device, resources,
    machine)."""
    top = sorted(p.stem for p in (REPO / "torchdoct").glob("*.py") if p.name != "__init__.py")
    assert len(top) <= 6, top
    assert {"conventions", "optics"} <= set(top)
    assert {"threads", "interrupt", "device", "resources", "machine"} <= {
        p.stem for p in (REPO / "torchdoct" / "runtime").glob("*.py")
    }


def test_every_command_goes_through_one_table():
    """Built-in and extension commands (and benchmarks) are entries of one table each, with the same names."""
    from torchdoct.cli import build_parser, commands
    from torchdoct.cli.bench import benchmarks

    table = commands()
    assert {"simulate", "render", "maps", "study", "bench", "translate"} <= set(table)
    assert {"classify", "maps", "all"} <= set(benchmarks())
    for entry in [*table.values(), *benchmarks().values()]:
        assert all(hasattr(entry, name) for name in ("HELP", "DESCRIPTION", "add_arguments", "run"))
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    assert list(sub.choices) == list(table)


def test_package_data_holds_only_the_shipped_models_and_their_reports():
    """classifier/data/ ships what the commands read: each model's ONNX file with its training report
    (.json, .md, .png of the same name) and, for a calibrated model, its conformal calibration
    (NAME.calibration.json, read by doct-classify) and reliability diagram (NAME.reliability.png);
    research reports live in research/results/."""
    data = REPO / "classifier" / "data"
    models = {p.stem for p in data.glob("*.onnx")}
    assert models
    companions = {".calibration.json", ".reliability.png"}

    def shipped(p):
        return (p.stem in models and p.suffix in (".onnx", ".json", ".md", ".png")) or any(
            p.name == m + c for m in models for c in companions
        )

    strays = sorted(p.name for p in data.iterdir() if not shipped(p))
    assert not strays, f"not a shipped model or its report: {strays}"
    assert not (REPO / "classifier" / "research").exists()


def test_research_and_reference_scripts_require_their_output_folder():
    """The research scripts and tests/reference/* write only where they are told: every ``--out`` is
    required (no default inside the package), so no run writes package data."""
    scripts = sorted((REPO / RESEARCH).glob("*.py")) + sorted((REPO / "tests" / "reference").glob("*.py"))
    outs = []
    for path in scripts:
        for node in ast.walk(_tree(path)):
            if (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Attribute)
                and node.func.attr == "add_argument"
                and node.args
                and isinstance(node.args[0], ast.Constant)
                and node.args[0].value == "--out"
            ):
                kw = {k.arg: k.value for k in node.keywords}
                outs.append(path.name)
                assert "default" not in kw, f"{path.name}: --out has a default"
                assert isinstance(kw.get("required"), ast.Constant) and kw["required"].value is True, (
                    f"{path.name}: --out must be required"
                )
    assert {"ablation.py", "g1fit.py", "learning_curve.py", "ceiling.py", "evaluate_models.py"} <= set(outs)


def test_the_commands_load_no_research_module():
    out = _run(
        "import sys\nimport classifier.cli, classifier.bench, classifier.train, classifier.export\n"
        "import torchdoct.cli, torchdoct.bench, torchdoct.cli.bench, torchdoct.cli.data, torchdoct.cli.render\n"
        "bad = sorted(m for m in sys.modules if m.startswith('research'))\n"
        "assert not bad, bad\nprint('ok')\n"
    )
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


def test_dir_of_the_packages_lists_only_their_public_api():
    """``dir(torchdoct)`` and ``dir(classifier)`` show ``__all__`` (and torchdoct's stage packages), not the
    helpers of their ``__init__`` (``importlib``, ``annotations``, the lazy tables), whatever was imported."""
    import classifier
    import torchdoct
    import torchdoct.sim.simulate

    stages = {"sim", "image", "measured", "study", "bench", "cli", "runtime", "conventions", "optics", "figures"}
    assert set(dir(torchdoct)) == set(torchdoct.__all__) | stages
    assert set(dir(classifier)) == set(classifier.__all__)
    assert not {"importlib", "annotations", "_LAZY", "_SUBMODULES"} & (set(dir(torchdoct)) | set(dir(classifier)))
    for name in set(dir(torchdoct)) | set(dir(classifier)):  # every listed name resolves
        assert getattr(torchdoct if name in dir(torchdoct) else classifier, name) is not None
