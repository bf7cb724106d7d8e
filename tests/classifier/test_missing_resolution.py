"""Maps of the shipped system that lack one of the resolutions the shipped models read are answered with
the ``--resolution`` to add to ``torchdoct maps``, not with a model to train."""

from __future__ import annotations

import numpy as np
from _clf_maps import feature_channels, maps_meta, save_maps

from classifier.cli import classify_main
from classifier.features import load_spec


def test_a_missing_resolution_names_the_resolution_to_add(tmp_path, capsys):
    spec = load_spec("single-acquisition-bscan")
    channels = [c for c in feature_channels(spec) if c["resolution"] != "lateral=18"]
    path = save_maps(
        tmp_path / "maps.npz", np.full((len(channels), 8, 8), 0.5, np.float32), maps_meta(spec, channels, axes="CZX")
    )
    out = tmp_path / "out"
    assert classify_main([str(path), "--out", str(out), "--threads", "1", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:"), err
    assert "`--resolution lateral=18`" in err[0] and "--resolution original --resolution axial=14" in err[0], err[0]
    assert "doct-train --like" not in err[0]
    assert not out.exists()
