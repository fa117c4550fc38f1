"""The preset paper-section-6 equals SPEC section 9; the published Table 2 is transcribed right."""

import re
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
GAMMAS = (0.005, 0.01, 0.05, 0.1)
N_GRID = tuple(range(10, 451, 10))
PAPER_TEX = Path("/work/shared/seed/svr-observer-paper.tex")


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


def test_common_grid_is_section_9(full):
    for spec in full.values():
        assert spec.T0 == 11
        if spec.bounds_method != "bootstrap":  # A2 re-simulates every cell: 5 N values
            assert spec.N == N_GRID and len(spec.N) == 45
        assert spec.M == 1.1 and spec.delta == 0.01
        assert spec.loss_scale == "sum" and spec.data == "all" and spec.seed == 0
        # sample length N0 = (T0 - 1) N runs over the paper's 100 .. 4500
        assert (spec.T0 - 1) * spec.N[0] == 100 and (spec.T0 - 1) * spec.N[-1] == 4500
        for system in spec.systems:
            assert system.sigma_u == 1.0 and system.sigma_v == 0.1
            np.testing.assert_array_equal(system.C, np.eye(3))
            np.testing.assert_array_equal(system.B, [[1.0], [1.5], [2.0]])
            diag = 0.9 if system.name == S else 1.01
            np.testing.assert_array_equal(
                system.A, [[diag, 0.01, 0], [0.01, diag, 0.01], [0, 0.01, diag]]
            )


def test_e1_table2(full):
    e1 = full["E1"]
    assert names(e1) == (S, U)
    assert e1.sigma_w == (0.1, 1.0, 10.0)
    assert e1.gamma == (0.05,)
    assert e1.estimators == ("ols", "svr")
    assert e1.reps == 45
    assert e1.stages == ("estimate", "bounds")


def test_e2_figs_2_3(full):
    e2 = full["E2"]
    assert names(e2) == (S, U) and e2.sigma_w == (0.1, 1.0, 10.0)
    assert e2.gamma == GAMMAS
    assert e2.reps == 45 and e2.stages == ("estimate", "bounds")
    assert "svr" in e2.estimators


@pytest.mark.parametrize("name,systems", [("E3", (S,)), ("E4", (S, U))])
def test_e3_e4_cost(full, name, systems):
    e = full[name]
    assert names(e) == systems
    assert e.sigma_w == (1.0,)
    assert e.gamma == GAMMAS
    assert e.estimators == ("svr",)
    assert e.reps == 1000
    assert e.stages == ("estimate", "bounds", "gain", "cost", "cost_bound")
    assert e.horizon == 200 and e.mc_runs == 1000
    # Monte Carlo J on the first 10 repetitions where J is reported (E3, S);
    # E4 is the cost ratio of the exact J
    assert e.mc_reps == (10 if name == "E3" else 0)
    assert e.gamma_ref == 0.1


def test_e4_size_is_section_9(full):
    # "E3 + E4 are 2 x 4 x 45 x 1000 = 360,000 pipeline cells" (E3's cells are E4's S cells)
    assert full["E4"].n_cells == 2 * 4 * 45 * 1000
    assert full["E3"].n_cells == 4 * 45 * 1000


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


def test_published_table2_spot_checks():
    assert len(PUBLISHED_TABLE2) == 12
    assert published_table2(S, 0.1, "A") == {"ols": 0.0261, "ours": 0.0265}
    assert published_table2(S, 1, "B") == {"ols": 0.0211, "ours": 0.0315}
    assert published_table2(S, 10.0, "B") == {"ols": 0.4278, "ours": 0.2695}
    assert published_table2(U, 0.1, "B") == {"ols": 0.0019, "ours": 0.0036}
    assert published_table2(U, 1.0, "A") == {"ols": 0.0166, "ours": 0.0165}
    assert published_table2(U, 10.0, "B") == {"ols": 0.3774, "ours": 0.2506}
    assert published_table2("other", 1.0, "A") is None
    assert PUBLISHED_CLAIMS["stable_after_sample_length"]["sample_length"] == 1800


@pytest.mark.skipif(not PAPER_TEX.exists(), reason="paper source not available")
def test_published_table2_matches_the_paper_source():
    tex = PAPER_TEX.read_text()
    start = tex.index(r"\label{Tabel:2}")
    table = tex[start : tex.index(r"\end{table*}", start)]
    rows = [line for line in table.splitlines() if r"\tilde{\bm{" in line]
    assert len(rows) == 4  # S: A, B; U: A, B
    for line, (system, mat) in zip(rows, [(S, "A"), (S, "B"), (U, "A"), (U, "B")]):
        nums = [float(x) for x in re.findall(r"\d+\.\d+", line.split(r"}}$", 1)[1])]
        assert len(nums) == 6
        for k, sigma_w in enumerate((0.1, 1.0, 10.0)):
            assert published_table2(system, sigma_w, mat) == {
                "ols": nums[2 * k],
                "ours": nums[2 * k + 1],
            }
