"""MkDocs hook of the documentation site (``hooks:`` in ``mkdocs.yml``).

At build time it

* generates the command-line reference from the argparse parsers (``reference/cli/*.md``);
* generates one model card per shipped model from its training report (``models/*.md``);
* includes ``CHANGELOG.md`` as ``changelog.md``;
* replaces every ``<!-- render: NAME -->`` line of a page by the table of a results file
  (``docs/hooks/results.py``), so no measured number is typed into a page;
* drops from the navigation the optional pages that are not in ``docs/`` (pages other parts of the
  project add), so the site builds with or without them;
* refuses a ``README.md`` that is no longer a front page, and a link of the repository's Markdown outside
  ``docs/`` to a file that does not exist (``docs/hooks/frontpage.py``): checked where the site is built, so
  no test reads the READMEs.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))

import cli_ref  # noqa: E402
import frontpage  # noqa: E402
import models  # noqa: E402
import results  # noqa: E402

ROOT = HERE.parents[1]

#: Pages shown in the navigation only when the file exists in docs/ at build time.
OPTIONAL = {
    "reliability.md",
    "formats.md",
    "napari.md",
    "concepts/speckle-motion.md",
    "abstention.md",
    "benchmarks/grid.md",
}

#: The public API by stage: (page, title, what it is, modules). A module that moved into a subpackage is
#: found by its last name (``torchdoct.figures`` -> ``torchdoct.plot.figures``); one that is gone is left out.
API = [
    (
        "simulation",
        "Simulation",
        "Scenes, plans, the simulator, metrics, the decorrelation signature and the "
        "closed forms they are tested against.",
        [
            "torchdoct.sim.config",
            "torchdoct.sim.scenes",
            "torchdoct.sim.plan",
            "torchdoct.sim.simulate",
            "torchdoct.sim.metrics",
            "torchdoct.sim.signature",
            "torchdoct.sim.theory",
            "torchdoct.sim.kernel",
        ],
    ),
    (
        "images",
        "Phantoms and rendering",
        "Phantom files and the image renderer.",
        ["torchdoct.image.phantom", "torchdoct.image.render"],
    ),
    (
        "measured",
        "Measured data",
        "Readers, resolution reduction, bulk-phase correction, the Doppler reference, DOCT maps and statistics.",
        [
            "torchdoct.measured.io",
            "torchdoct.measured.sequence",
            "torchdoct.measured.resolution",
            "torchdoct.measured.bulkphase",
            "torchdoct.measured.doppler",
            "torchdoct.measured.maps",
            "torchdoct.measured.mapsfile",
            "torchdoct.measured.compare",
            "torchdoct.measured.formats",
            "torchdoct.measured.guards",
        ],
    ),
    (
        "study",
        "Sweeps and the study",
        "Parameter sweeps and the reference paper's numerical study.",
        ["torchdoct.study.sweep", "torchdoct.study.run", "torchdoct.study.claims"],
    ),
    (
        "ground-floor",
        "Conventions and utilities",
        "Units and resolution conventions, optics, threads, figures, resources and files.",
        [
            "torchdoct.conventions",
            "torchdoct.optics",
            "torchdoct.runtime.threads",
            "torchdoct.figures",
            "torchdoct.runtime.resources",
            "torchdoct.runtime.interrupt",
            "torchdoct.runtime.machine",
            "torchdoct.files",
            "torchdoct.measured.imagej",
        ],
    ),
    (
        "classifier",
        "Classifier",
        "Classify maps (numpy and onnxruntime only), decide or abstain, train, match a system, translate.",
        [
            "classifier.infer",
            "classifier.outputs",
            "classifier.pooling",
            "classifier.rule",
            "classifier.conformal",
            "classifier.calibrate",
            "classifier.ambiguity",
            "classifier.features",
            "classifier.matching",
            "classifier.own_system",
            "classifier.prior",
            "classifier.truth",
            "classifier.simulation",
            "classifier.dataset",
            "classifier.train",
            "classifier.export",
            "classifier.report",
            "classifier.evaluation",
            "classifier.evaluate_images",
            "classifier.translate",
        ],
    ),
]


def _module_path(mod: str) -> str | None:
    """The dotted name of ``mod`` as it is in the checkout, following a move into a subpackage."""
    parts = mod.split(".")
    for cand in (ROOT.joinpath(*parts).with_suffix(".py"), ROOT.joinpath(*parts) / "__init__.py"):
        if cand.is_file():
            return mod
    pkg, last = ROOT / parts[0], parts[-1]
    hits = sorted(p for p in pkg.rglob(f"{last}.py") if "__pycache__" not in p.parts)
    hits += sorted(p.parent for p in pkg.rglob("__init__.py") if p.parent.name == last)
    if len(hits) == 1:
        rel = hits[0].relative_to(ROOT)
        return ".".join(rel.with_suffix("").parts if rel.suffix else rel.parts)
    return None


def _api_pages() -> dict[str, str]:
    pages, rows = {}, []
    for slug, title, what, mods in API:
        found = [m for m in (_module_path(x) for x in mods) if m]
        body = [f"# {title}", "", what, ""]
        body += [f"::: {m}\n" for m in found]
        pages[f"reference/api/{slug}.md"] = "\n".join(body)
        rows.append([f"[{title}]({slug}.md)", what, ", ".join(f"`{m}`" for m in found)])
    pages["reference/api/index.md"] = "\n".join(
        [
            "# Python API",
            "",
            "Generated from the docstrings at build time (mkdocstrings). Everything the command line does is one "
            "call of these functions; the names `import torchdoct as td` exposes are listed in `torchdoct.__all__`.",
            "",
            results.table(["page", "what", "modules"], rows),
            "",
        ]
    )
    return pages


_MARKER = re.compile(r"^<!-- render: ([\w-]+) -->$", re.M)


def _exit_codes() -> str:
    from torchdoct.cli import EXIT_CODES

    rows = [[str(code), text] for code, text in EXIT_CODES.items()]
    return "\n".join(
        [
            "# Command line",
            "",
            "Three programs: `torchdoct` (simulation, rendering, maps, studies, benchmarks, translation), "
            "`doct-train` (train a classifier) and `doct-classify` (classify maps). The pages below are "
            "generated from their parsers at build time.",
            "",
            *[f"- [`{n}`]({n}.md)" for n in cli_ref.names()],
            "",
            "## Exit codes (every command)",
            "",
            results.table(["code", "meaning"], rows),
            "",
            "Every command that computes takes `--threads N` (default: the usable cores, or "
            "`$TORCHDOCT_THREADS`); the numbers do not depend on it. Every long command takes "
            "`--no-progress`, and `TQDM_DISABLE=1` silences progress bars everywhere.",
            "",
        ]
    )


def _changelog() -> str:
    p = ROOT / "CHANGELOG.md"
    if p.is_file():
        return p.read_text(encoding="utf-8")
    return "# Changelog\n\nNo `CHANGELOG.md` in this checkout yet.\n"


def _generated() -> dict[str, str]:
    pages = {
        "reference/cli/index.md": _exit_codes(),
        "changelog.md": _changelog(),
        "models/index.md": models.index(ROOT),
    }
    for name in cli_ref.names():
        pages[f"reference/cli/{name}.md"] = cli_ref.page(name)
    for name in models.shipped(ROOT):
        pages[f"models/{name}.md"] = models.card(ROOT, name)
    pages.update(_api_pages())
    return pages


def _expand_nav(nav):
    """The entries the hook fills in: every model card under Models, every API page under Python API."""
    out = []
    for item in nav:
        if isinstance(item, dict):
            ((title, value),) = item.items()
            if value == "models/index.md":
                item = {title: ["models/index.md", *[{n: f"models/{n}.md"} for n in models.shipped(ROOT)]]}
            elif value == "reference/api/index.md":
                item = {title: ["reference/api/index.md", *[{t: f"reference/api/{s}.md"} for s, t, _, _ in API]]}
            elif isinstance(value, list):
                item = {title: _expand_nav(value)}
        out.append(item)
    return out


def _filter_nav(nav, docs_dir: Path):
    out = []
    for item in nav:
        if isinstance(item, dict):
            ((title, value),) = item.items()
            if isinstance(value, list):
                value = _filter_nav(value, docs_dir)
                if value:
                    out.append({title: value})
            elif value in OPTIONAL and not (docs_dir / value).is_file():
                continue
            else:
                out.append(item)
        elif isinstance(item, str) and item in OPTIONAL and not (docs_dir / item).is_file():
            continue
        else:
            out.append(item)
    return out


def on_config(config, **kwargs):
    readme = ROOT / "README.md"
    if readme.is_file():
        problems = frontpage.problems(readme.read_text(encoding="utf-8"), ROOT)
        if problems:
            raise PluginError("README.md is not a front page: " + "; ".join(problems))
    for name in frontpage.MARKDOWN:
        md = ROOT / name
        broken = frontpage.broken_links(md.read_text(encoding="utf-8"), md.parent) if md.is_file() else []
        if broken:
            raise PluginError(f"{name} links to files that are not in the repository: {', '.join(broken)}")
    if config.get("nav"):
        config["nav"] = _expand_nav(_filter_nav(config["nav"], Path(config["docs_dir"])))
    return config


#: Figures of the repository shown on the site: (folder, glob) -> assets/figures/.
FIGURES = [("notebooks/figures", "*.png")]


def on_files(files, config, **kwargs):
    for folder, pattern in FIGURES:
        for png in sorted((ROOT / folder).glob(pattern)):
            uri = f"assets/figures/{png.name}"
            if files.get_file_from_path(uri) is None:
                files.append(File.generated(config, uri, abs_src_path=str(png)))
    for uri, content in _generated().items():
        existing = files.get_file_from_path(uri)
        if existing is not None:
            files.remove(existing)
        files.append(File.generated(config, uri, content=content))
    return files


def on_page_markdown(markdown, page, config, files, **kwargs):
    return _MARKER.sub(lambda m: results.render(ROOT, m.group(1)), markdown)
