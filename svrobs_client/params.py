"""Query parameters of ``GET /jobs/{id}/results``, checked before any request.

Filters on grid coordinates (``system``, ``sigma_w``, ``N``, ``estimator``, ``gamma``,
``rep``), ``sort`` on numeric record fields (``"-rmse_A,N"``, ``-`` descending) and
range filters ``<field>_lt``, ``_lte``, ``_gt``, ``_gte`` on the non-boolean numeric
fields (README, "API"). A typo is a :class:`TypeError` (an unknown name) or a
:class:`ValueError` (a bad value) here; the server's 422 is the backstop.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Mapping
from numbers import Real
from typing import Any

__all__ = ["NUMERIC_FIELDS", "RANGE_FIELDS", "RESULT_FILTERS", "results_params", "sort_param"]

RESULT_FILTERS = ("system", "sigma_w", "N", "estimator", "gamma", "rep")
# docs/spec.md#record-fields: the scalar numeric record fields (svrobs_core.records.NUMERIC_FIELDS;
# a test keeps the two equal without making the client import the core). Booleans sort
# but take no range.
BOOL_FIELDS = ("thm1_holds_A", "thm1_holds_B", "stable_certified", "certified")
NUMERIC_FIELDS = (
    *("sigma_w", "N", "N0", "gamma", "rep", "rmse_A", "rmse_B", "H_A", "H_B", "r_A", "r_B"),
    *("eps_A", "eps_B", "coverage_A", "coverage_B", "thm1_holds_A", "thm1_holds_B"),
    *("rho_upper_bound", "stable_certified", "g_L", "certified", "rho_true", "J_exact"),
    *("J_stationary", "J_mc", "J_mc_se", "J_star", "cost_ratio", "J_bound", "delta_J"),
    *("J_opt", "J_opt_bound"),
)
RANGE_FIELDS = tuple(f for f in NUMERIC_FIELDS if f not in BOOL_FIELDS)
RANGE_OPS = ("lt", "lte", "gt", "gte")
MAX_SORT_KEYS = 5
_RANGE = re.compile(r"^(?P<field>\w+?)_(?P<op>lt|lte|gt|gte)$")


def _values(value: Any) -> list[Any]:
    return list(value) if isinstance(value, Iterable) and not isinstance(value, str) else [value]


def sort_param(sort: str | Iterable[str]) -> str:
    """``"-rmse_A,N"`` or ``["-rmse_A", "N"]`` -> the ``sort`` parameter; ValueError
    naming a key that is not a numeric record field."""
    keys = sort.split(",") if isinstance(sort, str) else list(sort)
    keys = [str(k).strip() for k in keys if str(k).strip()]
    if not 1 <= len(keys) <= MAX_SORT_KEYS:
        raise ValueError(f"sort must name 1 to {MAX_SORT_KEYS} numeric fields, e.g. '-rmse_A'")
    for key in keys:
        if key.lstrip("+-") not in NUMERIC_FIELDS:
            raise ValueError(
                f"sort: {key.lstrip('+-')!r} is not a numeric record field; "
                f"one of {', '.join(NUMERIC_FIELDS)}"
            )
    return ",".join(keys)


def _range_value(name: str, value: Any) -> str:
    m = _RANGE.match(name)
    field = m.group("field") if m else None
    if field in BOOL_FIELDS:
        raise TypeError(f"{name}: {field} is a yes/no field; ranges take numeric fields")
    if field not in RANGE_FIELDS:
        raise TypeError(
            f"unknown results filter {name!r}; filters: {', '.join(RESULT_FILTERS)}, and "
            f"<field>_lt/_lte/_gt/_gte on a numeric field ({', '.join(RANGE_FIELDS)})"
        )
    if isinstance(value, str):
        try:
            value = float(value)
        except ValueError:
            raise ValueError(f"{name} must be a number, got {value!r}") from None
    if isinstance(value, bool) or not isinstance(value, Real):
        raise TypeError(f"{name} must be a number, got {type(value).__name__}")
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return repr(float(value)) if isinstance(value, float) else str(math.trunc(value))


def results_params(
    filters: Mapping[str, Any], sort: str | Iterable[str] | None = None
) -> dict[str, Any]:
    """Filters, ranges and ``sort`` -> query parameters (a sequence repeats a grid
    filter; for ``gamma``, ``None`` selects OLS, whose gamma is null)."""
    params: dict[str, Any] = {}
    if sort is not None:
        params["sort"] = sort_param(sort)
    for name, value in filters.items():
        if name in ("limit", "offset"):
            if value is not None:
                params[name] = int(value)
        elif name in RESULT_FILTERS:
            if value is None and name != "gamma":
                continue
            values = _values(value)
            if name == "gamma":
                values = ["null" if v is None else v for v in values]
            params[name] = [str(v) for v in values]
        else:
            params[name] = _range_value(name, value)
    return params
