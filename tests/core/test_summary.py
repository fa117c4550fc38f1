"""summarize / summarize_columns (summary.json, docs/spec.md#summaries) against a per-group
loop written here: mean and std (ddof 0) of the non-null values, booleans as 0/1."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest

from svrobs_core.records import GROUP_FIELDS, SUMMARY_FIELDS, summarize, summarize_columns


def _records(seed: int, n_groups: int = 40) -> list[dict]:
    rng = random.Random(seed)
    recs = []
    for _ in range(n_groups):
        key = {
            "system": rng.choice(["S", "U"]),
            "sigma_w": rng.choice([0.1, 1.0]),
            "N": rng.choice([10, 20, 30]),
            "estimator": rng.choice(["ols", "svr"]),
        }
        key["gamma"] = None if key["estimator"] == "ols" else rng.choice([0.01, 0.1])
        for _ in range(rng.randint(1, 9)):
            r = dict(key)
            for f in SUMMARY_FIELDS:
                u = rng.random()
                if f in ("thm1_holds_A", "certified"):
                    r[f] = None if u < 0.2 else u < 0.6
                else:
                    r[f] = None if u < 0.3 else rng.gauss(0, 10) * 10 ** rng.randint(-5, 5)
            recs.append(r)
    rng.shuffle(recs)
    return recs


def _oracle(recs):
    groups = {}
    for r in recs:
        groups.setdefault(tuple(r[g] for g in GROUP_FIELDS), []).append(r)
    out = {}
    for key, rows in groups.items():
        st = {}
        for f in SUMMARY_FIELDS:
            vals = [float(r[f]) for r in rows if r[f] is not None]
            if vals:
                m = math.fsum(vals) / len(vals)
                st[f] = (m, math.sqrt(math.fsum((v - m) ** 2 for v in vals) / len(vals)), len(vals))
            else:
                st[f] = (None, None, 0)
        out[key] = (len(rows), st)
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_summarize_equals_a_per_group_loop(seed):
    recs = _records(seed)
    want = _oracle(recs)
    got = summarize(recs)
    keys = [tuple(g[k] for k in GROUP_FIELDS) for g in got]
    assert sorted(keys, key=lambda k: tuple((v is None, v) for v in k)) == keys  # sorted
    assert set(keys) == set(want)
    for g in got:
        n, st = want[tuple(g[k] for k in GROUP_FIELDS)]
        assert g["count"] == n
        for f in SUMMARY_FIELDS:
            m, s, c = st[f]
            assert g["stats"][f]["count"] == c
            if c == 0:
                assert g["stats"][f] == {"mean": None, "std": None, "count": 0}
            else:
                assert g["stats"][f]["mean"] == pytest.approx(m, rel=1e-12, abs=1e-300)
                assert g["stats"][f]["std"] == pytest.approx(s, rel=1e-9, abs=1e-12 * abs(m))


def test_summarize_columns_equals_summarize_of_records():
    recs = _records(5)
    cols = {f: [r[f] for r in recs] for f in GROUP_FIELDS + SUMMARY_FIELDS}
    cols = {f: (np.array(v, dtype=object) if f == "system" else v) for f, v in cols.items()}
    assert summarize_columns(cols) == summarize(recs)
    assert summarize([]) == []


@pytest.mark.parametrize(
    "spec",
    [
        {
            "systems": ["paper-stable", "paper-unstable"],
            "sigma_w": [0.1],
            "N": [5, 20],
            "reps": 9,
            "gamma": [0.01, 0.1],
            "stages": ["estimate", "bounds", "gain", "cost", "cost_bound"],
            "mc_reps": 3,
            "seed": 3,
        },
        # overflowing means and standard deviations (null with a note)
        {
            "systems": ["paper-stable"],
            "sigma_w": [1e100],
            "N": [5],
            "reps": 2,
            "stages": ["estimate", "bounds", "gain", "cost"],
            "horizon": 20,
            "mc_reps": 0,
        },
        # N = 1 with final data: undefined estimates and bounds (nulls), booleans
        {
            "systems": ["paper-stable"],
            "sigma_w": [0.0],
            "N": [1, 3],
            "reps": 5,
            "data": "final",
            "estimators": ["ols", "shrunk-ols", "svr"],
            "stages": ["estimate", "bounds", "gain"],
            "bounds_method": "self-normalized",
        },
    ],
)
def test_a_units_summaries_from_its_arrays_equal_those_of_its_records(spec):
    """The worker summarises a unit from its arrays (UnitResult.summary_columns), and
    a job split by repetitions from its records: the same numbers, to the bit."""
    import json

    from svrobs_core import parse_spec
    from svrobs_core.planning import plan_units
    from svrobs_core.runner import run_unit_result

    parsed = parse_spec(spec)
    for unit in plan_units(parsed):
        result = run_unit_result(parsed, unit)
        want = summarize(result.records())
        assert json.dumps(summarize_columns(result.summary_columns())) == json.dumps(want)
