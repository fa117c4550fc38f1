"""The report's column helpers (selection, factorising, grouping) against plain
Python over the same values, on random columns with NaNs and missing texts."""

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from svrobs_core.report.columns import (
    GAMMA_RTOL,
    Columns,
    by_N,
    group_indices,
    mean_of,
    select,
    systems_of,
)

NAN = float("nan")
texts = st.sampled_from(["paper-stable", "paper-unstable", "b", None])
gammas = st.sampled_from([NAN, 0.05, 0.05 * (1 + 1e-12), 0.05 * (1 + 1e-8), 0.1, 1e-3])
Ns = st.sampled_from([10.0, 20.0, 450.0, NAN])
values = st.one_of(st.floats(-1e6, 1e6), st.just(NAN))
# derandomized: the same examples on every run; each draws up to 60 rows of 7 columns
EXAMPLES = 60


@st.composite
def columns(draw):
    n = draw(st.integers(1, 60))
    col = {
        "system": np.array(draw(st.lists(texts, min_size=n, max_size=n)) + [None], object)[:-1],
        "gamma": np.array(draw(st.lists(gammas, min_size=n, max_size=n))),
        "sigma_w": np.array(
            draw(st.lists(st.sampled_from([0.1, 1.0, NAN]), min_size=n, max_size=n))
        ),
        "N": np.array(draw(st.lists(Ns, min_size=n, max_size=n))),
        "N0": np.array(draw(st.lists(st.sampled_from([19.0, 38.0, NAN]), min_size=n, max_size=n))),
        "v": np.array(draw(st.lists(values, min_size=n, max_size=n))),
    }
    mask = np.array(draw(st.lists(st.booleans(), min_size=n, max_size=n)))
    return Columns(col, n), mask


def _key(v):
    return None if isinstance(v, float) and math.isnan(v) else v


@settings(max_examples=EXAMPLES, deadline=None)
@given(columns())
def test_codes_give_back_every_value_once_and_sorted(cm):
    cols, _ = cm
    for f in ("gamma", "N", "system"):
        codes, distinct = cols.codes(f)
        assert [distinct[c] for c in codes] == [_key(v) for v in cols[f].tolist()]
        assert len(set(map(repr, distinct))) == len(distinct)
        if f != "system":  # floats: ascending, None (NaN) last
            finite = [v for v in distinct if v is not None]
            assert finite == sorted(finite) and None not in distinct[: len(finite)]


@settings(max_examples=EXAMPLES, deadline=None)
@given(columns(), gammas, st.sampled_from([0.1, 1.0]))
def test_select_is_isclose_of_each_value(cm, gamma, sigma):
    cols, _ = cm
    want = np.array(
        [
            (s == "paper-stable")
            and math.isclose(g, gamma, rel_tol=GAMMA_RTOL)
            and math.isclose(w, sigma, rel_tol=GAMMA_RTOL)
            for s, g, w in zip(cols["system"], cols["gamma"], cols["sigma_w"])
        ]
    )
    if math.isnan(gamma):
        return  # gamma=None selects NaN; NaN is never close
    got = select(cols, system="paper-stable", gamma=gamma, sigma_w=sigma)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(select(cols, gamma=None), np.isnan(cols["gamma"]))


@settings(max_examples=EXAMPLES, deadline=None)
@given(columns(), gammas, st.sampled_from([0.1, 1.0]))
def test_a_selection_asked_again_is_the_same_and_the_callers_own(cm, gamma, sigma):
    """select's masks are made of cached, read-only ones: a second call gives the same
    mask, and a caller that changes its mask in place changes no later selection."""
    cols, mask = cm
    first = select(cols, system="paper-stable", gamma=gamma, sigma_w=sigma)
    want = first.copy()
    first &= mask  # the caller's own array
    again = select(cols, system="paper-stable", gamma=gamma, sigma_w=sigma)
    np.testing.assert_array_equal(again, want)
    assert again.flags.writeable
    eq = cols.equals("system", "paper-stable")
    assert not eq.flags.writeable and eq is cols.equals("system", "paper-stable")


@settings(max_examples=EXAMPLES, deadline=None)
@given(columns())
def test_has_of_a_text_field_against_plain_python(cm):
    cols, mask = cm
    assert cols.has("system") == any(s is not None for s in cols["system"])
    want = any(s is not None for s, m in zip(cols["system"], mask) if m)
    assert cols.has("system", mask) == want
    assert cols.has("system", np.flatnonzero(mask)) == want


@settings(max_examples=EXAMPLES, deadline=None)
@given(columns())
def test_systems_and_groups_against_plain_python(cm):
    cols, mask = cm
    present = {s for s, m in zip(cols["system"], mask) if m and s is not None}
    assert set(systems_of(cols, mask)) == present
    groups: dict = {}
    for i in np.flatnonzero(mask).tolist():
        key = (_key(float(cols["gamma"][i])), cols["system"][i])
        groups.setdefault(key, []).append(i)
    got = group_indices(cols, ("gamma", "system"), mask)
    assert {k: v.tolist() for k, v in got.items()} == groups
    ordered = sorted(groups, key=lambda k: tuple((v is None, v if v is not None else 0) for v in k))
    assert list(got) == ordered  # by their keys, None last
    by_system = group_indices(cols, ("system", "N"), mask)
    assert list(by_system) == sorted(
        by_system, key=lambda k: tuple((v is None, v if v is not None else 0) for v in k)
    )


@settings(max_examples=EXAMPLES, deadline=None)
@given(columns())
def test_by_N_means_against_plain_python(cm):
    cols, mask = cm
    x0, uN, ys, cnt = by_N(cols, mask, cols["v"], mean_of)
    idx = np.flatnonzero(mask).tolist()
    Ns_present = sorted({cols["N"][i] for i in idx}, key=lambda v: (math.isnan(v), v))
    # NaN N: one group, last (as np.unique puts it)
    Ns_present = [v for v in Ns_present if not math.isnan(v)] + (
        [NAN] if any(math.isnan(cols["N"][i]) for i in idx) else []
    )
    np.testing.assert_array_equal(uN, np.array(Ns_present, dtype=float))
    for j, N in enumerate(Ns_present):
        rows = [i for i in idx if cols["N"][i] == N or (math.isnan(N) and math.isnan(cols["N"][i]))]
        vals = [cols["v"][i] for i in rows if math.isfinite(cols["v"][i])]
        assert cnt[j] == len(vals)
        if vals:
            assert math.isclose(ys[j], math.fsum(vals) / len(vals), rel_tol=1e-12, abs_tol=1e-9)
        else:
            assert math.isnan(ys[j])
        n0 = [cols["N0"][i] for i in rows if math.isfinite(cols["N0"][i])]
        want_x0 = sum(n0) / len(n0) if n0 else N
        assert (math.isnan(x0[j]) and math.isnan(want_x0)) or math.isclose(x0[j], want_x0)
