"""The record glossary (svrobs_core.records.FIELD_GLOSSARY) covers every record field
once, and docs/spec.md#glossary is that table."""

from __future__ import annotations

import re
from pathlib import Path

from svrobs_core.records import FIELD_GLOSSARY, RECORD_FIELDS

DOC = Path(__file__).resolve().parents[2] / "docs" / "spec.md"


UNITS = {  # one word for one unit across the table
    "",
    "dimensionless",
    "state units",
    "state units²",
    "state per input unit",
    "(state per input unit)²",
    "state per output unit",
    "share (0–1)",
    "true/false",
    "rollouts",
    "samples",
    "index",
}


def test_every_record_field_has_a_label_a_unit_and_a_meaning():
    assert list(FIELD_GLOSSARY) == list(RECORD_FIELDS)
    for field, (label, unit, meaning) in FIELD_GLOSSARY.items():
        assert label == label.strip() != "" and meaning and len(meaning) < 100, field
        assert unit in UNITS, (field, unit)


def test_the_docs_glossary_is_the_table():
    text = DOC.read_text(encoding="utf-8").split("\n## Glossary\n", 1)[1]
    rows = {}
    for line in text.splitlines():
        m = re.fullmatch(r"\| `([^`]+)` \| (.*?) \| (.*?) \| (.*) \|", line)
        if m:
            unit = "" if m.group(3) == "—" else m.group(3)
            rows[m.group(1)] = (m.group(2), unit, m.group(4).replace("\\|", "|"))
    assert rows == FIELD_GLOSSARY
