"""research.dynamic_speckle: the scores of its record and its command line (the rendering is what the grid
benchmark's tests check)."""

import pytest

from research import dynamic_speckle as D


def _c(pixels, right, wrong):
    return {"pixels": pixels, "decided": right + wrong, "right": right, "wrong": wrong}


def test_scores_count_a_motion_decided_as_another_as_its_wrong_share():
    s = D.scores({"diffusion": _c(10, 6, 2), "ballistic": _c(10, 0, 0), "flow": _c(20, 20, 0)})
    pm = s["per_motion"]
    assert pm["diffusion"]["coverage"] == pytest.approx(0.8) and pm["diffusion"]["wrong_share"] == pytest.approx(0.2)
    assert pm["diffusion"]["recall"] == pytest.approx(0.75) and pm["ballistic"]["recall"] is None
    assert s["coverage"] == pytest.approx((8 + 0 + 20) / 40)  # over the motions' pixels
    # a motion never decided counts for coverage, not for accuracy
    assert s["balanced_accuracy"] == pytest.approx((0.75 + 1) / 2)
    assert s["worst_wrong_share"] == pytest.approx(0.2)


def test_the_report_names_every_part_window_and_variant_and_the_command():
    per = {m: {"coverage": 0.5, "recall": 1.0, "wrong_share": 0.0, "pixels": 4} for m in D.MOTIONS}
    entry = {
        "per_motion": per,
        "coverage": 0.5,
        "balanced_accuracy": 1.0,
        "worst_wrong_share": 0.0,
        "worst_cell": 0.0,
        "worst_cell_key": "k",
        "cells_over": 0,
    }
    res = {
        "cell_wrong_max": D.CELL_WRONG_MAX,
        "parts": {
            "volume-background": {
                "windows": {str(w): dict.fromkeys(D.VARIANTS, entry) for w in D.POOLS},
                "seconds": {"signature_maps": 10.0, "dynamic_channels": 5.0},
            }
        },
        "seconds": 60.0,
        "command": "python -m research.dynamic_speckle --out DIR --parts volume-background",
    }
    md = D.format_md(res)
    assert md.count("| volume-background |") == 2 * len(D.POOLS) + 1  # both variants per window, and the time row
    assert "| volume-background | 10 | 5 | 0.50 |" in md
    assert "Reproduce: `python -m research.dynamic_speckle --out DIR --parts volume-background`" in md


@pytest.mark.parametrize("parts", ["volume-nowhere", "volume-none,volume-none", ""])
def test_unknown_or_repeated_parts_are_refused(tmp_path, parts):
    with pytest.raises(SystemExit):
        D.main(["--out", str(tmp_path), "--parts", parts])
    assert not (tmp_path / "dynamic-speckle.json").exists()
