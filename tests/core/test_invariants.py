"""The certificate invariant over random extreme-but-valid specs.

A property test (hypothesis, derandomized, 200 specs)
drives specs with tiny to huge M, sigma_w including 0, T0 from 1 up, small N,
tiny / huge gamma, custom systems with nearly singular C, zero B columns and
zero sigma_v, through ``parse_spec`` and ``run_spec``. For every spec either
validation refuses it with a SpecError naming a field, or it runs without an
exception and every record

* is JSON without NaN / inf (``allow_nan=False``) and has every stage's fields;
* has ``certified``, ``stable_certified``, ``thm1_holds_*`` true only when every
  quantity they rest on is non-null (finite): the estimate, the radius, the
  bound's eps, rho_upper_bound < 1 / g(L) < 1 and the gain L;
* has a note whenever a certificate of a stage that ran is null.

Plus two specs whose radii leave the double range: ``"M": 1e20`` and ``"T0": 10000`` on
paper-unstable give null radii with a note, never 0 and a certificate.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, note, settings
from hypothesis import strategies as st

from svrobs_core import SpecError, estimators, parse_spec, run_spec
from svrobs_core.spec import STAGES

MAX_EXAMPLES = 200
COUNTS = {"generated": 0, "refused": 0, "ran": 0, "records": 0}

# -- strategies ----------------------------------------------------------------
log_uniform = st.floats(min_value=-12, max_value=12).map(lambda e: float(10.0**e))
extreme = st.one_of(st.sampled_from([1e-300, 1e-30, 1e-8, 1.0, 1.1, 2.0, 1e20, 1e150]), log_uniform)


@st.composite
def systems(draw):
    if draw(st.booleans()):
        return draw(st.sampled_from(["paper-stable", "paper-unstable"]))
    n = draw(st.integers(1, 3))
    m = draw(st.integers(1, 2))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    A = rng.standard_normal((n, n)) * draw(st.sampled_from([0.3, 0.6, 1.0, 1.5]))
    B = rng.standard_normal((n, m))
    if draw(st.booleans()):
        B[:, 0] = 0.0  # a zero input column
    kind = draw(st.sampled_from(["identity", "rows", "near-singular"]))
    if kind == "identity":
        C = np.eye(n)
    elif kind == "rows":
        C = rng.standard_normal((draw(st.integers(1, n)), n))
    else:  # square, nearly singular: two almost equal rows
        C = rng.standard_normal((n, n))
        if n > 1:
            C[-1] = C[0] + draw(st.sampled_from([1e-15, 1e-13, 1e-10, 1e-6])) * rng.standard_normal(
                n
            )
        else:
            C *= 1e-12
    sigma_v = draw(st.sampled_from([0.0, 1e-8, 0.1, 1.0, 10.0]))
    return {
        "name": "custom",
        "A": A.tolist(),
        "B": B.tolist(),
        "C": C.tolist(),
        "sigma_u": draw(st.sampled_from([1e-3, 1.0, 1e3])),
        "sigma_v": sigma_v,
    }


@st.composite
def specs(draw):
    stages = ["estimate"]
    for st_name in STAGES[1:5]:
        if not draw(st.booleans()):
            break
        stages.append(st_name)
    if "bounds" in stages and draw(st.integers(0, 5)) == 0:
        stages.append("sls")
    T0 = draw(st.one_of(st.integers(1, 40), st.sampled_from([200, 2000])))
    N = draw(st.lists(st.integers(1, 25), min_size=1, max_size=2, unique=True))
    if T0 >= 200:
        N = [min(N)]
    return {
        "systems": [draw(systems())],
        "sigma_w": draw(
            st.lists(
                st.sampled_from([0.0, 1e-8, 0.1, 1.0, 1e4]), min_size=1, max_size=2, unique=True
            )
        ),
        "N": N,
        "T0": T0,
        "gamma": draw(st.lists(log_uniform, min_size=1, max_size=2, unique=True)),
        "estimators": draw(
            st.lists(
                st.sampled_from(["ols", "svr", "shrunk-ols"]), min_size=1, max_size=3, unique=True
            )
        ),
        "loss_scale": draw(st.sampled_from(["sum", "mean"])),
        "data": draw(st.sampled_from(["all", "final"])),
        "reps": draw(st.integers(1, 2)),
        "M": draw(extreme),
        "delta": draw(st.sampled_from([1e-12, 0.01, 0.5, 0.99])),
        "stages": stages,
        "mc_runs": draw(st.integers(2, 8)),
        "mc_reps": draw(st.integers(0, 1)),
        "horizon": draw(st.integers(1, 30)),
        "margin": draw(st.sampled_from([0.0, 0.01, 0.5])),
        "reuse_gain": draw(st.booleans()),
        "sls": {"T_fir": draw(st.integers(2, 4))},
        "x0_std": draw(st.sampled_from([0.0, 1.0, 1e3])),
        "seed": draw(st.integers(0, 2**32)),
        **draw(
            st.sampled_from(
                [
                    {},
                    {},
                    {"bounds_method": "self-normalized"},
                    {"bounds_method": "self-normalized", "S": 1e-3, "lambda0": 1e6},
                    {"bounds_method": "bootstrap", "boot_reps": 3},
                    {"bounds_method": "bootstrap", "boot_reps": 2, "boot_sigma_w": "spec"},
                ]
            )
        ),
    }


# -- the invariant ---------------------------------------------------------------
def _finite(x) -> bool:
    """Non-null and, for a matrix, every entry non-null (records hold None for NaN/inf)."""
    if x is None:
        return False
    if isinstance(x, list):
        return all(_finite(v) for v in x)
    return bool(np.isfinite(x))


# certificate field -> (stage, the fields it rests on)
RESTS_ON = {
    "stable_certified": ("bounds", ("A_hat", "r_A", "radii_A", "eps_A", "rho_upper_bound")),
    "thm1_holds_A": ("bounds", ("A_hat", "H_A")),
    "thm1_holds_B": ("bounds", ("B_hat", "H_B")),
    "certified": ("gain", ("A_hat", "r_A", "radii_A", "L", "g_L")),
}


def check_record(record: dict, stages) -> None:
    json.dumps(record, allow_nan=False)
    for field, (stage, needs) in RESTS_ON.items():
        value = record[field]
        if stage not in stages:
            assert value is None
            continue
        assert value in (True, False, None), (field, value)
        if value is not None:
            for need in needs:
                assert _finite(record[need]), (field, need, record)
        else:
            assert record["notes"], (field, "null without a note", record)
    if record["stable_certified"]:
        assert record["rho_upper_bound"] < 1
    if record["certified"]:
        assert record["g_L"] < 1
    if record["coverage_A"] is not None:
        assert _finite(record["r_A"])
    if record.get("J_bound") is not None:
        assert all(_finite(record[f]) for f in ("eps_A", "eps_B", "L"))
    if record.get("J_opt_bound") is not None:
        assert _finite(record["eps_A"])


def _run(obj: dict) -> None:
    note(json.dumps(obj))  # printed with a falsifying example
    COUNTS["generated"] += 1
    try:
        spec = parse_spec(obj)
    except SpecError as e:
        assert e.field and e.message  # refused, naming the field
        COUNTS["refused"] += 1
        return
    n = 0
    for batch in run_spec(spec):
        for record in batch:
            check_record(record, spec.stages)
            n += 1
    assert n == spec.n_cells
    COUNTS["ran"] += 1
    COUNTS["records"] += n


@settings(
    max_examples=MAX_EXAMPLES,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(specs())
def _property(obj):
    _run(obj)


def test_certificates_rest_on_finite_quantities_for_random_extreme_specs(capsys):
    for k in COUNTS:
        COUNTS[k] = 0
    _property()
    with capsys.disabled():
        print(
            f"\n[invariants] {COUNTS['generated']} specs generated: {COUNTS['ran']} ran "
            f"({COUNTS['records']} records), {COUNTS['refused']} refused by validation"
        )
    assert COUNTS["generated"] >= MAX_EXAMPLES * 0.9
    assert COUNTS["ran"] >= COUNTS["generated"] // 2  # mostly valid specs, not rejections


# -- radii out of the double range ---------------------------------------------
@pytest.mark.parametrize(
    "extra",
    [{"systems": ["paper-stable"], "M": 1e20}, {"systems": ["paper-unstable"], "T0": 10_000}],
)
def test_overflowing_bounds_give_null_radii_with_a_note(extra):
    obj = {"sigma_w": [1.0], "N": [20], "reps": 1, "stages": ["estimate", "bounds", "gain"]}
    spec = parse_spec({**obj, **extra})
    records = [r for batch in run_spec(spec) for r in batch]
    assert records
    for r in records:
        for f in ("H_A", "H_B", "r_A", "r_B", "eps_A", "coverage_A", "rho_upper_bound"):
            assert r[f] is None, (f, r[f])
        for f in ("stable_certified", "certified", "thm1_holds_A", "thm1_holds_B"):
            assert r[f] is None, (f, r[f])
        assert "out of the double range" in r["notes"]
        check_record(r, spec.stages)


def test_no_certificate_from_an_untrustworthy_solve():
    """paper-unstable over 3000 steps: cond(Z Z^T) ~ 1e60. The bounds are finite
    (M = 1.0001), but OLS had certified: true with rho(A - L C) = 1.01."""
    obj = {
        "systems": ["paper-unstable"],
        "sigma_w": [1.0],
        "N": [3],
        "reps": 2,
        "T0": 3000,
        "M": 1.0001,
        "stages": ["estimate", "bounds", "gain"],
    }
    spec = parse_spec(obj)
    records = [r for batch in run_spec(spec) for r in batch]
    for r in records:
        assert r["certified"] is None and r["stable_certified"] is None
        if r["estimator"] == "ols" or r["A_hat"][0][0] is not None:
            assert r["r_A"] is not None and r["A_hat"] is not None  # estimate and radii kept
            assert "certificates withheld" in r["notes"]
        else:  # an SVR solve whose refinement does not contract: rounding, null
            assert "estimate: not finite" in r["notes"]
        check_record(r, spec.stages)
    assert any(r["estimator"] == "ols" for r in records)


def test_an_exact_cost_beyond_the_doubles_is_null_with_its_note(monkeypatch):
    """An SVR fit with gamma = 1e-300 on a one-rollout, two-step dataset: its QR
    solve is rounding (the refinement step is larger than the estimate, which is
    therefore null); kept here (REFINE_STEP_NULL = inf) as a huge but finite input
    to the later stages. Over one step with sigma_w = sigma_v = 0,
    J = E||e_1||^2 = sigma_u^2 (B_hat - B)^2 exactly, which (in logs) is beyond
    the largest double: J_exact (and J_mc) null, J_exact with its note, and
    nothing warns."""
    monkeypatch.setattr(estimators, "REFINE_STEP_NULL", np.inf)
    su = 1e-3
    obj = {
        "systems": [{"name": "s", "A": [[1.0]], "B": [[1.0]], "sigma_u": su, "sigma_v": 0.0}],
        "sigma_w": [0.0],
        "N": [1],
        "T0": 2,
        "reps": 1,
        "estimators": ["svr"],
        "gamma": [1e-300],
        "stages": ["estimate", "bounds", "gain", "cost", "cost_bound"],
        "horizon": 1,
        "seed": 0,
    }
    spec = parse_spec(obj)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # an unsilenced overflow fails here
        records = [r for batch in run_spec(spec) for r in batch]
    (r,) = records
    b_hat = r["B_hat"][0][0]
    assert r["g_L"] is not None and r["L"] is not None  # the gain is defined
    log10_J = 2 * np.log10(su) + 2 * np.log10(abs(b_hat - 1.0))
    assert log10_J > np.log10(np.finfo(float).max)
    assert r["J_exact"] is None and r["J_mc"] is None
    assert "J_exact: not finite (the cost leaves the double range)" in r["notes"]
    check_record(r, spec.stages)
