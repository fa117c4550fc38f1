"""Strict numeric query and path parameters: numbers written in ASCII decimal only.

Pydantic's lax mode (what FastAPI applies to query strings) reads ``+30``, ``3_0``
and ``3.0`` as the integer 30 or 3, and Python's ``int``/``float`` read non-ASCII
digits such as ``٣٠``. A request naming a number must write it plainly; anything
else is a 422 naming the parameter. The raw text is checked (:func:`check_numbers`,
from :mod:`service.http.query_text` on every route of the API and every page) before
FastAPI parses it, so the declared types, and their OpenAPI bounds, stay plain
``int`` and ``float``. A parameter named by pattern (a range filter ``rmse_A_lt``)
or read by a page from its form is read by :func:`read_number` /
:func:`read_int32`. An integer compared with a column (a grid coordinate N or rep)
is also within the column's 32 bits (:func:`int32_problem`): a larger one would
overflow the driver (SQLite's 64-bit INTEGER, PostgreSQL's ``::INTEGER``).
"""

from __future__ import annotations

import math
import re

from .auth import MAX_ID
from .errors import Invalid

INT_TEXT = re.compile(r"-?[0-9]+", re.ASCII)
FLOAT_TEXT = re.compile(r"-?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][-+]?[0-9]+)?", re.ASCII)

# the integer and number parameters of the API's routes, by name
INT_PARAMS = frozenset({"limit", "offset", "N", "rep", "job_id", "schedule_id", "dataset_id"})
FLOAT_PARAMS = frozenset({"sigma_w"})
INT32_MIN, INT32_MAX = -MAX_ID - 1, MAX_ID  # an integer column's range on every dialect
NON_FINITE = frozenset({"nan", "inf", "infinity"})  # what float() reads but is no bound


def is_int_text(text: str) -> bool:
    return INT_TEXT.fullmatch(text) is not None


def is_float_text(text: str) -> bool:
    return FLOAT_TEXT.fullmatch(text) is not None


def int32_problem(text: str) -> str | None:
    """Why ``text`` is not an integer of a 32-bit column, written in ASCII decimal, or
    None."""
    if not is_int_text(text):
        return "must be an integer"
    digits = text.lstrip("-").lstrip("0")  # int() of over 4300 digits is an error
    sign = -1 if text.startswith("-") else 1
    if len(digits) > 10 or not INT32_MIN <= sign * int(digits or "0") <= INT32_MAX:
        return f"must be from {INT32_MIN} to {INT32_MAX}"
    return None


def number_problem(text: str) -> str | None:
    """Why ``text`` is not a finite number written in ASCII decimal, or None."""
    if is_float_text(text):
        return None if math.isfinite(float(text)) else "must be finite"
    return "must be finite" if text.lower().lstrip("+-") in NON_FINITE else "must be a number"


def read_int32(name: str, text: str) -> int:
    """The integer of parameter ``name``, a 32-bit column's (Invalid naming it otherwise)."""
    problem = int32_problem(text)
    if problem is not None:
        raise Invalid(problem, field=name)
    return int(text)


def read_number(name: str, text: str) -> float:
    """The finite number of parameter ``name`` (Invalid naming it otherwise)."""
    problem = number_problem(text)
    if problem is not None:
        raise Invalid(problem, field=name)
    return float(text)


def check_numbers(items) -> tuple[str, str] | None:
    """``(name, message)`` of the first (name, raw text) pair of a numeric parameter
    that is not plain ASCII decimal, or None."""
    for name, value in items:
        if name in INT_PARAMS and not is_int_text(value):
            return name, "must be an integer written with the digits 0-9"
        if name in FLOAT_PARAMS and not is_float_text(value):
            return name, "must be a decimal number (digits 0-9, '.', an exponent)"
    return None
