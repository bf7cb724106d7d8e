"""The fuzz harness's two profiles: ``short`` (the default suite: a tenth of the generated cases, at least
four per test) and ``full`` (``TORCHDOCT_FUZZ=full``: every case; ``.ci/run`` runs it after the slow suite).
Both are derandomized, so a profile always generates the same cases."""

from __future__ import annotations

import os

PROFILE = os.environ.get("TORCHDOCT_FUZZ", "short")
if PROFILE not in ("short", "full"):
    raise RuntimeError(f"TORCHDOCT_FUZZ must be short or full; got {PROFILE!r}")


def examples(n: int) -> int:
    """The ``max_examples`` of a fuzz test written for ``n`` cases under the current profile."""
    return int(n) if PROFILE == "full" else max(4, int(n) // 10)
