"""The OCDS pair check (torchdoct.sim.config.delay_pair_counts) counts a uniform protocol's frame pairs per
delay without listing its N·(N − 1)/2 pairs (the maps check every slab's OCDS: a listing grew as N², gigabytes
and minutes per check for thousands of frames), and gives the counts the delay grouping gives."""

from __future__ import annotations

import numpy as np
import pytest

from torchdoct.conventions import delay_groups
from torchdoct.sim import config


@pytest.mark.parametrize(
    "times",
    [
        [k * 0.2048 for k in range(40)],
        [float(v) for v in np.arange(40, dtype=np.float32) * np.float32(0.0123)],  # single-precision steps
        [0.0, 0.1, 0.25, 0.3, 0.7, 0.75],  # not uniform: grouped from the pairs
    ],
    ids=["uniform", "uniform-float32", "irregular"],
)
def test_pair_counts_are_those_of_the_delay_grouping(times):
    assert config.delay_pair_counts(times) == [(d, len(ij)) for d, ij in delay_groups(times)]


def test_a_long_uniform_protocol_is_counted_without_listing_its_pairs(monkeypatch):
    def listed(_):
        raise AssertionError("the pairs of a uniform protocol were listed")

    monkeypatch.setattr(config, "delay_groups", listed)
    counts = config.delay_pair_counts([k * 0.2048 for k in range(20000)])
    assert len(counts) == 19999 and counts[0] == (0.2048, 19999) and counts[-1][1] == 1
    config.check_ocds_pairs([k * 0.2048 for k in range(20000)], (0.2048, 1.2288))  # enough pairs: no error
