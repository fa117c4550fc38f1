"""The record glossary (svrobs_core.records.FIELD_GLOSSARY) as the pages show it: a
column head or axis label, and its tooltip (what the field is and its unit)."""

from __future__ import annotations

from svrobs_core.measured.spec import SIGMA_W_ESTIMATED
from svrobs_core.records import FIELD_GLOSSARY


def label(field: str) -> str:
    """The short human head of ``field`` (its name when it is not a record field)."""
    entry = FIELD_GLOSSARY.get(field)
    return entry[0] if entry else field


def unit(field: str) -> str:
    entry = FIELD_GLOSSARY.get(field)
    return entry[1] if entry else ""


def title(field: str) -> str:
    """The tooltip of ``field``: ``rmse_A: Root mean square ... [dimensionless]``."""
    entry = FIELD_GLOSSARY.get(field)
    if entry is None:
        return field
    _, u, description = entry
    return f"{field}: {description}" + (f" [{u}]" if u else "")


def coordinate(field: str, value) -> str | None:
    """The text of a grid coordinate that is not its number, else None: the σ_w key
    of a dataset job that estimates σ_w (docs/measured.md#spec) is "estimate"."""
    if field == "sigma_w" and value == SIGMA_W_ESTIMATED:
        return "estimate"
    return None


def as_json() -> dict[str, dict[str, str]]:
    """Every field's label, unit and description (for the chart scripts)."""
    return {
        f: {"label": lab, "unit": u, "description": d} for f, (lab, u, d) in FIELD_GLOSSARY.items()
    }
