"""Names users give things (systems, datasets, columns, labels): printable text only.

A name is shown in terminals, pages, file names and CSV cells; a control character
(an ESC starts a terminal escape sequence, a line break splits a table row) or a lone
surrogate (which UTF-8 cannot encode) has no place in one (docs/security.md).
"""

from __future__ import annotations

import re

# the characters a name may not hold: C0 and C1 control characters, DEL, line and
# paragraph separators (U+2028, U+2029), lone surrogates
UNPRINTABLE = re.compile(r"[\x00-\x1f\x7f-\x9f\u2028\u2029\ud800-\udfff]")


NOT_PRINTABLE = "must be printable text (no control characters)"  # the message of a refusal


def printable(text: str) -> bool:
    """No control character, line separator or lone surrogate in ``text``."""
    return UNPRINTABLE.search(text) is None


def strip_unprintable(text: str) -> str:
    """``text`` without the characters :func:`printable` refuses."""
    return UNPRINTABLE.sub("", text)


__all__ = ["NOT_PRINTABLE", "UNPRINTABLE", "printable", "strip_unprintable"]
