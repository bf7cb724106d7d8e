"""The README is a front page, and the repository's Markdown outside the site links to files that exist; the
documentation build (``docs/hooks/site.py``) refuses a README or a link that is not.

The policy is checked where the site is built (``mkdocs build --strict`` in CI), so no test reads the READMEs.
"""

from __future__ import annotations

import re
from pathlib import Path

#: The README is a front page: what it is, one picture, install, the two commands, a short example, links.
README_MAX_LINES = 300
#: The two commands of the front page: install and run the main job; install and run the tests (.ci/run runs it).
FRONT_PAGE_COMMANDS = (
    'pip install torch==2.13.0 ".[all]" && torchdoct simulate example',
    'pip install torch==2.13.0 ".[test]" && python -m pytest',
)
_PICTURE = re.compile(r"!\[[^\]]*\]\(([^)]+\.png)\)")
_TIMING = re.compile(r"\b\d+(?:\.\d+)?\s?(?:ms|s|min|h)\b(?![\w/])")
_SCORE = re.compile(r"\b0\.\d{2,}\b")
#: The Markdown files of the repository outside ``docs/`` whose relative links must resolve.
MARKDOWN = ("README.md", "CONTRIBUTING.md", "classifier/README.md", "research/README.md")
_LINK = re.compile(r"\]\(([^)\s]+)\)")


def problems(text: str, root: Path) -> list[str]:
    """What keeps ``text`` (a README under ``root``) from being a front page; empty when it is one.
    Measured figures (timings, scores) belong to the results files the site renders."""
    out: list[str] = []
    if len(text.splitlines()) > README_MAX_LINES:
        out.append(f"{len(text.splitlines())} lines, more than {README_MAX_LINES}")
    out += [f"the command `{c}` is missing" for c in FRONT_PAGE_COMMANDS if c not in text]
    picture = _PICTURE.search(text)
    if picture is None:
        out.append("no picture")
    elif not (root / picture.group(1)).is_file():
        out.append(f"its picture {picture.group(1)} is not in the repository")
    figures = _TIMING.findall(text) + _SCORE.findall(text)
    if figures:
        out.append(f"measured figures typed into it ({', '.join(figures)}): render them from a results file")
    return out


def broken_links(text: str, folder: Path) -> list[str]:
    """The relative links of Markdown ``text`` (a file in ``folder``) whose target is not in the repository
    (web links and in-page anchors are not checked)."""
    out = []
    for target in _LINK.findall(text):
        if "://" in target or target.startswith(("#", "mailto:")):
            continue
        path = target.split("#", 1)[0]
        if path and not (folder / path).exists():
            out.append(target)
    return out
