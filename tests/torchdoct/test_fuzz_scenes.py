"""Property-based tests: malformed scene and phantom files fail clearly; valid extreme scenes run.

Every generated bad file must give ``SceneError``/``TypeError`` (exit code 2 and one ``error:`` line
from the CLI) whose message names the key that was broken, never an exception from deep inside.
"""

from __future__ import annotations

import copy
import math
import tomllib

import pytest
import torch
from _fuzz import examples

hypothesis = pytest.importorskip("hypothesis")
from _scenes import SMALL_SCENE_TOML  # noqa: E402
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from torchdoct.cli import main  # noqa: E402
from torchdoct.image.phantom import phantom_from_dict  # noqa: E402
from torchdoct.sim.config import SceneError, scene_from_dict  # noqa: E402
from torchdoct.sim.plan import make_plan  # noqa: E402
from torchdoct.sim.simulate import MemoryLimitError, simulate  # noqa: E402

BASE = tomllib.loads(SMALL_SCENE_TOML)
BASE["noise"] = {"snr_db": 30.0}
BASE["population"].append(
    {
        "name": "flowing",
        "density_per_um3": 0.01,
        "reflectivity": 0.5,
        "motion": [
            {"kind": "flow", "speed_um_per_s": 1.0, "polar_angle_deg": 30.0},
            {"kind": "ballistic", "speed_um_per_s": 0.2, "directions": "isotropic"},
        ],
    }
)

BAD_VALUES = [
    None,
    "text",
    "",
    [],
    [1, 2],
    {},
    {"x": 1},
    True,
    math.nan,
    math.inf,
    -math.inf,
    -1,
    0,
    -0.5,
    1e300,
    -1e300,
    10**12,
    2**70,
]


def _paths(obj, prefix=()):
    """Every key path of a nested scene dict (tables, arrays of tables, leaves)."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield prefix + (k,)
            yield from _paths(v, prefix + (k,))
    elif isinstance(obj, list) and obj and isinstance(obj[0], dict):
        for i, v in enumerate(obj):
            yield from _paths(v, prefix + (i,))


ALL_PATHS = sorted(set(_paths(BASE)), key=str)


def _get_parent(d, path):
    for k in path[:-1]:
        d = d[k]
    return d


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v == math.inf else "-inf" if v == -math.inf else repr(v))
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(v)


def to_toml(d: dict) -> str:
    """A TOML document for a scene-like dict (inline tables for nested arrays of tables)."""
    lines = []
    for k, v in d.items():
        if not isinstance(v, (dict, list)) or (isinstance(v, list) and not (v and all(isinstance(x, dict) for x in v))):
            lines.append(f"{k} = {_toml_value(v)}")
    for k, v in d.items():
        if isinstance(v, dict):
            lines.append(f"[{k}]")
            lines += [f"{kk} = {_toml_value(vv)}" for kk, vv in v.items()]
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            for item in v:
                lines.append(f"[[{k}]]")
                lines += [f"{kk} = {_toml_value(vv)}" for kk, vv in item.items()]
    return "\n".join(lines) + "\n"


@st.composite
def broken_scenes(draw):
    d = copy.deepcopy(BASE)
    kind = draw(st.sampled_from(["replace", "delete", "unknown", "special"]))
    if kind == "special":
        which = draw(
            st.sampled_from(
                [
                    "dup-system",
                    "no-population",
                    "no-system",
                    "motion-kind",
                    "frames",
                    "ocds-range",
                    "delay-order",
                    "times",
                ]
            )
        )
        if which == "dup-system":
            d["system"].append(dict(d["system"][0]))
            return d, "system", "name"
        if which == "no-population":
            d["population"] = []
            return d, "population", "population"
        if which == "no-system":
            d["system"] = []
            return d, "system", "system"
        if which == "motion-kind":
            d["population"][0]["motion"][0]["kind"] = draw(st.sampled_from(["swim", "Diffusion", "", "brownian"]))
            return d, "kind", "kind"
        if which == "frames":
            d["protocol"]["n_frames"] = draw(st.sampled_from([1, 0, -3, 10**7, 10**12]))
            return d, "n_frames", "n_frames"
        if which == "ocds-range":
            d["analysis"]["ocds_delay_range_s"] = draw(
                st.sampled_from([[5.0, 9.0], [0.6, 0.2], [0.0, 0.0], [math.nan, 1.0], [0.2]])
            )
            return d, "ocds_delay_range_s", "ocds_delay_range_s"
        if which == "delay-order":
            d["protocol"] = {"n_frames": 3, "frame_times_s": [0.0, 0.2, 0.1]}
            return d, "frame_times_s", "frame_times_s"
        d["protocol"] = {"n_frames": 4, "frame_times_s": [0.0, 0.2]}
        return d, "frame_times_s", "frame_times_s"
    if kind == "unknown":
        tables = [p for p in ALL_PATHS if isinstance(_get_parent(d, p + ("x",)), dict)] + [()]
        path = draw(st.sampled_from(tables))
        table = d
        for k in path:
            table = table[k]
        name = draw(st.sampled_from(["colour", "speed_mm_per_s", "Density_per_um3", "wavelength_nm", "zz"]))
        table[name] = 1.0
        return d, name, name
    path = draw(st.sampled_from(ALL_PATHS))
    parent = _get_parent(d, path)
    key = path[-1]
    named = next(k for k in reversed(path) if isinstance(k, str))
    if kind == "delete":
        del parent[key]
        return d, named, named
    parent[key] = draw(st.sampled_from(BAD_VALUES))
    return d, named, named


def _valid_or_clear(d, named, alt):
    """Either the scene is valid (and plans), or the error names the broken key."""
    try:
        scene = scene_from_dict(d)
    except (SceneError, TypeError) as err:
        msg = str(err)
        assert named in msg or alt in msg, f"error does not name {named!r}: {msg}"
        return None
    return scene


@settings(max_examples=examples(250), deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(broken_scenes())
def test_broken_scene_dicts_fail_clearly_or_run(case):
    d, named, alt = case
    scene = _valid_or_clear(d, named, alt)
    if scene is not None:  # the change happened to be valid: it must plan and run
        plan = make_plan(scene)
        if plan.expected_scatterers_per_trial * scene.protocol.n_frames < 2e6:
            try:
                res = simulate(scene, trials=2, seed=1)
            except MemoryLimitError:
                return
            m = res.metrics()
            for k in ("liv", "ocds"):
                if k in m:  # an empty metrics list is valid: the run gives signals only
                    bad = ~torch.isfinite(m[k]) & ~m["zero_intensity"]
                    assert not bool(bad.any()), f"non-finite {k} without the zero-intensity flag"


@settings(
    max_examples=examples(200),
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
@given(broken_scenes())
def test_broken_scene_files_give_one_error_line(tmp_path, capsys, case):
    d, named, alt = case
    if any(v is None for v in _leaves(d)):
        return  # TOML has no null
    path = tmp_path / "scene.toml"
    path.write_text(to_toml(d), encoding="utf-8")
    code = main(["plan", str(path)])
    err = capsys.readouterr().err
    if code == 0:
        assert err == ""
    else:
        assert code == 2 and err.startswith("error: ") and (named in err or alt in err), err


def _leaves(obj):
    if isinstance(obj, dict):
        for v in obj.values():
            yield from _leaves(v)
    elif isinstance(obj, list):
        for v in obj:
            yield from _leaves(v)
    else:
        yield obj


def test_not_toml_and_missing_files(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text("[[system]\nname = ", encoding="utf-8")
    assert main(["plan", str(bad)]) == 2
    assert "not valid TOML" in capsys.readouterr().err
    assert main(["simulate", str(tmp_path / "nope.toml")]) == 2
    assert "not found" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------------
# phantoms

PHANTOM = {
    "system": BASE["system"],
    "protocol": BASE["protocol"],
    "analysis": BASE["analysis"],
    "grid": {"n_x": 8, "n_z": 8, "pitch_x_um": 2.0, "pitch_z_um": 2.0},
    "region": [
        {"name": "ball", "shape": "sphere", "center_um": [0.0, 0.0, 0.0], "radius_um": 6.0, "density_per_um3": 0.05},
        {
            "name": "vessel",
            "shape": "cylinder",
            "axis": [1.0, 0.0, 0.0],
            "radius_um": 3.0,
            "density_per_um3": 0.05,
            "motion": [{"kind": "flow", "speed_um_per_s": 1.0}],
        },
    ],
}
PHANTOM_PATHS = sorted(set(_paths(PHANTOM)), key=str)


@settings(max_examples=examples(200), deadline=None, derandomize=True)
@given(st.sampled_from(PHANTOM_PATHS), st.sampled_from(BAD_VALUES + ["delete"]))
def test_broken_phantoms_fail_clearly(path, value):
    d = copy.deepcopy(PHANTOM)
    parent = _get_parent(d, path)
    if value == "delete":
        del parent[path[-1]]
    else:
        parent[path[-1]] = value
    named = next(k for k in reversed(path) if isinstance(k, str))
    try:
        phantom_from_dict(d)
    except (SceneError, TypeError, FileNotFoundError) as err:
        assert named in str(err) or "region" in str(err), f"error does not name {named!r}: {err}"


# ------------------------------------------------------------------------------------------------
# valid extreme scenes run and give finite metrics or the documented zero-intensity policy


@settings(max_examples=examples(30), deadline=None, derandomize=True)
@given(
    density=st.sampled_from([1e-6, 1e-3, 0.055, 2.0]),
    motion=st.sampled_from(
        [
            None,
            ("diffusion", 1e-8),
            ("diffusion", 50.0),
            ("ballistic", 1e-6),
            ("ballistic", 100.0),
            ("flow", 1e-6),
            ("flow", 300.0),
        ]
    ),
    wavelength=st.sampled_from([0.2, 0.84, 5.0]),
    frames=st.sampled_from([2, 3, 200]),
)
def test_valid_extreme_scenes_run(density, motion, wavelength, frames):
    d = copy.deepcopy(BASE)
    del d["noise"]
    d["population"] = [{"density_per_um3": density}]
    if motion is not None:
        kind, val = motion
        key = "diffusion_um2_per_s" if kind == "diffusion" else "speed_um_per_s"
        d["population"][0]["motion"] = [{"kind": kind, key: val}]
    d["system"][0]["wavelength_um"] = wavelength
    d["protocol"] = {"n_frames": frames, "frame_interval_s": 0.2048}
    d["analysis"] = {"metrics": ["liv", "ocds"] if frames >= 4 else ["liv"], "ocds_delay_range_s": [0.2048, 0.6144]}
    scene = scene_from_dict(d)
    try:
        res = simulate(scene, trials=64, seed=3)
    except MemoryLimitError as err:  # the documented policy: refused up front, with the knob to turn
        assert "truncation_tolerance" in str(err) and "GB" in str(err)
        return
    except ValueError as err:  # a motion below float32's resolution: refused naming it, and float64 runs it
        assert "float32 spacings" in str(err) and "--dtype float64" in str(err), err
        res = simulate(scene, trials=64, seed=3, dtype="float64")
    m = res.metrics()
    for k in ("liv", "ocds") if frames >= 4 else ("liv",):
        v = m[k]
        assert bool(torch.isfinite(v[~m["zero_intensity"]]).all())
        assert bool(torch.isnan(v[m["zero_intensity"]]).all())
        if motion is None:
            assert bool((v[~m["zero_intensity"]] == 0).all())


# ------------------------------------------------------------------------------------------------
# files that are not scene text: binary data, truncated or corrupted TOML


@settings(
    max_examples=examples(150),
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(
    st.one_of(
        st.binary(min_size=1, max_size=400),
        st.tuples(st.integers(0, len(SMALL_SCENE_TOML)), st.binary(min_size=1, max_size=8)).map(
            lambda t: SMALL_SCENE_TOML.encode()[: t[0]] + t[1]
        ),
    )
)
def test_binary_or_corrupted_scene_files_give_one_error_line(tmp_path, capsys, content):
    path = tmp_path / "scan.toml"
    path.write_bytes(content)
    for argv in (["plan", str(path)], ["simulate", str(path), "--trials", "2", "--no-progress"]):
        code = main(argv)
        err = capsys.readouterr().err
        if code != 0:  # a truncation can leave a valid scene (e.g. cut after the last table)
            assert code == 2 and err.startswith("error: ") and err.count("\n") == 1, err
            assert "scan.toml" in err, err


@settings(
    max_examples=examples(80),
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(
    st.one_of(
        st.sampled_from(
            [
                "cpu",
                "cpu:0",
                "cuda",
                "cuda:0",
                "cuda:-1",
                "cuda:1e9",
                "mps",
                "xpu",
                "meta",
                "CPU",
                "gpu",
                "",
                " ",
                "cpu:",
                ":0",
                "cuda:0:1",
            ]
        ),
        st.text(max_size=12),
    )
)
def test_device_strings_give_one_error_line(tmp_path, capsys, device):
    path = tmp_path / "scene.toml"
    path.write_text(SMALL_SCENE_TOML, encoding="utf-8")
    # ``--device=VALUE``: any string reaches the device check (``--device -x`` would be argparse's
    # usage error for a missing value, tested in test_cli)
    code = main(["simulate", str(path), "--trials", "2", "--no-progress", f"--device={device}"])
    captured = capsys.readouterr()
    if code != 0:
        assert code == 2 and captured.err.startswith("error: ") and captured.err.count("\n") == 1, captured.err
        assert "--device" in captured.err and "devices here: cpu" in captured.err, captured.err
