"""svrobs_core.float_text.json_texts against json.dumps (Python's repr of each float)."""

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from svrobs_core.float_text import json_texts
from svrobs_core.records import json_value


def dumps_rows(arr: np.ndarray) -> list[str]:
    """The oracle: json.dumps of each row as the records hold it (NaN/inf -> null)."""
    return [json.dumps(json_value(row), allow_nan=False) for row in arr]


any_float = st.floats(allow_nan=True, allow_infinity=True, width=64)


@settings(max_examples=300, deadline=None)
@given(hnp.arrays(np.float64, st.integers(1, 60), elements=any_float))
def test_scalar_rows_are_json_dumps(arr):
    assert json_texts(arr) == dumps_rows(arr)


@settings(max_examples=200, deadline=None)
@given(
    hnp.arrays(
        np.float64,
        st.tuples(st.integers(1, 8), st.integers(1, 4), st.integers(1, 4)),
        elements=any_float,
    )
)
def test_matrix_rows_are_json_dumps(arr):
    assert json_texts(arr) == dumps_rows(arr)


def test_every_decade_and_the_layout_boundaries():
    """Each power of ten from the smallest subnormal to the largest double, their
    neighbours, and the ranges where orjson's layout differs from Python's
    (one-digit exponents, 1e-5 <= |x| < 1e-4, numbers like 10.00001)."""
    rng = np.random.default_rng(0)
    decades = 10.0 ** np.arange(-323, 309)
    x = np.concatenate(
        [
            decades,
            -decades,
            np.nextafter(decades, 0),
            np.nextafter(decades, np.inf),
            rng.standard_normal(20_000) * 10.0 ** rng.integers(-12, 20, 20_000),
            rng.uniform(1e-5, 1e-4, 2_000) * rng.choice([-1, 1], 2_000),
            10 + rng.uniform(0, 1e-4, 2_000),
            [0.0, -0.0, 5e-324, 1.7976931348623157e308, 1e15, 1e16, 0.1, 1 / 3, 2.0],
            [np.nan, np.inf, -np.inf],
        ]
    )
    assert json_texts(x) == dumps_rows(x)
    mats = x[: 3 * 3 * 2_000].reshape(-1, 3, 3)
    assert json_texts(mats) == dumps_rows(mats)
    assert json_texts(x[:1_200].reshape(-1, 4)) == dumps_rows(x[:1_200].reshape(-1, 4))


def test_empty_and_bad_shapes():
    assert json_texts(np.zeros(0)) == []
    with pytest.raises(ValueError, match="scalar"):
        json_texts(np.float64(1.0))
    with pytest.raises(ValueError, match="without entries"):
        json_texts(np.zeros((3, 0)))


def test_without_orjsons_layout_every_array_is_written_by_repr(monkeypatch):
    """Where orjson's text of a float is not repr's (orjson before 3.11.7 wrote
    1e16 for 1e+16), the module writes every entry by repr: the same text."""
    import svrobs_core.float_text as ft

    rng = np.random.default_rng(1)
    x = rng.standard_normal(3_000) * 10.0 ** rng.integers(-320, 300, 3_000)
    x[::97] = np.nan
    x[::89] = -np.inf
    monkeypatch.setattr(ft, "_FAST", False)
    assert json_texts(x) == dumps_rows(x)
    assert json_texts(x[:2_997].reshape(-1, 3, 1)) == dumps_rows(x[:2_997].reshape(-1, 3, 1))


def test_the_orjson_installed_writes_repr_text():
    """The fast path is on with the orjson this project requires (>= 3.11.7)."""
    from svrobs_core import float_text

    assert float_text._FAST


def test_unit_fields_of_every_kind_are_json_dumps():
    """unit_result's per-field writer (the one json_lines uses) against json.dumps
    of json_value per cell: floats, matrices, booleans of one and of more
    dimensions, objects, and a field constant along the repetitions."""
    from svrobs_core.unit_result import _json_strings

    rng = np.random.default_rng(2)
    R, E = 4, 3
    fields = [
        rng.standard_normal((R, E)) * 1e-6,
        rng.standard_normal((R, E, 2, 3)),
        rng.random((R, E)) < 0.5,
        rng.random((R, E, 2)) < 0.5,
        np.array([[None, 1.5, "x"]] * R, dtype=object),
        np.broadcast_to(rng.standard_normal((E, 3, 1)), (R, E, 3, 1)),
    ]
    for f in fields:
        cells = np.asarray(f).reshape((R * E,) + np.shape(f)[2:])
        assert _json_strings(f, R * E) == [json.dumps(json_value(c)) for c in cells]
