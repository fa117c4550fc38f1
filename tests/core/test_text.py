"""svrobs_core.text: the one class of characters a name may not hold
(docs/security.md#names-in-downloads-and-pages)."""

import pytest

from svrobs_core.text import UNPRINTABLE, printable, strip_unprintable

REFUSED = [*range(0x20), *range(0x7F, 0xA0), 0x2028, 0x2029, 0xD800, 0xDBFF, 0xDC00, 0xDFFF]


@pytest.mark.parametrize("code", REFUSED, ids=hex)
def test_each_refused_character_is_not_printable_and_is_stripped(code):
    text = f"a{chr(code)}b"
    assert not printable(text) and UNPRINTABLE.search(text)
    assert strip_unprintable(text) == "ab"


def test_the_rest_is_printable_and_kept():
    kept = "".join(chr(c) for c in range(0x3000) if c not in REFUSED)
    kept += "\u00a0\u200b\ufeff\U0001f600"  # no-break and zero-width spaces, BOM, emoji
    assert printable(kept) and strip_unprintable(kept) == kept
