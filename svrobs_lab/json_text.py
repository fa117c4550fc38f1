"""JSON text from a user (a pasted spec, a form field, a file) read with every way it
can fail as one ``ValueError`` in plain words (docs/spec.md#validation-errors).

``json.loads`` fails three ways: a ``JSONDecodeError`` (a ``ValueError``) for bad
syntax, a ``RecursionError`` for arrays or objects nested thousands deep, and a plain
``ValueError`` for an integer longer than ``int()`` converts.
"""

from __future__ import annotations

import json
import sys
from typing import Any


def loads(text: str, **options: Any) -> Any:
    """``json.loads(text, **options)``; its failures as a ``ValueError`` whose message says
    what is wrong (``not valid JSON: ...``, or the integer too long).
    An exception raised by an option's hook that is not a ``ValueError`` passes as it is."""
    try:
        return json.loads(text, **options)
    except json.JSONDecodeError as exc:
        raise ValueError(
            f"not valid JSON: {exc.msg} at line {exc.lineno}, column {exc.colno}"
        ) from None
    except RecursionError:
        raise ValueError("not valid JSON: nested too deeply") from None
    except ValueError as exc:
        if "integer string conversion" not in str(exc):
            raise
        raise ValueError(
            f"an integer of more than {sys.get_int_max_str_digits():,} digits "
            "(a float64 is at most about 1.8e308)"
        ) from None


__all__ = ["loads"]
