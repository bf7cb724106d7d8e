"""The tiny study of the test suite: the shipped ``paper-reduced`` study with 8 frames, 3 motion values per
curve and 64 trials per point (imported by module name, never through ``conftest``)."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

from torchdoct.study import shipped_studies


def tiny_study_dict(**study_changes) -> dict:
    data = tomllib.loads((Path(shipped_studies()["paper-reduced"])).read_text(encoding="utf-8"))
    data["name"] = "tiny"
    data["study"].update({"trials": 64, "seed": 11, **study_changes})
    data["scene"]["protocol"] = {"n_frames": 8, "frame_interval_s": 0.2048}
    data["scene"]["analysis"]["ocds_delay_range_s"] = [0.2048, 0.6144]
    for p in data["part"]:
        p["values"] = [0.0, 0.01, 1.0] if p["name"] == "diffusion" else [0.0, 0.1, 3.0]
        p["inset_max"] = 0.05 if p["name"] == "diffusion" else 0.5
    return data


def write_tiny_study(tmp_path, **changes) -> Path:
    """The tiny study as a TOML file (written by hand: the standard library has no TOML writer)."""
    data = tiny_study_dict(**changes)
    lines = [f'name = "{data["name"]}"', "", "[study]"]
    for k, v in data["study"].items():
        if k != "comparison":
            lines.append(f"{k} = {json.dumps(v)}")
    for c in data["study"]["comparison"]:
        lines += ["", "[[study.comparison]]", *(f"{k} = {json.dumps(v)}" for k, v in c.items())]
    lines += ["", "[scene]"]
    for s in data["scene"]["system"]:
        lines += ["", "[[scene.system]]", *(f"{k} = {json.dumps(v)}" for k, v in s.items())]
    lines += ["", "[scene.protocol]", *(f"{k} = {json.dumps(v)}" for k, v in data["scene"]["protocol"].items())]
    lines += ["", "[[scene.population]]", "density_per_um3 = 0.055"]
    lines += ["", "[scene.analysis]", *(f"{k} = {json.dumps(v)}" for k, v in data["scene"]["analysis"].items())]
    for p in data["part"]:
        lines += ["", "[[part]]"]
        for k, v in p.items():
            if k == "motion":
                lines.append("motion = { " + ", ".join(f"{a} = {json.dumps(b)}" for a, b in v.items()) + " }")
            else:
                lines.append(f"{k} = {json.dumps(v)}")
    path = tmp_path / "tiny.toml"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path
