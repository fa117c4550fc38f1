"""Strict numeric query and path parameters: numbers written in ASCII decimal only.

Pydantic's lax mode (what FastAPI applies to query strings) reads ``+30``, ``3_0``
and ``3.0`` as the integer 30 or 3, and Python's ``int``/``float`` read non-ASCII
digits such as ``٣٠``. A request naming a number must write it plainly; anything
else is a 422 naming the parameter. The raw text is checked (:func:`check_numbers`,
from :func:`service.api.deps.clean_query_text` on every route) before FastAPI
parses it, so the declared types, and their OpenAPI bounds, stay plain ``int`` and
``float``.
"""

from __future__ import annotations

import re

INT_TEXT = re.compile(r"-?[0-9]+", re.ASCII)
FLOAT_TEXT = re.compile(r"-?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][-+]?[0-9]+)?", re.ASCII)

# the integer and number parameters of the API's routes, by name
INT_PARAMS = frozenset({"limit", "offset", "N", "rep", "job_id", "schedule_id", "dataset_id"})
FLOAT_PARAMS = frozenset({"sigma_w"})


def is_int_text(text: str) -> bool:
    return INT_TEXT.fullmatch(text) is not None


def is_float_text(text: str) -> bool:
    return FLOAT_TEXT.fullmatch(text) is not None


def check_numbers(items) -> tuple[str, str] | None:
    """``(name, message)`` of the first (name, raw text) pair of a numeric parameter
    that is not plain ASCII decimal, or None."""
    for name, value in items:
        if name in INT_PARAMS and not is_int_text(value):
            return name, "must be an integer written with the digits 0-9"
        if name in FLOAT_PARAMS and not is_float_text(value):
            return name, "must be a decimal number (digits 0-9, '.', an exponent)"
    return None
