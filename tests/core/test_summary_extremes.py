"""summarize_columns near the ends of the double range (docs/spec.md#summaries).

Oracle: mean and population std in exact rational arithmetic (fractions)."""

from __future__ import annotations

import json
import math
from fractions import Fraction

import pytest

from svrobs_core.records import OVERFLOW_NOTE, summarize_columns


def _exact(values):
    xs = [Fraction(v) for v in values]
    m = sum(xs) / len(xs)
    var = sum((x - m) ** 2 for x in xs) / len(xs)
    k = 1024 if var > 1 else -1024
    return float(m), math.sqrt(float(var / Fraction(2) ** k)) * 2.0 ** (k // 2)


def _one_group(k):
    """The group fields of k records of one group."""
    return {
        "system": ["s"] * k,
        "sigma_w": [1.0] * k,
        "N": [5] * k,
        "estimator": ["ols"] * k,
        "gamma": [None] * k,
    }


def _summary(values):
    cols = {**_one_group(len(values)), "J_exact": list(values)}
    (group,) = summarize_columns(cols)
    json.dumps(group, allow_nan=False)  # always valid JSON
    return group["stats"]["J_exact"]


@pytest.mark.parametrize(
    "values",
    [
        [3e200, 3.2e200, 2.9e200, 3.1e200],  # squared deviations ~1e396
        [1.7e308, -1.7e308],  # the sum of squares ~6e616
        [1.7e308, 1.7e308, 1.6e308],  # the sum itself overflows
        [1e300, -1e-300, 5.0, 1e299],
    ],
)
def test_huge_values_give_the_exact_mean_and_std(values):
    st = _summary(values)
    mean, std = _exact(values)
    assert st["count"] == len(values) and "note" not in st
    assert st["mean"] == pytest.approx(mean, rel=1e-12)
    assert st["std"] == pytest.approx(std, rel=1e-12)


def test_ordinary_values_keep_the_plain_sums_bit_for_bit():
    values = [0.1, 0.7, 1e-3, 2.5]
    st = _summary(values)
    m = sum(values) / 4
    assert st["mean"] == m
    assert st["std"] == math.sqrt(sum((v - m) * (v - m) for v in values) / 4)


def test_a_statistic_beyond_the_double_range_is_null_with_a_note():
    st = _summary([math.inf, 1.0])  # only a non-finite input gets here
    assert st["mean"] is None and st["std"] is None and st["count"] == 2
    assert st["note"] == f"mean and std {OVERFLOW_NOTE}"


def test_one_fields_overflow_leaves_the_other_fields_of_the_call_plain():
    huge, plain = [1.7e308, 1.7e308, 1.6e308], [0.1, 0.7, 2.5]
    cols = {
        **_one_group(3),
        "J_exact": huge,
        "rmse_A": plain,
        "J_mc": [None, 1.0, 3.0],  # nulls skipped
        "certified": [True, False, True],  # booleans as 0/1
    }
    (group,) = summarize_columns(cols)
    st = group["stats"]
    mean, std = _exact(huge)
    assert st["J_exact"]["mean"] == pytest.approx(mean, rel=1e-12)
    assert st["J_exact"]["std"] == pytest.approx(std, rel=1e-12)
    mean, std = _exact(plain)
    assert st["rmse_A"]["mean"] == pytest.approx(mean, rel=1e-15)
    assert st["rmse_A"]["std"] == pytest.approx(std, rel=1e-15)
    for f in ("J_exact", "rmse_A", "J_mc", "certified"):  # each the field's own, to the bit
        alone = {**_one_group(3), f: cols[f]}
        assert st[f] == summarize_columns(alone)[0]["stats"][f]
    assert st["J_mc"] == {"mean": 2.0, "std": 1.0, "count": 2}
    assert st["certified"]["mean"] == pytest.approx(2 / 3, rel=1e-15)
    assert st["J_opt"] == {"mean": None, "std": None, "count": 0}  # not a column here


@pytest.mark.parametrize("values", [[1.0], [1.0, 2.0, 3.0, 4.0], 1.0])
def test_a_summary_field_of_another_length_than_the_keys_is_refused(values):
    cols = {**_one_group(3), "J_exact": values}
    with pytest.raises(ValueError, match="'J_exact' has"):
        summarize_columns(cols)
