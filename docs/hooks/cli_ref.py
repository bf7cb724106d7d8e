"""The command-line reference, generated from the argparse parsers themselves, so it cannot drift."""

from __future__ import annotations

import argparse

from results import cell


def _parsers() -> dict[str, tuple[str, argparse.ArgumentParser]]:
    from classifier.cli import build_classify_parser, build_train_parser
    from torchdoct.cli import build_parser

    return {
        "torchdoct": ("torchdoct", build_parser()),
        "doct-train": ("doct-train", build_train_parser()),
        "doct-classify": ("doct-classify", build_classify_parser()),
    }


def _arg_row(parser: argparse.ArgumentParser, a: argparse.Action) -> list[str]:
    fmt = parser._get_formatter()
    if a.option_strings:
        name = ", ".join(f"`{o}`" for o in a.option_strings)
        if a.nargs != 0:
            metavar = fmt._format_args(a, a.dest.upper())
            name += f" `{metavar}`"
    else:
        name = f"`{a.metavar or a.dest}`"
    helptext = fmt._expand_help(a) if a.help else ""
    if a.choices and not isinstance(a, argparse._SubParsersAction):
        helptext += f" (one of: {', '.join(f'`{c}`' for c in a.choices)})"
    default = ""
    if a.default not in (None, False, argparse.SUPPRESS) and a.nargs != 0 and a.option_strings:
        default = f"`{a.default}`"
    if getattr(a, "required", False) and a.option_strings:
        default = "required"
    return [name, cell(helptext), default]


def _section(parser: argparse.ArgumentParser, level: int, summary: str = "") -> list[str]:
    out = [f"{'#' * level} `{parser.prog}`", ""]
    if summary:
        out += [summary[0].upper() + summary[1:] + ".", ""]
    if parser.description and parser.description != summary:
        out += [parser.description, ""]
    out += ["```text", parser.format_usage().replace("usage: ", "").strip(), "```", ""]
    rows = [
        _arg_row(parser, a)
        for a in parser._actions
        if not isinstance(a, (argparse._HelpAction, argparse._SubParsersAction))
    ]
    if rows:
        out += ["| argument | what it does | default |", "|---|---|---|"]
        out += ["| " + " | ".join(r) + " |" for r in rows] + [""]
    if parser.epilog:
        out += [parser.epilog, ""]
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            helps = {c.dest: c.help or "" for c in a._choices_actions}
            for name, sub in a.choices.items():
                out += _section(sub, min(level + 1, 4), helps.get(name, ""))
    return out


def page(name: str) -> str:
    prog, parser = _parsers()[name]
    out = [
        f"# `{prog}`",
        "",
        f"Generated at build time from the parser of `{prog}`; `{prog} --help` prints the same. "
        "Exit codes are on the [command line page](index.md).",
        "",
    ]
    body = _section(parser, 2)
    return "\n".join(out + body[2:])


def names() -> list[str]:
    return list(_parsers())
