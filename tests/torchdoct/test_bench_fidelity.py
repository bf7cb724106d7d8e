"""`torchdoct bench tradeoffs --part fidelity`: the bias of every model feature against a tight reference.

A loose hard truncation (tolerance 0.1: scatterers pop in at 10 % of the peak amplitude) must show a
resolvable bias on the short-lag intensity correlation of slow axial flow; tolerance 1e-4 must not.
"""

from __future__ import annotations

import json

import pytest

from torchdoct.bench import tradeoffs
from torchdoct.cli import main


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_fidelity_resolves_a_loose_truncation_and_not_a_tight_one():
    settings = [
        {"truncation_tolerance": 0.1, "truncation": "hard", "dtype": "float32"},
        {"truncation_tolerance": 1e-4, "truncation": "hard", "dtype": "float32"},
    ]
    res = tradeoffs.feature_fidelity(trials=256, reference_trials=256, settings=settings, cells=["flow v=0.2 θ=0°"])
    loose, tight = res["settings"]
    assert loose["resolvable_bias"] and "rho_lin_1" in loose["resolvable_features"]
    assert loose["rho_lin_1_worst"]["bias"] < 0  # pops decorrelate
    assert not tight["resolvable_bias"], tight["worst"]
    assert res["cheapest_without_resolvable_bias"]["truncation_tolerance"] == 1e-4
    n_comp = len(tradeoffs.FIDELITY_FEATURES) * 3
    assert loose["comparisons"] == n_comp and loose["z_bound"] > 3.0
    table = tradeoffs.format_fidelity_table(res)
    assert "rho_lin_1" in table and "cheapest setting" in table
    json.dumps(res)


def test_fidelity_rejects_unknown_cell():
    with pytest.raises(ValueError, match="unknown fidelity cell"):
        tradeoffs.feature_fidelity(trials=64, reference_trials=64, cells=["no such cell"])


def test_fidelity_settings_include_taper_when_the_simulator_has_it():
    rows = tradeoffs.fidelity_settings()
    assert {(r["truncation_tolerance"], r["dtype"]) for r in rows if r["truncation"] == "hard"} == {
        (t, d) for t in (1e-2, 1e-3, 1e-4) for d in ("float32", "float64")
    }
    if "taper" in tradeoffs._truncation_modes():
        assert any(r["truncation"] == "taper" for r in rows)


def test_cli_part_fidelity_is_offered(capsys):
    with pytest.raises(SystemExit):
        main(["bench", "tradeoffs", "--help"])
    assert "fidelity" in capsys.readouterr().out
