"""The query-text rule of every route, the API's and the web's: a query parameter (or
an Idempotency-Key) holding a NUL character, or a numeric parameter not written in
plain ASCII decimal (:mod:`svrobs_lab.params`), is a 422 naming it
(:class:`svrobs_lab.errors.Invalid`: JSON under /api/v1, the error page on the web).
On the web, a form's empty field is no value, in a query (:class:`EmptyFieldsAbsent`)
and in a posted form that a route parses itself (:func:`form_without_empty_fields`);
FastAPI gives a declared ``Form()`` field sent empty its default."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Sequence
from urllib.parse import unquote_plus

from fastapi import Request
from starlette.datastructures import UploadFile
from starlette.types import ASGIApp, Receive, Scope, Send

from svrobs_lab.errors import Invalid
from svrobs_lab.params import check_numbers


def check_query_text(request: Request, *, empty_is_absent: bool = False) -> None:
    """Invalid for a query parameter or an Idempotency-Key holding a NUL character
    (which a PostgreSQL text column cannot hold: it would be a 500 there and a silent
    miss on SQLite), and for a numeric query or path parameter not written in plain
    ASCII decimal (``+30``, ``3_0``, ``3.0``, ``٣٠`` are not the integer 30). With
    ``empty_is_absent``, an empty value (a form's empty field) is not a number."""
    items = list(request.query_params.multi_items())
    key = request.headers.get("idempotency-key")
    for name, value in items + ([("Idempotency-Key", key)] if key is not None else []):
        if "\x00" in name or "\x00" in value:
            raise Invalid(
                "must not contain NUL (\\u0000) characters", field=name.replace("\x00", "")
            )
    numbers = [(k, v) for k, v in items if not (empty_is_absent and v == "")]
    # a path parameter as sent (one a route's ``{id:int}`` converted is digits already)
    numbers += [(k, v) for k, v in request.path_params.items() if isinstance(v, str)]
    bad = check_numbers(numbers)
    if bad is not None:
        raise Invalid(bad[1], field=bad[0])


async def clean_query_text(request: Request) -> None:
    """The rule on an /api/v1 route: every value as sent."""
    check_query_text(request)


async def clean_page_query(request: Request) -> None:
    """The rule on a web page: a form's empty field (``rep=``) is no value."""
    check_query_text(request, empty_is_absent=True)


def kept_fields(fields: Sequence[tuple[str, bool]]) -> list[bool]:
    """Which fields of a form, each ``(name, empty)``, count as sent: all but a name
    sent once with an empty value (a form's empty field). A name sent more than once
    keeps every value: the empty ones hold their place in a row of parallel fields."""
    sent = Counter(name for name, _ in fields)
    return [not empty or sent[name] > 1 for name, empty in fields]


def without_empty_fields(query: bytes) -> bytes:
    """A raw query string without a form's empty fields (:func:`kept_fields`: ``at=``,
    or ``at`` alone, sent once)."""
    parts = query.split(b"&")
    fields = [
        (unquote_plus(name.decode("latin-1")), not value)
        for name, _, value in (p.partition(b"=") for p in parts)
    ]
    return b"&".join(p for p, keep in zip(parts, kept_fields(fields), strict=True) if keep)


def form_without_empty_fields(
    items: Sequence[tuple[str, str | UploadFile]],
) -> list[tuple[str, str | UploadFile]]:
    """A posted form's fields without its empty ones (:func:`kept_fields`): a text
    field left empty, a file field with no file chosen (no name, no bytes)."""
    fields = [
        (name, value == "" if isinstance(value, str) else not (value.filename or value.size))
        for name, value in items
    ]
    return [item for item, keep in zip(items, kept_fields(fields), strict=True) if keep]


class EmptyFieldsAbsent:
    """ASGI middleware: on a path ``applies(path)`` accepts (the web's pages), a query
    parameter sent once with an empty value, a form's empty field, is left out before
    the request is routed, so the page sees no value (the parameter's default) rather
    than an empty text that is not a number."""

    def __init__(self, app: ASGIApp, applies: Callable[[str], bool]):
        self.app, self.applies = app, applies

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and scope.get("query_string") and self.applies(scope["path"]):
            scope = {**scope, "query_string": without_empty_fields(scope["query_string"])}
        await self.app(scope, receive, send)
