"""results: a radius matrix equal to its row's scalar radius stored as zero bytes

With the paper's bounds (docs/science.md#3-error-bounds-theorem-1-lemma-2-corollary-1) every
entry of ``radii_A`` is ``r_A``
and every entry of ``radii_B`` is ``r_B``: 0006 stored each as that float's 8
bytes (rows it converted from the JSON format: every entry); from here such a matrix is stored as zero bytes and read back from the
row's ``r_A`` / ``r_B`` (``service.db.result_codec``), 16 bytes less per cell.
The upgrade converts the rows whose radius entries are bit for bit their
finite scalar; the downgrade writes the 8 bytes back. Rows are visited in key order,
in batches (keyset pagination: never a cursor over rows being updated).

Revision ID: 0007
Revises: 0006
Create Date: 2026-12-01 12:40:00
"""

from __future__ import annotations

import math
import struct

import sqlalchemy as sa
from alembic import op

revision = "0007"
down_revision = "0006"
branch_labels = None
depends_on = None

KEY = ("job_id", "system", "sigma_w", "N", "estimator", "gamma_key", "rep")
PAIRS = (("radii_A", "r_A"), ("radii_B", "r_B"))
BATCH = 2000

results = sa.table(
    "results",
    *[sa.column(c) for c in KEY],
    *[sa.column(r) for _, r in PAIRS],
    *[sa.column(m, sa.LargeBinary()) for m, _ in PAIRS],
)


def _packed(v) -> bytes | None:
    return struct.pack("<d", v) if v is not None and math.isfinite(v) else None


def _convert(stored, new_value) -> None:
    """Rewrite the radius blobs that ``stored(length)`` selects (a SQL condition on
    their length) to ``new_value(blob, r)`` (a blob, or None to keep it)."""
    conn = op.get_bind()
    t = results
    lengths = [stored(sa.func.length(t.c[m])) for m, _ in PAIRS]
    update = (
        t.update()
        .where(*(t.c[k] == sa.bindparam(f"k_{k}") for k in KEY))
        .values({m: sa.bindparam(f"v_{m}") for m, _ in PAIRS})
    )
    last = None
    while True:
        q = sa.select(*t.c).where(sa.or_(*lengths))
        if last is not None:
            q = q.where(sa.tuple_(*(t.c[k] for k in KEY)) > sa.tuple_(*last))
        rows = conn.execute(q.order_by(*(t.c[k] for k in KEY)).limit(BATCH)).mappings().all()
        if not rows:
            return
        changes = []
        for r in rows:
            new = {m: new_value(r[m], r[s]) for m, s in PAIRS}
            if any(v is not None for v in new.values()):
                changes.append(
                    {
                        **{f"k_{k}": r[k] for k in KEY},
                        **{f"v_{m}": r[m] if new[m] is None else new[m] for m, _ in PAIRS},
                    }
                )
        if changes:
            conn.execute(update, changes)
        last = [rows[-1][k] for k in KEY]


def upgrade() -> None:
    def to_empty(blob, r):  # every entry (or the one float of 0006's short form) is r
        one = _packed(r)
        if blob is None or one is None or not len(blob) or len(blob) % 8:
            return None
        return b"" if bytes(blob) == one * (len(blob) // 8) else None

    _convert(lambda length: length > 0, to_empty)


def downgrade() -> None:
    def to_float(blob, r):
        return _packed(r) if blob is not None and len(blob) == 0 else None

    _convert(lambda length: length == 0, to_float)
