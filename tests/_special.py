"""Special files for the tests that refuse them (imported by module name, never through ``conftest``)."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest


@pytest.fixture(autouse=True)
def no_hang():
    """A command that blocks on a FIFO fails the test after 30 s instead of hanging the suite."""

    def hung(*_):
        raise AssertionError("the command blocked (opened a FIFO or read a device without end)")

    old = signal.signal(signal.SIGALRM, hung)
    signal.alarm(30)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, old)


def special(path: Path, kind: str) -> Path:
    """Make ``path`` a FIFO, a link to the endless character device ``/dev/zero``, or a directory."""
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "device":
        path.symlink_to("/dev/zero")
    else:
        path.mkdir()
    return path
