"""Progress bars: ``--no-progress`` is the same on every command, and ``TQDM_DISABLE`` silences them all."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def _leaves(parser: argparse.ArgumentParser):
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield parser
    for a in subs:
        for sp in a.choices.values():
            yield from _leaves(sp)


def test_every_command_takes_no_progress():
    from classifier.cli import build_classify_parser, build_train_parser
    from torchdoct.cli import build_parser

    leaves = [p for b in (build_parser, build_train_parser, build_classify_parser) for p in _leaves(b())]
    assert len(leaves) > 15
    missing = [p.prog for p in leaves if not any("--no-progress" in a.option_strings for a in p._actions)]
    assert not missing, missing
    for p in leaves:
        action = next(a for a in p._actions if "--no-progress" in a.option_strings)
        assert action.nargs == 0 and action.default is False, p.prog


def test_tqdm_disable_turns_off_a_bar_the_caller_asked_for(monkeypatch):
    from torchdoct.runtime.interrupt import progress_disabled

    monkeypatch.delenv("TQDM_DISABLE", raising=False)
    assert not progress_disabled(True) and progress_disabled(False)
    for value in ("1", "true", "True"):
        monkeypatch.setenv("TQDM_DISABLE", value)
        assert progress_disabled(True)


def test_no_progress_leaves_the_environment_as_it_was(monkeypatch, capsys):
    from torchdoct.cli import main

    monkeypatch.delenv("TQDM_DISABLE", raising=False)
    assert main(["scenes", "--no-progress"]) == 0
    assert "TQDM_DISABLE" not in os.environ


def _simulate(extra_args, extra_env):
    env = {k: v for k, v in os.environ.items() if not k.startswith("TQDM_")}
    env.update(TQDM_DELAY="0", PYTHONPATH=str(REPO), **extra_env)
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "torchdoct.cli",
            "simulate",
            "example",
            "--trials",
            "256",
            "--threads",
            "1",
            *extra_args,
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    return r.stderr


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under five minutes
@pytest.mark.parametrize("how", ["--no-progress", "TQDM_DISABLE"])
def test_no_progress_and_tqdm_disable_silence_a_command_that_shows_a_bar(how):
    shown = _simulate([], {})
    assert "trial" in shown and "%" in shown  # the control: with no delay the bar is drawn
    quiet = _simulate(["--no-progress"], {}) if how == "--no-progress" else _simulate([], {"TQDM_DISABLE": "1"})
    assert "%" not in quiet and "trial" not in quiet, quiet
