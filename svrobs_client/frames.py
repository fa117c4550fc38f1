"""JSON from the API -> pandas DataFrames (pandas is the optional ``dataframe`` extra).

Records keep the field order of docs/spec.md#record-fields; the matrix fields become 2-D float
numpy arrays (a ``null`` entry becomes NaN, a ``null`` matrix stays ``None``).
"""

from __future__ import annotations

from typing import Any

# docs/spec.md#record-fields: the record fields holding matrices (svrobs_core.records.MATRIX_FIELDS;
# a test keeps the two equal, without making the client import the core).
MATRIX_FIELDS = ("A_hat", "B_hat", "radii_A", "radii_B", "L", "K")
GROUP_FIELDS = ("system", "sigma_w", "N", "estimator", "gamma")


def _pandas() -> Any:
    try:
        import pandas as pd
    except ImportError:
        raise ImportError(
            "DataFrames need pandas: pip install pandas (in a checkout: "
            ".venv/bin/pip install -e '.[dataframe]') "
            "(or use the *_records methods, which return plain dicts)"
        ) from None
    return pd


def _matrix(value: Any) -> Any:
    import numpy as np

    return None if value is None else np.asarray(value, dtype=float)


def records_frame(records: list[dict[str, Any]], *, columns: list[str] | None = None) -> Any:
    """One row per record, columns in record order, matrices as numpy arrays."""
    pd = _pandas()
    if columns is None:
        columns = list(records[0]) if records else []
    df = pd.DataFrame.from_records(records, columns=columns)
    for f in MATRIX_FIELDS:
        if f in df.columns:
            df[f] = pd.Series([_matrix(v) for v in df[f]], index=df.index, dtype=object)
    return df


def summary_frame(body: dict[str, Any], *, long: bool = False) -> Any:
    """``GET /jobs/{id}/summary`` as a DataFrame.

    Wide (default): one row per group (system, sigma_w, N, estimator, gamma) with
    ``count`` and ``<field>_mean``, ``<field>_std``, ``<field>_count`` per numeric field.
    Long: one row per (group, field) with ``mean``, ``std``, ``count``. ``attrs`` holds
    ``job_id`` and ``partial`` (true while the job is not yet succeeded).
    """
    pd = _pandas()
    rows = []
    for g in body.get("groups", []):
        key = {k: g.get(k) for k in GROUP_FIELDS}
        stats = g.get("stats") or {}
        if long:
            for name, s in stats.items():
                rows.append({**key, "field": name, **_stat(s)})
        else:
            row = {**key, "count": g.get("count")}
            for name, s in stats.items():
                row.update({f"{name}_{k}": v for k, v in _stat(s).items()})
            rows.append(row)
    cols = [*GROUP_FIELDS, "field", "mean", "std", "count"] if long else None
    df = pd.DataFrame.from_records(rows, columns=cols)
    df.attrs.update(job_id=body.get("job_id"), partial=bool(body.get("partial")))
    return df


def _stat(s: dict[str, Any]) -> dict[str, Any]:
    return {"mean": s.get("mean"), "std": s.get("std"), "count": s.get("count")}


def compare_frame(body: dict[str, Any]) -> Any:
    """``GET /compare`` as a DataFrame: ``job_id``, the ``by`` fields, ``mean``, ``std``,
    ``count``; ``attrs`` holds ``metric``, ``by`` and ``jobs``."""
    pd = _pandas()
    cols = ["job_id", *body.get("by", []), "mean", "std", "count"]
    df = pd.DataFrame.from_records(body.get("rows", []), columns=cols)
    df.attrs.update(metric=body.get("metric"), by=list(body.get("by", [])), jobs=body.get("jobs"))
    return df
