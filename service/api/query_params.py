"""The query-string rules of the API (issue 11, item 4), in one place.

* :func:`reject_unknown_query`, a dependency of every router: a query parameter the
  route does not declare is a 422 naming it (``sort=-rmse_A`` on a route without
  ``sort`` is never silently ignored). A route taking parameters by pattern (the
  range filters of the results) says so with :func:`accepts_query`.
* :func:`sort_order`: ``sort=-rmse_A,N`` -> ORDER BY of numeric record fields,
  ``-`` for descending; nulls last either way.
* :func:`range_conditions`: ``rmse_A_lt=0.01``, ``N_gte=100`` -> WHERE conditions on
  numeric record fields (suffixes ``_lt``, ``_lte``, ``_gt``, ``_gte``).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable

from fastapi import Request

from service.api.errors import FieldHTTPException
from svrobs_core.records import BOOL_FIELDS, NUMERIC_FIELDS

RANGE_OPS = {"lt": "__lt__", "lte": "__le__", "gt": "__gt__", "gte": "__ge__"}
RANGE_RE = re.compile(r"^(?P<field>\w+?)_(?P<op>lt|lte|gt|gte)$")
MAX_SORT_KEYS = 5
RANGE_FIELDS = tuple(f for f in NUMERIC_FIELDS if f not in BOOL_FIELDS)  # booleans: no <


def accepts_query(predicate: Callable[[str], bool]):
    """Mark a route's endpoint as also taking the query parameters ``predicate`` accepts."""

    def mark(endpoint):
        endpoint.extra_query = predicate
        return endpoint

    return mark


def _declared(route) -> frozenset[str]:
    """The query parameter names of a route and its dependencies (cached on it)."""
    names = getattr(route, "_declared_query", None)
    if names is None:
        found, todo = set(), [route.dependant]
        while todo:
            dep = todo.pop()
            found.update(p.alias for p in dep.query_params)
            todo.extend(dep.dependencies)
        names = route._declared_query = frozenset(found)
    return names


async def reject_unknown_query(request: Request) -> None:
    """422 naming the first query parameter the route neither declares nor accepts."""
    route = request.scope.get("route")
    if route is None or not hasattr(route, "dependant"):
        return
    declared = _declared(route)
    extra = getattr(route.endpoint, "extra_query", None)
    for name in dict.fromkeys(request.query_params.keys()):
        if name in declared or (extra is not None and extra(name)):
            continue
        known = ", ".join(sorted(declared)) or "none"
        raise FieldHTTPException(
            422, f"unknown query parameter {name!r} (this route takes: {known})", name
        )


def is_range_param(name: str) -> bool:
    m = RANGE_RE.match(name)
    return m is not None and m.group("field") in RANGE_FIELDS


def _numeric(field: str, param: str) -> None:
    if field not in NUMERIC_FIELDS:
        raise FieldHTTPException(
            422, f"{field!r} is not a numeric record field; one of {list(NUMERIC_FIELDS)}", param
        )


def sort_order(sort: str | None, table) -> list:
    """ORDER BY terms of ``sort`` (comma-separated numeric fields, ``-`` descending)."""
    if not sort:
        return []
    keys = [k.strip() for k in sort.split(",") if k.strip()]
    if not keys or len(keys) > MAX_SORT_KEYS:
        raise FieldHTTPException(
            422, f"must name 1 to {MAX_SORT_KEYS} numeric fields, e.g. -rmse_A", "sort"
        )
    terms = []
    for key in keys:
        desc = key.startswith("-")
        field = key.lstrip("+-")
        _numeric(field, "sort")
        col = table.c[field]
        terms.append((col.desc() if desc else col.asc()).nulls_last())
    return terms


def range_conditions(request: Request, table) -> list:
    """WHERE conditions of the range parameters in the query string (finite numbers)."""
    return range_terms(request.query_params.multi_items(), table)


def range_terms(items, table) -> list:
    """WHERE conditions of the ``(name, value)`` pairs that are range parameters."""
    conds = []
    for name, value in items:
        m = RANGE_RE.match(name)
        if m is None or m.group("field") not in RANGE_FIELDS:
            continue
        try:
            v = float(value)
        except ValueError:
            raise FieldHTTPException(422, "must be a number", name) from None
        if not math.isfinite(v):
            raise FieldHTTPException(422, "must be finite", name)
        col = table.c[m.group("field")]
        conds.append(getattr(col, RANGE_OPS[m.group("op")])(v))
    return conds
