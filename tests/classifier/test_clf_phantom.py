"""End to end on images with the signature model: the shipped ``motion-types`` phantom →
``torchdoct render`` → ``torchdoct maps --signature`` → ``doct-classify`` (default model) → scores
(:func:`classifier.evaluate_images.score_images`).

The phantom has nine discs in static tissue: diffusion D = 0.0003, 0.002, 0.01 µm²/s, random-ballistic
v = 0.01, 0.05, 0.3 µm/s, flow v = 0.3, 1, 3 µm/s, all identifiable by the ground-truth definition
(``classifier.truth.identifiability``, checked below) and spanning the range where the model
decides. All labelled moving pixels count (edge 0). The maps are B-scans reduced laterally along x
only, so the default model is the B-scan signature model (``signature-bscan``).

Floors: ``mean − z·SD`` over the recorded renderings of ``tests/floors/phantoms.json`` (z and the command
that records them are in the file; ``tests/reference/floors.py``), a ceiling ``mean + z·SD`` for the median
magnitude error. The test renders the shipped seed, but any change of the renderer's random stream is
another draw, so the spread over renderings is the standard error of the test's one run.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

torchdoct = pytest.importorskip("torchdoct")
from classifier.cli import classify_main  # noqa: E402
from classifier.evaluate_images import MOVING_CODES, read_rendered_labels, score_images  # noqa: E402
from tests.reference.floors import floor, load  # noqa: E402
from torchdoct.cli import main as torchdoct_main  # noqa: E402

RECORDED = load("phantoms")


def _floors(phantom: str, pool: int) -> dict[str, float]:
    """The floors of one phantom and pool from its recorded renderings (module docstring)."""
    runs, z = RECORDED["runs"][phantom][str(pool)], RECORDED["z"]
    out = {k: floor(runs[k], z) for k in ("balanced_accuracy", "coverage")}
    mags = runs["magnitude_median_abs_log10_error"]
    if all(m is not None for m in mags):
        out["magnitude"] = floor(mags, z, error=True)
    return out


def _render_map_classify(tmp_path_factory, phantom: str):
    """The README's chain on a shipped phantom: render → maps --signature → doct-classify at pools 1 and 5."""
    d = tmp_path_factory.mktemp(phantom)
    seq, maps = d / "seq.npz", d / "maps.npz"
    assert (
        torchdoct_main(["render", phantom, "--out", str(seq), "--no-progress", "--no-preview", "--threads", "1"]) == 0
    )
    assert (
        torchdoct_main(
            [
                "maps",
                str(seq),
                "--resolution",
                "original",
                "--resolution",
                "axial=14",
                "--resolution",
                "lateral=18",
                "--signature",
                "--out",
                str(maps),
                "--no-progress",
                "--threads",
                "1",
            ]
        )
        == 0
    )
    out = {}
    for pool in (
        1,
        5,
    ):  # the floors of this file are the model's (--decision rule --decide-ballistic); the default beside them
        out[pool] = d / f"classified-{pool}"
        assert (
            classify_main(
                [
                    str(maps),
                    "--out",
                    str(out[pool]),
                    "--pool",
                    str(pool),
                    "--threads",
                    "1",
                    "--decision",
                    "rule",
                    "--decide-ballistic",
                ]
            )
            == 0
        )
        out[f"conformal-{pool}"] = d / f"conformal-{pool}"
        assert (
            classify_main([str(maps), "--out", str(out[f"conformal-{pool}"]), "--pool", str(pool), "--threads", "1"])
            == 0
        )
    return seq, out


@pytest.fixture(scope="module")
def chain(tmp_path_factory):
    return _render_map_classify(tmp_path_factory, "motion-types")


def test_phantom_regions_are_identifiable():
    from classifier.features import load_spec
    from classifier.prior import Draw, Prior
    from classifier.truth import identifiability
    from torchdoct.image.phantom import load_phantom

    spec, prior = load_spec("signature"), Prior()
    phantom = load_phantom("motion-types")
    kinds = {"Diffusion": 0, "RandomBallistic": 1, "Flow": 2}
    seen = set()
    for pop in phantom.scene.populations:
        if not pop.motion:
            continue
        m = pop.motion[0]
        label = kinds[type(m).__name__]
        mag = m.diffusion_um2_per_s if label == 0 else m.speed_um_per_s
        draw = Draw(
            label=label,
            magnitude=mag,
            polar_angle_deg=getattr(m, "polar_angle_deg", 0.0),
            azimuth_deg=0.0,
            density_per_um3=pop.density_per_um3,
            sim_seed=0,
        )
        assert identifiability(spec, draw, prior)[0] == "identifiable", (pop.name, mag)
        seen.add((label, mag))
    assert sorted({lab for lab, _ in seen}) == [0, 1, 2] and len(seen) == 9  # three magnitudes per type


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
@pytest.mark.parametrize("pool", [1, 5])
def test_motion_types_phantom_scores(chain, pool):
    seq, out = chain
    summary = json.loads((out[pool] / "summary.json").read_text())
    assert summary["model_spec"] == "signature-bscan"  # picked by default for B-scan maps with signature channels
    s = score_images(out[pool], seq)
    o, floor = s["overall"], _floors("motion-types", pool)
    assert s["pool"] == pool and o["pixels"] == 9 * 616
    assert o["balanced_accuracy"] >= floor["balanced_accuracy"], o
    assert o["coverage"] >= floor["coverage"], o
    assert o["magnitude"]["median_abs_log10_error"] <= floor["magnitude"], o["magnitude"]
    assert all(c["recall"] > 1 / 3 for c in o["per_class"].values()), o["per_class"]  # each type beats chance
    assert len(s["regions"]) == 9
    # interior pixels (10 µm from any other label) are a subset, scored the same way
    inner = score_images(out[pool], seq, edge_um=10.0)["overall"]
    assert 0 < inner["pixels"] < o["pixels"]


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
@pytest.mark.parametrize("pool", [1, 5])
def test_conformal_sets_decide_fewer_pixels_wrong_than_the_rule(chain, oblique_chain, pool):
    """The default decision (conformal sets at alpha 0.1) on the same maps as the rule: on both shipped
    B-scan phantoms no motion type has more pixels decided as another type than under the rule, and the
    undecided pixels are indeterminate or a two-class set."""
    for seq, out in (chain, oblique_chain):
        summary = json.loads((out[f"conformal-{pool}"] / "summary.json").read_text())
        assert summary["info"]["decision"] == "conformal" and summary["info"]["conformal"]["alpha"] == 0.1
        rule = score_images(out[pool], seq)["overall"]["per_class"]
        conf = score_images(out[f"conformal-{pool}"], seq)["overall"]["per_class"]
        for name, c in conf.items():
            wrong = {
                k: sum(v for m, v in d["decided_as"].items() if m != name) for k, d in (("c", c), ("r", rule[name]))
            }
            assert wrong["c"] <= wrong["r"], (name, c["decided_as"], rule[name]["decided_as"])


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_pooling_helps(chain):
    seq, out = chain
    one, five = (score_images(out[p], seq)["overall"] for p in (1, 5))
    assert five["balanced_accuracy"] > one["balanced_accuracy"] and five["coverage"] > one["coverage"]


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_scores_of_a_perfect_and_an_abstaining_classifier(chain, tmp_path):
    """Scores are exact on edited outputs: the truth itself scores 1; all indeterminate decides nothing."""
    import shutil

    import tifffile

    seq, out = chain
    labels, params = read_rendered_labels(seq)
    legend = json.loads((out[1] / "legend.json").read_text())
    value = {c["name"]: c["value"] for c in legend["classes"]}
    for name, fill in (("perfect", None), ("abstain", value["indeterminate"])):
        d = tmp_path / name
        shutil.copytree(out[1], d)
        classes = np.full(labels.shape, value["indeterminate"] if fill is None else fill, np.uint8)
        if fill is None:
            for code, cls in MOVING_CODES.items():
                classes[labels == code] = value[cls]
        tifffile.imwrite(d / "classes.tif", classes)
        (d / "magnitude.tif").unlink()
        o = score_images(d, labels, params)["overall"]
        if fill is None:
            assert o["coverage"] == 1.0 and o["balanced_accuracy"] == 1.0 and o["accuracy"] == 1.0
            assert "magnitude" not in o
        else:
            assert o["coverage"] == 0.0 and o["balanced_accuracy"] is None and o["accuracy"] is None
    # edge exclusion: a label image with one disc of radius 28 µm (2-µm pixels) keeps the pixels
    # farther than 10 µm (5 pixels per axis, a box) from the rest
    z, x = np.meshgrid(np.arange(40) - 19.5, np.arange(40) - 19.5, indexing="ij")
    lab = np.where(z**2 + x**2 <= 14.0**2, 2, 1).astype(np.uint8)
    d = tmp_path / "perfect"
    tifffile.imwrite(d / "classes.tif", np.where(lab == 2, value["diffusion"], value["indeterminate"]).astype(np.uint8))
    full = score_images(d, lab)["overall"]["pixels"]
    inner = score_images(d, lab, edge_um=10.0)["overall"]["pixels"]
    assert full == int((lab == 2).sum())
    zz, xx = np.nonzero(lab == 2)
    want = sum(bool(np.all(lab[max(a - 5, 0) : a + 6, max(b - 5, 0) : b + 6] == 2)) for a, b in zip(zz, xx))
    assert inner == want


def test_ground_truth_declaring_a_tebibyte_is_refused_before_a_member_is_read(tmp_path):
    import io
    import zipfile

    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": "|i1", "fortran_order": False, "shape": (1 << 20, 1 << 20)})
    path = tmp_path / "truth.npz"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("labels.npy", buf.getvalue() + bytes(1000))
    assert path.stat().st_size < 4096
    with pytest.raises(ValueError, match=r"truth\.npz\[labels\].*1 TiB.*TORCHDOCT_MAX_INPUT_GB"):
        read_rendered_labels(path)


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_bad_inputs_are_named(chain, tmp_path):
    seq, out = chain
    labels, _ = read_rendered_labels(seq)
    with pytest.raises(ValueError, match="classes.tif is missing"):
        score_images(tmp_path, labels)
    with pytest.raises(ValueError, match="shape"):
        score_images(out[1], labels[:10])
    with pytest.raises(ValueError, match="no such file"):
        read_rendered_labels(tmp_path / "nothing.npz")
    np.savez(tmp_path / "nolabels.npz", data=np.zeros(3))
    with pytest.raises(ValueError, match="no 'labels'"):
        read_rendered_labels(tmp_path / "nolabels.npz")
    with pytest.raises(ValueError, match="edge_um"):
        score_images(out[1], labels, edge_um=float("nan"))


def test_scoring_does_not_import_torch():
    code = "import sys, classifier.evaluate_images; assert 'torch' not in sys.modules, 'torch imported'"
    subprocess.run([sys.executable, "-c", code], check=True, cwd=Path(__file__).resolve().parents[2])


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_module_command(chain, tmp_path, capsys):
    from classifier.evaluate_images import main

    seq, out = chain
    assert main([str(out[5]), str(seq), "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed == json.loads(json.dumps(score_images(out[5], seq)))
    assert main([str(out[5]), str(seq), "--edge-um", "10"]) == 0
    text = capsys.readouterr().out
    assert text.startswith("pool 5, edge 10 µm:") and "flow 3" in text
    assert main([str(tmp_path), str(seq)]) == 2
    assert "classes.tif is missing" in capsys.readouterr().err


#: The ``oblique-flow`` phantom: its three flows leave the B-scan plane (0.3 µm/s at 30° along y, 1 µm/s at
#: 60° azimuth 60°, 3 µm/s at 20° azimuth 120°), decided by the B-scan signature model; floors from its
#: recorded renderings (module docstring).


@pytest.fixture(scope="module")
def oblique_chain(tmp_path_factory):
    return _render_map_classify(tmp_path_factory, "oblique-flow")


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
@pytest.mark.parametrize("pool", [1, 5])
def test_oblique_out_of_plane_flow_phantom_scores(oblique_chain, pool):
    """Flow leaving the B-scan plane: the default model for these B-scan maps is the B-scan signature model
    (trained on the 18 × 4.9 µm PSF of the x-only lateral reduction), and it keeps its floors."""
    seq, out = oblique_chain
    summary = json.loads((out[pool] / "summary.json").read_text())
    assert summary["model_spec"] == "signature-bscan"
    o, floor = score_images(out[pool], seq)["overall"], _floors("oblique-flow", pool)
    assert o["balanced_accuracy"] >= floor["balanced_accuracy"], o
    assert o["coverage"] >= floor["coverage"], o
    assert all(c["recall"] > 1 / 3 for c in o["per_class"].values()), o["per_class"]


@pytest.mark.slow
def test_oblique_flow_volume_phantom_scores(tmp_path_factory):
    """The volume counterpart (``oblique-flow-volume``: 32 × 96 × 96 pixels, the same motions, the flows at
    30°, 60° and 20° from the beam): volume maps are reduced isotropically, so doct-classify picks the volume
    model ``signature``. Floors from its recorded renderings (module docstring)."""
    seq, out = _render_map_classify(tmp_path_factory, "oblique-flow-volume")
    summary = json.loads((out[1] / "summary.json").read_text())
    assert "signature.onnx" in json.dumps(summary)
    for pool in (1, 5):
        s, f = score_images(out[pool], seq)["overall"], _floors("oblique-flow-volume", pool)
        assert s["balanced_accuracy"] >= f["balanced_accuracy"] and s["coverage"] >= f["coverage"], (pool, s, f)
