"""The preset paper-section-6 is the paper's Section 6 (docs/science.md#91-the-preset-paper-section-6),
and svrobs_core.paper's published numbers are the paper's.

The paper's numbers are in paper_facts.json beside this file, typed in from the paper
(cited by title and authors in docs/science.md) with the table, figure or section each
comes from; nothing is read from outside the repository."""

import json
from pathlib import Path

import numpy as np
import pytest

from svrobs_core import parse_spec
from svrobs_core.paper import (
    EXPERIMENTS,
    PUBLISHED_CLAIMS,
    PUBLISHED_TABLE2,
    paper_specs,
    published_table2,
)

S, U = "paper-stable", "paper-unstable"
FACTS = json.loads((Path(__file__).with_name("paper_facts.json")).read_text())
SYSTEMS, SETUP = FACTS["systems"], FACTS["setup"]
GAMMAS = tuple(SETUP["gamma"])
SIGMA_W = tuple(float(s) for s in SYSTEMS["sigma_w"])
ROLLOUTS = SETUP["rollouts"]
# the paper varies the number of rollouts "from 10 to 450"; the preset steps by 10
N_GRID = tuple(range(ROLLOUTS["from"], ROLLOUTS["to"] + 1, 10))
PAPER_C = np.eye(3) if SYSTEMS["C"] == "identity" else np.array(SYSTEMS["C"])


@pytest.fixture(scope="module")
def full():
    return {name: parse_spec(s) for name, s in paper_specs("full").items()}


def names(spec):
    return tuple(s.name for s in spec.systems)


def test_experiments_are_e1_to_e4_and_the_audit(full):
    assert list(full) == ["E1", "E2", "E3", "E4", "A1", "A2"] == list(EXPERIMENTS)


def test_audit_experiments_are_e2_with_another_bounds_method(full):
    e2 = full["E2"].to_dict()
    a1, a2 = full["A1"].to_dict(), full["A2"].to_dict()
    assert a1 == {**e2, "bounds_method": "self-normalized", "S": None, "lambda0": 1.0}
    assert a2 == {
        **e2,
        "N": [10, 50, 100, 200, 450],
        "bounds_method": "bootstrap",
        "boot_reps": 100,
        "boot_sigma_w": "estimate",
    }


def test_common_grid_is_the_papers(full):
    lengths = FACTS["section_6_1"]["sample_length"]
    for spec in full.values():
        assert spec.T0 == SETUP["rollout_length_T0"]
        if spec.bounds_method != "bootstrap":  # A2 re-simulates every cell: 5 N values
            assert spec.N == N_GRID and len(spec.N) == 45
        assert spec.M == SETUP["M"] and spec.delta == SETUP["delta"]
        assert spec.loss_scale == "sum" and spec.data == "all" and spec.seed == 0
        # sample length N0 = (T0 - 1) N runs over the paper's 100 .. 4500
        assert (spec.T0 - 1) * spec.N[0] == lengths["from"]
        assert (spec.T0 - 1) * spec.N[-1] == lengths["to"]
        for system in spec.systems:
            # sigma_v = 0.1: the paper gives none (docs/science.md#91-the-preset-paper-section-6)
            assert system.sigma_u == SYSTEMS["sigma_u"] and system.sigma_v == 0.1
            np.testing.assert_array_equal(system.C, PAPER_C)
            paper = SYSTEMS["stable" if system.name == S else "unstable"]
            np.testing.assert_array_equal(system.B, paper["B"])
            np.testing.assert_array_equal(system.A, paper["A"])


def test_e1_table2(full):
    e1 = full["E1"]
    assert names(e1) == (S, U)
    assert e1.sigma_w == SIGMA_W
    assert e1.gamma == (FACTS["section_6_1"]["gamma"],)
    assert e1.estimators == ("ols", "svr")
    assert e1.reps == FACTS["section_6_1"]["repetitions"]
    assert e1.stages == ("estimate", "bounds")


def test_e2_figs_2_3(full):
    e2 = full["E2"]
    assert names(e2) == (S, U) and e2.sigma_w == SIGMA_W
    assert e2.gamma == GAMMAS
    assert e2.reps == FACTS["section_6_1"]["repetitions"] and e2.stages == ("estimate", "bounds")
    assert "svr" in e2.estimators


@pytest.mark.parametrize("name,systems", [("E3", (S,)), ("E4", (S, U))])
def test_e3_e4_cost(full, name, systems):
    e = full[name]
    assert names(e) == systems
    assert e.sigma_w == (1.0,)
    assert e.gamma == GAMMAS
    assert e.estimators == ("svr",)
    # "1000 Monte Carlo simulations": 1000 repetitions of the whole pipeline
    # (docs/science.md#91-the-preset-paper-section-6)
    assert e.reps == FACTS["section_6_3"]["monte_carlo_simulations"]
    assert e.stages == ("estimate", "bounds", "gain", "cost", "cost_bound")
    assert e.horizon == 200 and e.mc_runs == 1000
    # Monte Carlo J on the first 10 repetitions where J is reported (E3, S);
    # E4 is the cost ratio of the exact J
    assert e.mc_reps == (10 if name == "E3" else 0)
    assert e.gamma_ref == 0.1


def test_e4_size(full):
    # E4: 2 systems x 4 gammas x 45 N x 1000 repetitions (E3's cells are E4's S cells)
    reps = FACTS["section_6_3"]["monte_carlo_simulations"]
    assert full["E4"].n_cells == 2 * len(GAMMAS) * len(N_GRID) * reps
    assert full["E3"].n_cells == len(GAMMAS) * len(N_GRID) * reps


def test_reduced_has_the_same_structure():
    full, red = paper_specs("full"), paper_specs("reduced")
    assert list(red) == list(full)
    for name in full:
        f, r = parse_spec(full[name]), parse_spec(red[name])
        assert names(r) == names(f)
        assert r.sigma_w == f.sigma_w and r.gamma == f.gamma
        assert r.estimators == f.estimators and r.stages == f.stages
        assert r.T0 == f.T0 and r.gamma_ref == f.gamma_ref and r.seed == f.seed
        assert 1 < len(r.N) < 10 and 1 < r.reps < 10
        assert r.n_cells < 1000


def test_specs_are_fresh_copies():
    a = paper_specs("full")
    a["E1"]["sigma_w"].append(99.0)
    a["E3"]["N"]["stop"] = 20
    b = paper_specs("full")
    assert b["E1"]["sigma_w"] == [0.1, 1.0, 10.0] and b["E3"]["N"]["stop"] == 450


def test_unknown_scale():
    with pytest.raises(ValueError):
        paper_specs("huge")


TABLE2_SYSTEMS = {"open-loop stable": S, "open-loop unstable": U}


def test_published_table2_is_the_papers():
    table = FACTS["table_2"]
    seen = 0
    for row in table["rows"]:
        system = TABLE2_SYSTEMS[row["system"]]
        by_sigma: dict[float, dict[str, float]] = {}
        for (sigma_w, method), value in zip(table["columns"], row["values"], strict=True):
            by_sigma.setdefault(float(sigma_w), {})[{"OLS": "ols", "Ours": "ours"}[method]] = value
        for sigma_w, entry in by_sigma.items():
            assert published_table2(system, sigma_w, row["matrix"]) == entry
            seen += 1
    assert seen == len(PUBLISHED_TABLE2) == 12
    assert published_table2("other", 1.0, "A") is None


def test_published_claims_are_the_papers():
    claim = PUBLISHED_CLAIMS["stable_after_sample_length"]
    assert claim["system"] == S
    assert claim["sample_length"] == FACTS["section_6_2"]["stable_after_sample_length"]
