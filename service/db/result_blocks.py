"""A unit's stored cells as report columns, one binary value per unit
(``result_blocks``).

A report build that reads a large job's rows gets one Python object per value
(3.8 s for the 625,050 cells of the paper's preset on SQLite). The worker therefore
writes, with a unit's rows and in the same transaction, the values it stored as
the report's float64 columns (:data:`BLOCK_FIELDS`): every scalar field (NULL as
NaN, booleans as 0/1), each text field as a code into the block's own list of
values, ``notes`` as its ``result_notes`` id (-1: none) and ``gamma_key``. A
column whose values are all the same bits is stored once. :func:`block_columns`
reads a job's blocks into the arrays :func:`~service.db.report_order.ordered_columns`
puts in the row read's order: the same columns as the rows give, bit for bit.

The blocks are a copy kept only as long as it is needed: a job's are deleted when
its report is stored (and with its rows, when they are pruned or the job deleted).
A job whose blocks do not add up to its rows (stored before blocks existed, or
with another :data:`BLOCK_FIELDS`), or whose blocks hold fewer than
:data:`MIN_ROWS_PER_BLOCK` rows on average, is read from its rows
(docs/performance.md#the-first-report-of-a-large-job).
"""

from __future__ import annotations

import itertools
import json
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from sqlalchemy import delete, func, insert, select
from sqlalchemy.orm import Session

from svrobs_core.report.columns import SCALAR_FIELDS, FirstCodes

from .models import ResultBlock
from .report_order import CODED, collated, driver_errors, psycopg_conn

BLOCKS = ResultBlock.__table__
# the report's fields as stored in a block, in this order ("notes" holds the id)
BLOCK_FIELDS = (*SCALAR_FIELDS, *CODED, "notes", "gamma_key")
_HEADER = 4  # bytes of the header's length, little-endian, before the JSON header
_PER_READ = 8  # blocks fetched at once
# Below this many rows per block on average the row read is faster (a block costs
# about 35 us to parse and place, a row about 6 us to read: 20,000 blocks of one
# row took 0.72 s, their rows 0.40 s)
MIN_ROWS_PER_BLOCK = 16
_CURSORS = itertools.count()  # a name per server-side cursor: two reads may overlap
_SELECT = "SELECT n_rows, data FROM result_blocks WHERE job_id = %s"  # psycopg's, in binary


@dataclass(frozen=True)
class BlockDraft:
    """A block without its ``notes`` ids (:func:`draft_block`): made from a unit's
    columns before the write transaction, finished by :func:`finish_block` once the
    notes' ids are known."""

    n: int
    text: dict[str, list]
    runs: list[int]
    parts: list[np.ndarray]
    note_codes: np.ndarray  # each row's note, as a code into the block's notes
    note_rows: list[int]  # the first row of each of those notes


def draft_block(
    columns: Mapping[str, Sequence],
    *,
    signed_zeros: bool = True,
    arrays: Mapping[str, np.ndarray] | None = None,
) -> BlockDraft:
    """The block of a unit's columns as stored (``upsert_results``' return, or its
    :class:`~service.db.results_store.UnitColumns`' columns: the same values, the
    notes as texts or ids). ``arrays``: some scalar fields already as float arrays
    of those values (NaN for NULL, booleans 0/1: ``UnitResult.summary_columns``),
    used instead of their columns. ``signed_zeros=False`` stores -0.0 as 0.0, as
    SQLite does."""
    arrays = arrays or {}
    k = len(columns["system"])
    text: dict[str, list] = {}
    runs: list[int] = []
    parts: list[np.ndarray] = []
    note_codes, note_rows = np.zeros(k, dtype=np.int64), []
    for f in BLOCK_FIELDS:
        if f in CODED:
            lut = FirstCodes()
            a = lut.encode(columns[f]).astype(float)
            text[f] = list(lut)
        elif f == "notes":  # filled in by finish_block
            note_codes = FirstCodes().encode(columns["notes_id"])
            note_rows = np.unique(note_codes, return_index=True)[1].tolist()
            runs.append(0)
            parts.append(np.empty(0))
            continue
        else:
            given = arrays.get(f)
            # None -> NaN, booleans -> 0/1
            a = np.array(columns[f] if given is None else given, dtype=float)  # a copy
            if not signed_zeros:
                a += 0.0  # -0.0 -> 0.0
        runs.append(_runs(a, k))
        parts.append(a[: runs[-1]])
    return BlockDraft(k, text, runs, parts, note_codes, note_rows)


def finish_block(draft: BlockDraft, note_ids: Sequence) -> bytes:
    """The block's bytes, with the rows' notes ids (``note_ids``: the stored
    ``notes_id`` column, None for none)."""
    ids = np.array([-1 if note_ids[i] is None else note_ids[i] for i in draft.note_rows])
    notes = ids.astype(float)[draft.note_codes]
    at = BLOCK_FIELDS.index("notes")
    runs, parts = list(draft.runs), list(draft.parts)
    runs[at] = _runs(notes, draft.n)
    parts[at] = notes[: runs[at]]
    fields = {"n": draft.n, "fields": BLOCK_FIELDS, "runs": runs, "text": draft.text}
    header = json.dumps(fields).encode()
    body = np.concatenate(parts).astype("<f8", copy=False).tobytes()
    return len(header).to_bytes(_HEADER, "little") + header + body


def _runs(a: np.ndarray, k: int) -> int:
    """1 when every value of ``a`` has the same bits (stored once), else ``k``."""
    bits = a.view(np.int64)
    return 1 if k and (bits == bits[0]).all() else k


def encode_block(stored: Mapping[str, Sequence], *, signed_zeros: bool = True) -> bytes:
    """:func:`draft_block` and :func:`finish_block` of a unit's stored columns."""
    return finish_block(draft_block(stored, signed_zeros=signed_zeros), stored["notes_id"])


def signed_zeros(session: Session) -> bool:
    """Whether the session's database keeps -0.0 (SQLite stores it as 0.0)."""
    return session.get_bind().dialect.name != "sqlite"


def store_block(
    session: Session,
    job_id: int,
    unit_id: int,
    stored: Mapping[str, Sequence],
    *,
    draft: BlockDraft | None = None,
) -> None:
    """Write (or replace) the block of the unit's stored columns (``draft``: its
    :func:`draft_block`, made before the transaction)."""
    if draft is None:
        draft = draft_block(stored, signed_zeros=signed_zeros(session))
    data = finish_block(draft, stored["notes_id"])
    c = BLOCKS.c
    session.execute(delete(BLOCKS).where(c.job_id == job_id, c.unit_id == unit_id))
    session.execute(
        insert(BLOCKS).values(job_id=job_id, unit_id=unit_id, n_rows=draft.n, data=data)
    )


def drop_blocks(session: Session, job_id: int) -> None:
    """Delete the job's blocks (its report is stored, or its rows are gone)."""
    session.execute(delete(BLOCKS).where(BLOCKS.c.job_id == job_id))


def block_columns(
    session: Session, job_id: int, n: int
) -> tuple[dict[str, np.ndarray], dict[str, list]] | None:
    """(raw arrays of :data:`BLOCK_FIELDS`, coded field -> its values in
    :func:`~service.db.report_order.collated` order) from the job's blocks, for
    :func:`~service.db.report_order.ordered_columns`; None when the blocks do not
    hold exactly the job's ``n`` rows (some unit's are missing, or of another
    layout): read the rows then."""
    c = BLOCKS.c
    total, count = session.execute(
        select(func.coalesce(func.sum(c.n_rows), 0), func.count()).where(c.job_id == job_id)
    ).one()
    if total != n or count * MIN_ROWS_PER_BLOCK > n:  # not the job's, or the rows are faster
        return None
    raw = {f: np.empty(n) for f in BLOCK_FIELDS}
    values = {f: FirstCodes() for f in CODED}
    at = 0
    for k, data in _stored(session, job_id):
        parsed = _parse(data if isinstance(data, bytes) else bytes(data), k)
        if parsed is None or at + k > n:
            return None  # another layout, or a unit stored between the two reads
        header, body = parsed
        pos = 0
        for f, run in zip(BLOCK_FIELDS, header["runs"], strict=True):
            col = body[pos : pos + run]
            pos += run
            if f in CODED:  # the block's codes -> the job's (first appearance over blocks)
                col = values[f].encode(header["text"][f]).astype(float)[col.astype(np.int64)]
            raw[f][at : at + k] = col
        at += k
    if at != n:
        return None
    distinct: dict[str, list] = {}
    for f in CODED:
        found = list(values[f])
        distinct[f] = collated(session, set(found))
        at_rank = {v: i for i, v in enumerate(distinct[f])}
        rank = np.array([at_rank[v] for v in found], dtype=float)
        raw[f] = rank[raw[f].astype(np.int64)]
    return raw, distinct


def _stored(session: Session, job_id: int) -> Iterator[tuple[int, bytes]]:
    """The job's (n_rows, data), a few blocks fetched at a time; on PostgreSQL in
    binary (the text protocol's hex doubles the bytes and costs about 0.3 s for the
    150 MB of 625,050 cells)."""
    c = BLOCKS.c
    pg = psycopg_conn(session)
    if pg is None:
        q = select(c.n_rows, c.data).where(c.job_id == job_id)
        yield from session.execute(q.execution_options(yield_per=_PER_READ)).tuples()
        return
    statement = _SELECT
    with (
        driver_errors(session.connection(), statement),
        pg.cursor(f"svrobs_result_blocks_{next(_CURSORS)}", binary=True) as cur,
    ):
        cur.itersize = _PER_READ
        cur.execute(statement, (job_id,))
        yield from cur


def _parse(data: bytes, k: int) -> tuple[dict, np.ndarray] | None:
    """(header, float64 body) of a block of ``k`` rows of today's fields, else None."""
    size = int.from_bytes(data[:_HEADER], "little")
    header = json.loads(data[_HEADER : _HEADER + size])
    runs = header.get("runs", [])
    if (
        header.get("n") != k
        or header.get("fields") != list(BLOCK_FIELDS)
        or any(r not in (1, k) for r in runs)
    ):
        return None
    body = np.frombuffer(data, dtype="<f8", offset=_HEADER + size)
    return (header, body) if body.size == sum(runs) else None
