"""Strict query and path parameters: numbers written in ASCII decimal only.

Pydantic's lax mode (what FastAPI applies to query strings) reads ``+30``, ``3_0``
and ``3.0`` as the integer 30 or 3, and Python's ``int``/``float`` read non-ASCII
digits such as ``٣٠``. A request naming a number must write it plainly; anything
else is a 422 naming the parameter.
"""

from __future__ import annotations

import re
from typing import Annotated

from pydantic import BeforeValidator

INT_TEXT = re.compile(r"-?[0-9]+", re.ASCII)
FLOAT_TEXT = re.compile(r"-?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][-+]?[0-9]+)?", re.ASCII)


def _int_text(value):
    if isinstance(value, str) and not INT_TEXT.fullmatch(value):
        raise ValueError("must be an integer written with the digits 0-9")
    return value


def _float_text(value):
    if isinstance(value, str) and not FLOAT_TEXT.fullmatch(value):
        raise ValueError("must be a finite decimal number (digits 0-9, '.', an exponent)")
    return value


def is_int_text(text: str) -> bool:
    return INT_TEXT.fullmatch(text) is not None


def is_float_text(text: str) -> bool:
    return FLOAT_TEXT.fullmatch(text) is not None


IntText = BeforeValidator(_int_text)
FloatText = BeforeValidator(_float_text)
StrictInt = Annotated[int, IntText]
StrictFloat = Annotated[float, FloatText]
