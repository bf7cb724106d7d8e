"""Property-based tests of doct-classify's inputs: malformed maps files and options fail clearly.

Every generated bad input (a truncated, corrupted, empty or pickled maps file; a ``meta_json`` with
a broken or missing key; a ``--pool`` larger than the image) must give ``ValueError``/``TypeError``
whose message names the file or the option, and the CLI must exit with code 2 and one ``error:``
line, never a traceback. Inputs that happen to stay valid must classify (exit 0).
"""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest
from _fuzz import examples

hypothesis = pytest.importorskip("hypothesis")
from _clf_maps import feature_channels, maps_meta, save_maps  # noqa: E402
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from classifier.cli import classify_main  # noqa: E402
from classifier.features import load_spec  # noqa: E402
from classifier.infer import read_maps  # noqa: E402

SPEC = load_spec("single-acquisition")  # the shipped default model's spec: no training needed
Z, X = 6, 7
META = maps_meta(SPEC, feature_channels(SPEC))
DATA = np.random.default_rng(0).uniform(0.1, 1.0, size=(len(META["channels"]), Z, X)).astype(np.float32)
DATA[-1] = 20.0  # mean_db: no background
ERRORS = (ValueError, TypeError)
SETTINGS = settings(
    max_examples=examples(150),
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
BAD_VALUES = [None, "text", "", [], [1, "a"], {}, {"x": 1}, True, float("nan"), float("inf"), -1, 0, 1e300, 2**70]


def _classify(path: Path, out: Path, *extra: str) -> tuple[int, str, str]:
    import io
    from contextlib import redirect_stderr, redirect_stdout

    o, e = io.StringIO(), io.StringIO()
    with redirect_stdout(o), redirect_stderr(e):
        code = classify_main([str(path), "--out", str(out), "--threads", "1", "--force", *extra])
    return code, o.getvalue(), e.getvalue()


def _assert_clear(code: int, err: str, *names: str) -> None:
    assert code in (0, 2), (code, err)
    if code == 2:
        assert err.startswith("error: ") and err.count("\n") == 1, err
        assert any(n in err for n in names), (names, err)
    else:
        assert err == "", err


def _paths(obj, prefix=()):
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield prefix + (k,)
            yield from _paths(v, prefix + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            if isinstance(v, (dict, list)):
                yield prefix + (i,)
                yield from _paths(v, prefix + (i,))


META_PATHS = sorted(set(_paths(META)), key=str)


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> dict[str, bytes]:
    tmp = tmp_path_factory.mktemp("clf-fuzz")
    return {fmt: save_maps(tmp / f"good.{fmt}", DATA, META).read_bytes() for fmt in ("npz", "tif")}


def test_the_valid_file_classifies(good, tmp_path):
    for fmt, raw in good.items():
        path = tmp_path / f"maps.{fmt}"
        path.write_bytes(raw)
        code, out, err = _classify(path, tmp_path / "o")
        assert code == 0 and err == "" and "pixels classified" in out, err


@SETTINGS
@given(
    fmt=st.sampled_from(["npz", "tif"]),
    cut=st.floats(0.0, 1.0, exclude_max=True),
    flips=st.lists(st.tuples(st.floats(0.0, 1.0, exclude_max=True), st.integers(1, 255)), max_size=3),
)
def test_truncated_or_corrupted_maps_files_fuzz(good, tmp_path, fmt, cut, flips):
    raw = bytearray(good[fmt])
    for where, xor in flips:
        raw[int(where * len(raw))] ^= xor
    raw = bytes(raw[: int(cut * len(raw))] if cut > 0 or not flips else raw)
    path = tmp_path / f"broken.{fmt}"
    path.write_bytes(raw)
    try:
        read_maps(path)
    except ERRORS as err:
        assert "broken." + fmt in str(err), err
    code, _, err = _classify(path, tmp_path / "o")
    _assert_clear(code, err, f"broken.{fmt}")


@SETTINGS
@given(data=st.data())
def test_broken_meta_json_keys_fuzz(tmp_path, data):
    meta = copy.deepcopy(META)
    path_ = data.draw(st.sampled_from(META_PATHS))
    parent = meta
    for k in path_[:-1]:
        parent = parent[k]
    value = data.draw(st.sampled_from(BAD_VALUES + ["delete"]))
    if value == "delete":
        del parent[path_[-1]]
    else:
        parent[path_[-1]] = value
    path = tmp_path / "meta.npz"
    np.savez(path, maps=DATA, meta_json=np.asarray(json.dumps(meta)))
    code, _, err = _classify(path, tmp_path / "o")
    _assert_clear(code, err, "meta.npz", *(str(k) for k in path_ if isinstance(k, str)))


@SETTINGS
@given(
    meta_json=st.one_of(
        st.text(max_size=40),
        st.recursive(
            st.none() | st.booleans() | st.floats(allow_nan=False) | st.text(max_size=5),
            lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=5), c, max_size=3),
            max_leaves=8,
        ).map(json.dumps),
    ),
    kind=st.sampled_from(["text", "pickled-meta", "pickled-maps", "pickled-npy", "number-meta", "int-maps", "1d-maps"]),
)
def test_malformed_meta_json_and_pickles_fuzz(tmp_path, meta_json, kind):
    path = tmp_path / "odd.npz"
    maps, meta = DATA, np.asarray(meta_json)
    if kind == "pickled-meta":
        meta = np.array([meta_json], dtype=object)
    elif kind == "pickled-maps":
        maps, meta = np.array([DATA, None], dtype=object), np.asarray(json.dumps(META))
    elif kind == "number-meta":
        meta = np.arange(3.0)
    elif kind == "int-maps":
        maps, meta = DATA.astype(np.int32), np.asarray(json.dumps(META))
    elif kind == "1d-maps":
        maps, meta = DATA.reshape(-1), np.asarray(json.dumps(META))
    if kind == "pickled-npy":  # a pickled .npy given the maps suffix
        with open(path, "wb") as fh:
            np.save(fh, np.array([meta_json, DATA], dtype=object), allow_pickle=True)
    else:
        np.savez(path, maps=maps, meta_json=meta)
    with pytest.raises(ERRORS) as info:
        read_maps(path)
    assert "odd.npz" in str(info.value)
    if kind.startswith("pickled"):
        assert "(a pickle)" in str(info.value), info.value
    code, _, err = _classify(path, tmp_path / "o")
    _assert_clear(code, err, "odd.npz")
    assert code == 2


@settings(
    max_examples=examples(40),
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(pool=st.integers(-3, 3 * X))
def test_pool_sizes_fuzz(good, tmp_path, pool):
    path = tmp_path / "maps.npz"
    path.write_bytes(good["npz"])
    code, _, err = _classify(path, tmp_path / "o", "--pool", str(pool))
    _assert_clear(code, err, "pool")
    assert (code == 0) == (1 <= pool <= min(Z, X) and pool % 2 == 1), (pool, err)
    if pool > min(Z, X) and pool % 2:
        assert f"largest valid pool is {min(Z, X) - 1 + min(Z, X) % 2}" in err


def test_a_pickle_under_the_maps_suffix_is_named_as_such(tmp_path):
    import pickle

    path = tmp_path / "p.npz"
    path.write_bytes(pickle.dumps({"maps": DATA, "meta_json": json.dumps(META)}))
    with pytest.raises(ValueError, match=r"p\.npz: holds Python objects \(a pickle\)"):
        read_maps(path)
