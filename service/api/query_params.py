"""The query-string rule of the API: a query parameter the route does not declare is a
422 naming it (``sort=-rmse_A`` on a route without ``sort`` is never silently
ignored). :func:`reject_unknown_query` is a dependency of every router; a route
taking parameters by pattern (the range filters of the results,
:func:`service.db.result_queries.is_range_param`) says so with :func:`accepts_query`.
"""

from __future__ import annotations

from collections.abc import Callable

from fastapi import Request

from svrobs_lab.errors import Invalid


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
        found: set[str] = set()
        todo = [route.dependant]
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
        raise Invalid(f"unknown query parameter {name!r} (this route takes: {known})", field=name)
