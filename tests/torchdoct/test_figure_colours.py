"""Figures are readable by colour-blind readers: classes take the Okabe–Ito colours, the ground truth of a
rendered phantom and the classifier's output share them, and continuous maps use perceptual colour maps."""

from __future__ import annotations

import numpy as np
import pytest

from torchdoct import figures

OKABE_ITO = {"#000000", "#E69F00", "#56B4E9", "#009E73", "#F0E442", "#0072B2", "#D55E00", "#CC79A7"}


def test_the_palette_is_the_okabe_ito_set():
    assert {c.upper() for c in figures.OKABE_ITO.values()} == OKABE_ITO


def test_class_and_ground_truth_colours_are_okabe_ito_and_distinct():
    assert {c.upper() for c in figures.CLASS_COLORS.values()} <= OKABE_ITO
    assert {c.upper() for c in figures.LABEL_COLORS.values()} <= OKABE_ITO
    assert len(set(figures.CLASS_COLORS.values())) == len(figures.CLASS_COLORS)
    moving = {k: v for k, v in figures.LABEL_COLORS.items() if k != "static"}
    assert len(set(moving.values())) == len(moving)


def test_ground_truth_and_classification_share_the_colour_of_each_motion():
    from classifier.outputs import CLASS_COLORS, MASKED_COLOR
    from torchdoct.image.phantom import MOTION_CODES
    from torchdoct.image.render import _LABEL_COLOURS

    for motion in ("diffusion", "ballistic", "flow"):
        assert _LABEL_COLOURS[MOTION_CODES[motion]] == CLASS_COLORS[motion] == figures.CLASS_COLORS[motion]
    # static tissue does not decorrelate: the classifier calls it indeterminate, and it is drawn so
    assert _LABEL_COLOURS[MOTION_CODES["static"]] == CLASS_COLORS["indeterminate"]
    # empty pixels and masked pixels: black in both
    assert _LABEL_COLOURS[MOTION_CODES["empty"]].upper() == MASKED_COLOR.upper() == "#000000"


@pytest.mark.parametrize("name", [figures.CONTINUOUS_CMAP, figures.MAGNITUDE_CMAP])
def test_continuous_colour_maps_are_perceptual(name):
    """Lightness (CIE L*, from sRGB) rises monotonically along the map: no hue-only scale, readable in grey."""
    import matplotlib

    assert name in ("viridis", "cividis")
    rgb = np.asarray(matplotlib.colormaps[name](np.linspace(0, 1, 64)))[:, :3]
    lin = np.where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055) ** 2.4)
    y = lin @ np.array([0.2126, 0.7152, 0.0722])
    lightness = np.where(y > (6 / 29) ** 3, 116 * np.cbrt(y) - 16, y * (29 / 3) ** 3)
    assert np.all(np.diff(lightness) > 0)


def test_maps_pseudo_colour_is_the_perceptual_map_and_flags_lie_outside_it():
    import matplotlib

    from torchdoct.measured.maps import FLAG_RGB, pseudo_color

    values = np.linspace(0, 1, 50)[None, :]
    rgb = pseudo_color(values, None, value_range=(0, 1))
    want = np.round(np.asarray(matplotlib.colormaps[figures.CONTINUOUS_CMAP](values[0]))[:, :3] * 255)
    assert np.array_equal(rgb[0].astype(int), want.astype(int))
    lut = np.round(np.asarray(matplotlib.colormaps[figures.CONTINUOUS_CMAP](np.linspace(0, 1, 256)))[:, :3] * 255)
    assert np.min(np.abs(lut - np.array(FLAG_RGB)).sum(axis=1)) > 60
