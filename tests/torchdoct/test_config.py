"""Scene validation, round trips and file loading (torchdoct.sim.config, torchdoct.sim.scenes)."""

from __future__ import annotations

import copy
import json
from collections.abc import Callable
from typing import Any

import pytest

import torchdoct
from torchdoct import SceneError, load_scene, make_plan, scene_from_dict, shipped_scenes


def _base() -> dict[str, Any]:
    """A valid scene in the file schema: one system, 32 frames at 0.2048 s, one diffusing population."""
    return {
        "name": "base",
        "system": [{"name": "840nm", "wavelength_um": 0.84, "lateral_resolution_um": 4.9, "axial_resolution_um": 3.8}],
        "protocol": {"n_frames": 32, "frame_interval_s": 0.2048},
        "population": [{"density_per_um3": 0.055, "motion": [{"kind": "diffusion", "diffusion_um2_per_s": 0.1}]}],
        "analysis": {"metrics": ["liv", "ocds"]},
    }


# ----------------------------------------------------------------------------------------------------------
# shipped scenes and round trips
# ----------------------------------------------------------------------------------------------------------
SHIPPED = sorted(shipped_scenes())


def test_shipped_scenes_are_listed():
    assert "example" in SHIPPED and len(SHIPPED) >= 2
    for path in shipped_scenes().values():
        assert path.is_file() and path.suffix == ".toml"


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_scene_loads_plans_and_round_trips(name):
    scene = load_scene(name)
    assert scene == load_scene(shipped_scenes()[name])  # by name and by path
    assert scene.name == name
    plan = make_plan(scene)
    assert plan.n_frames == scene.protocol.n_frames
    assert len(plan.systems) == len(scene.systems)
    assert len(plan.populations) == len(scene.populations)
    # to_dict is plain data: survives JSON and rebuilds an equal scene
    data = scene.to_dict()
    assert scene_from_dict(data) == scene
    assert scene_from_dict(json.loads(json.dumps(data))) == scene


def test_python_scene_round_trips(small_scene):
    assert scene_from_dict(small_scene.to_dict()) == small_scene


def test_round_trip_with_frame_times_noise_and_all_motion_kinds():
    data = _base()
    data["protocol"] = {"n_frames": 4, "frame_times_s": [0.0, 0.25, 0.75, 1.5]}
    data["population"][0]["motion"] += [
        {"kind": "ballistic", "speed_um_per_s": 2.0, "directions": "uniform-angles"},
        {"kind": "flow", "speed_um_per_s": 1.0, "polar_angle_deg": 30.0, "azimuth_deg": -10.0},
    ]
    data["population"].append({"name": "static", "density_per_um3": 0.01, "reflectivity": 0.5})
    data["noise"] = {"snr_db": 25.0}
    # no "ocds": its delays here rest on one frame pair each (refused, test_degenerate_ocds.py)
    data["analysis"] = {
        "metrics": ["liv", "autocorrelation"],
        "ocds_delay_range_s": [0.25, 1.5],
        "ocds_scale": "linear",
        "ocds_estimator": "biased",
    }
    data["simulation"] = {"trials": 10, "seed": 3, "truncation_tolerance": 1e-4, "dtype": "float64"}
    scene = scene_from_dict(data)
    assert scene.protocol.frame_times_s == (0.0, 0.25, 0.75, 1.5)
    assert scene_from_dict(scene.to_dict()) == scene
    make_plan(scene)


def test_scene_file_loads_and_name_defaults_to_file_stem(tmp_scene_file, small_scene):
    scene = load_scene(tmp_scene_file)
    expected = small_scene.replace(
        name="small-file", description=scene.description, simulation=torchdoct.SimulationSettings(trials=64, seed=7)
    )
    assert scene == expected
    text = tmp_scene_file.read_text().replace('name = "small-file"\n', "", 1)
    unnamed = tmp_scene_file.with_name("unnamed-scene.toml")
    unnamed.write_text(text)
    assert load_scene(unnamed).name == "unnamed-scene"


# ----------------------------------------------------------------------------------------------------------
# validation errors: type, key path, and an actionable hint
# ----------------------------------------------------------------------------------------------------------
def _set(*path_and_value) -> Callable[[dict], None]:
    *path, key, value = path_and_value

    def f(d):
        for p in path:
            d = d[p]
        d[key] = value

    return f


def _pop(*path) -> Callable[[dict], None]:
    *path, key = path

    def f(d):
        for p in path:
            d = d[p]
        del d[key]

    return f


def _chain(*fs) -> Callable[[dict], None]:
    def f(d):
        for g in fs:
            g(d)

    return f


def _dup_system(d):
    d["system"].append(dict(d["system"][0]))


# id, mutation, error type, fragments the message must contain (key path first, then the hint)
CASES = [
    (
        "unknown-top-level-key",
        _set("colour", "red"),
        SceneError,
        ["scene", "'colour'", "unknown key", "allowed keys are", "'population'"],
    ),
    (
        "unknown-system-key",
        _set("system", 0, "wavelength_nm", 840),
        SceneError,
        ["system[0]", "'wavelength_nm'", "allowed keys are", "'wavelength_um'"],
    ),
    (
        "unknown-population-key",
        _set("population", 0, "density", 0.05),
        SceneError,
        ["population[0]", "'density'", "allowed keys are", "'density_per_um3'"],
    ),
    (
        "unknown-motion-key",
        _set("population", 0, "motion", 0, "speed_um_per_s", 1.0),
        SceneError,
        ["population[0].motion[0]", "'speed_um_per_s'", "allowed keys are", "'diffusion_um2_per_s'"],
    ),
    (
        "string-wavelength",
        _set("system", 0, "wavelength_um", "0.84"),
        TypeError,
        ["system[0].wavelength_um", "must be a number", "str"],
    ),
    (
        "bool-resolution",
        _set("system", 0, "axial_resolution_um", True),
        TypeError,
        ["system[0].axial_resolution_um", "must be a number", "bool"],
    ),
    ("string-n-frames", _set("protocol", "n_frames", "32"), TypeError, ["protocol.n_frames", "must be an integer"]),
    (
        "zero-lateral-resolution",
        _set("system", 0, "lateral_resolution_um", 0),
        SceneError,
        ["system[0].lateral_resolution_um", "must be > 0", "positive"],
    ),
    (
        "negative-axial-resolution",
        _set("system", 0, "axial_resolution_um", -3.8),
        SceneError,
        ["system[0].axial_resolution_um", "must be > 0", "positive"],
    ),
    ("one-frame", _set("protocol", "n_frames", 1), SceneError, ["protocol.n_frames", "must be >= 2", "got 1"]),
    (
        "ocds-range-outside-protocol",
        _set("analysis", "ocds_delay_range_s", [10, 20]),
        SceneError,
        [
            "analysis.ocds_delay_range_s",
            "[10.0, 20.0]",
            "0 frame delay",
            "6.3488",
            "widen the range or lengthen the protocol",
        ],
    ),
    (
        "ocds-range-reversed",
        _set("analysis", "ocds_delay_range_s", [1.0, 0.5]),
        SceneError,
        ["analysis.ocds_delay_range_s", "max must exceed min"],
    ),
    (
        "frame-times-not-increasing",
        _chain(
            _pop("protocol", "frame_interval_s"),
            _set("protocol", "n_frames", 3),
            _set("protocol", "frame_times_s", [0.0, 0.4, 0.2]),
        ),
        SceneError,
        ["protocol.frame_times_s", "strictly increasing"],
    ),
    (
        "frame-times-repeated",
        _chain(
            _pop("protocol", "frame_interval_s"),
            _set("protocol", "n_frames", 3),
            _set("protocol", "frame_times_s", [0.0, 0.4, 0.4]),
        ),
        SceneError,
        ["protocol.frame_times_s", "strictly increasing"],
    ),
    (
        "frame-times-length-mismatch",
        _chain(
            _pop("protocol", "frame_interval_s"),
            _set("protocol", "n_frames", 3),
            _set("protocol", "frame_times_s", [0.0, 0.2, 0.4, 0.6]),
        ),
        SceneError,
        ["protocol.frame_times_s", "4 entries", "n_frames = 3", "make n_frames equal"],
    ),
    (
        "both-interval-and-times",
        _set("protocol", "frame_times_s", [0.2048 * i for i in range(32)]),
        SceneError,
        ["protocol", "exactly one of frame_interval_s and frame_times_s", "fix:"],
    ),
    (
        "neither-interval-nor-times",
        _pop("protocol", "frame_interval_s"),
        SceneError,
        ["protocol", "exactly one of frame_interval_s and frame_times_s", "fix:"],
    ),
    (
        "unknown-motion-kind",
        _set("population", 0, "motion", 0, "kind", "swim"),
        SceneError,
        ["population[0].motion[0].kind", "must be one of", "'diffusion'", "'ballistic'", "'flow'", "'swim'"],
    ),
    (
        "motion-without-kind",
        _pop("population", 0, "motion", 0, "kind"),
        SceneError,
        ["population[0].motion[0]", "missing key 'kind'", 'kind = "diffusion"'],
    ),
    (
        "motion-missing-parameter",
        _pop("population", 0, "motion", 0, "diffusion_um2_per_s"),
        SceneError,
        ["population[0].motion[0]", "missing required key", "'diffusion_um2_per_s'"],
    ),
    (
        "flow-missing-speed",
        _set("population", 0, "motion", [{"kind": "flow", "polar_angle_deg": 45.0}]),
        SceneError,
        ["population[0].motion[0]", "missing required key", "'speed_um_per_s'"],
    ),
    (
        "negative-diffusion",
        _set("population", 0, "motion", 0, "diffusion_um2_per_s", -0.1),
        SceneError,
        ["population[0].motion[0].diffusion_um2_per_s", "must be >= 0", "non-negative"],
    ),
    ("duplicate-system-names", _dup_system, SceneError, ["system.name", "duplicate", "'840nm'", "unique name"]),
    ("no-systems", _set("system", []), SceneError, ["system", "at least one [[system]]", "add a [[system]]"]),
    (
        "no-populations",
        _set("population", []),
        SceneError,
        ["population", "at least one [[population]]", "add a [[population]]"],
    ),
    ("missing-system-table", _pop("system"), SceneError, ["scene", "missing required key", "'system'"]),
    (
        "wavelength-in-nm",
        _set("system", 0, "wavelength_um", 840),
        SceneError,
        ["system[0].wavelength_um", "840", "micrometres", "0.84"],
    ),
    (
        "unknown-metric",
        _set("analysis", "metrics", ["liv", "speed"]),
        SceneError,
        ["analysis.metrics[1]", "'speed'", "must be one of", "'liv'", "'ocds'"],
    ),
    ("metric-twice", _set("analysis", "metrics", ["liv", "liv"]), SceneError, ["analysis.metrics", "twice"]),
    (
        "density-per-mm3",
        _set("population", 0, "density_per_um3", 5.5e7),
        SceneError,
        ["population[0].density_per_um3", "per cubic micrometre"],
    ),
    (
        "zero-lateral-y-resolution",
        _set("system", 0, "lateral_resolution_y_um", 0),
        SceneError,
        ["system[0].lateral_resolution_y_um", "must be > 0", "positive"],
    ),
    (
        "string-lateral-y-resolution",
        _set("system", 0, "lateral_resolution_y_um", "4.9"),
        TypeError,
        ["system[0].lateral_resolution_y_um", "must be a number", "str"],
    ),
    (
        "lateral-y-resolution-in-nm",
        _set("system", 0, "lateral_resolution_y_um", 4.9e4),
        SceneError,
        ["system[0].lateral_resolution_y_um", "larger than 1 cm", "micrometres"],
    ),
    (
        "unknown-truncation-mode",
        _set("simulation", {"truncation": "smooth"}),
        SceneError,
        ["simulation.truncation", "must be one of", "'hard'", "'taper'", "'smooth'"],
    ),
]


@pytest.mark.parametrize("mutate, error, fragments", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_invalid_scene_dict(mutate, error, fragments):
    data = copy.deepcopy(_base())
    mutate(data)
    with pytest.raises(error) as info:
        scene_from_dict(data)
    assert type(info.value) is error
    msg = str(info.value)
    assert msg.startswith(fragments[0]), msg  # the key path leads the message
    for frag in fragments:
        assert frag in msg, f"{frag!r} not in {msg!r}"


def test_scene_error_is_a_value_error():
    assert issubclass(SceneError, ValueError)


def test_bug_key_path_survives_a_dot_in_the_system_name():
    # A system named "1.3um" must still be reported as system[0].<key>; currently config._build splits
    # the message at the first "." (inside the name) and produces "system[0].3um'].lateral_resolution_um".
    data = _base()
    data["system"][0]["name"] = "1.3um"
    data["system"][0]["lateral_resolution_um"] = 0
    with pytest.raises(SceneError) as info:
        scene_from_dict(data)
    assert str(info.value).startswith("system[0].lateral_resolution_um:"), str(info.value)


# non-finite values through TOML's own nan / inf literals
TOML_CASES = [
    ("nan-resolution", "axial_resolution_um = 3.8", "axial_resolution_um = nan", "system[0].axial_resolution_um"),
    ("inf-density", "density_per_um3 = 0.055", "density_per_um3 = inf", "population[0].density_per_um3"),
    ("minus-inf-interval", "frame_interval_s = 0.2048", "frame_interval_s = -inf", "protocol.frame_interval_s"),
    (
        "nan-diffusion",
        "diffusion_um2_per_s = 0.1",
        "diffusion_um2_per_s = nan",
        "population[0].motion[0].diffusion_um2_per_s",
    ),
    (
        "nan-delay-range",
        "ocds_delay_range_s = [0.2048, 0.6144]",
        "ocds_delay_range_s = [0.2048, nan]",
        "analysis.ocds_delay_range_s[1]",
    ),
]


@pytest.mark.parametrize("old, new, key_path", [c[1:] for c in TOML_CASES], ids=[c[0] for c in TOML_CASES])
def test_non_finite_toml_values(tmp_scene_file, old, new, key_path):
    text = tmp_scene_file.read_text()
    assert old in text
    tmp_scene_file.write_text(text.replace(old, new, 1))
    with pytest.raises(SceneError) as info:
        load_scene(tmp_scene_file)
    msg = str(info.value)
    assert msg.startswith(f"{tmp_scene_file.name}: {key_path}"), msg
    assert "must be a finite number" in msg and "give a finite value" in msg


def test_unknown_key_in_file_names_file_and_key(tmp_scene_file):
    tmp_scene_file.write_text(
        tmp_scene_file.read_text().replace("wavelength_um = 0.84", "wavelength_um = 0.84\nwavelenght = 1")
    )
    with pytest.raises(SceneError, match=r"small\.toml: system\[0\]: unknown key\(s\) \['wavelenght'\]"):
        load_scene(tmp_scene_file)


def test_missing_file_names_shipped_scenes(tmp_path):
    missing = tmp_path / "no-such-scene.toml"
    with pytest.raises(FileNotFoundError) as info:
        load_scene(missing)
    msg = str(info.value)
    assert "no-such-scene.toml" in msg and "not found" in msg
    for name in SHIPPED:
        assert name in msg
    with pytest.raises(FileNotFoundError, match="example"):
        load_scene("no-such-shipped-name")


def test_directory_is_not_a_scene(tmp_path):
    with pytest.raises(ValueError, match="is not a regular file"):
        load_scene(tmp_path)


def test_invalid_toml_is_a_scene_error(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[[system]\nname = 840nm\n")
    with pytest.raises(SceneError) as info:
        load_scene(bad)
    msg = str(info.value)
    assert "bad.toml" in msg and "not valid TOML" in msg
