"""A unit's report columns stored as one block (``service.db.result_blocks``).

Oracle: the row read of the same job (``load_records``, every record decoded row by
row, and ``load_columns`` with the blocks gone): the block read gives the same
columns bit for bit, on SQLite and PostgreSQL, whatever the values (NaN, infinities
stored as NULL, signed zeros, booleans, missing texts, notes, names the database
orders by its collation) and whatever order the units were stored in."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from sqlalchemy import delete, func, select

from service.db import reports
from service.db.models import Job, ResultBlock, WorkUnit
from service.db.reports import load_columns, store_report
from service.db.result_blocks import BLOCK_FIELDS, _parse, block_columns, encode_block
from service.db.results_store import load_records
from svrobs_core.report import Columns
from tests.service.svc_fakes import fake_records
from tests.service.svc_helpers import SMALL_SPEC
from tests.service.test_service_reads import _finished_fake_job, _same_columns

API = "/api/v1"


def _odd_records(spec: dict, payload: dict) -> list[dict]:
    """fake_records with the values a store changes or keeps: -0.0, infinities (stored
    as NULL), NaN, booleans with None, a missing bounds_method, two notes."""
    out = fake_records(spec, payload)
    for i, r in enumerate(out):
        r["eps_A"] = -0.0 if i % 3 == 0 else 0.0
        r["J_exact"] = math.inf if i % 4 == 0 else (-math.inf if i % 4 == 1 else 1e-300 * i)
        r["coverage_A"] = float("nan") if i % 2 else 0.5
        r["certified"] = None if i % 3 == 2 else bool(i % 2)
        r["bounds_method"] = None if i % 5 == 0 else "dean"
        r["sls_status"] = "optimal" if i % 2 else None
        r["notes"] = ["two", None, "one; with 'quotes'"][i % 3]
    return out


def _job(client, session, make_account, spec=SMALL_SPEC) -> tuple[int, list[dict]]:
    return _finished_fake_job(client, session, make_account, spec, make=_odd_records)


def _blocks(session, jid) -> int:
    return session.scalar(select(func.count()).where(ResultBlock.job_id == jid))


def _no_other_read(monkeypatch):
    from service.db import reports as r

    monkeypatch.setattr(r, "_chunks", lambda *a, **k: pytest.fail("the row read was used"))
    monkeypatch.setattr(r, "copy_columns", lambda *a, **k: pytest.fail("the COPY was used"))


def _row_read(session, jid) -> Columns:
    """load_columns with the blocks gone: the COPY (PostgreSQL) or the rows."""
    session.execute(delete(ResultBlock).where(ResultBlock.job_id == jid))
    return load_columns(session, jid, matrices=False)


def test_the_block_read_equals_the_row_read_bit_for_bit(client, session, make_account, monkeypatch):
    from svrobs_core.systems import resolve_system

    paper = resolve_system("paper-stable")
    names = ["Zeta 'q' \\ ü", "alpha", "Émile;--", "Alpha"]
    systems = [{"name": n, "A": paper.A.tolist(), "B": paper.B.tolist()} for n in names]
    jid, records = _job(client, session, make_account, {**SMALL_SPEC, "systems": systems})
    n_units = session.scalar(select(Job.progress_total).where(Job.id == jid))
    assert _blocks(session, jid) == n_units > 1
    with monkeypatch.context() as m:
        _no_other_read(m)
        cols = load_columns(session, jid, matrices=False)
    eps = cols.data["eps_A"]
    # the row read's -0.0: SQLite keeps none (it stores an integral REAL as an integer)
    assert (np.signbit(eps) & (eps == 0)).any() == (session.bind.dialect.name != "sqlite")
    assert np.isnan(cols.data["J_exact"]).any()  # the infinities, stored as NULL
    _same_columns(cols, Columns.from_records(records, matrices=False))
    rows = _row_read(session, jid)
    _same_columns(cols, rows)
    for f, a in cols.data.items():  # bit for bit: -0.0 is not 0.0, NaN's bits alike
        if a.dtype != object:
            assert a.view(np.int64).tolist() == rows.data[f].view(np.int64).tolist(), f


def test_a_unit_stored_again_replaces_its_block(client, session, make_account):
    from service.db import jobs, units

    jid, _ = _job(client, session, make_account)
    uid = jobs.unit_ids_of_job(session, jid, pending_only=False)[0]
    before = _blocks(session, jid)
    spec, payload = session.get(Job, jid).spec, session.get(WorkUnit, uid).payload
    units.complete_unit(session, uid, _odd_records(spec, payload))
    session.commit()
    assert _blocks(session, jid) == before
    assert block_columns(session, jid, len(load_records(session, jid))) is not None


def test_missing_or_foreign_blocks_send_the_read_to_the_rows(client, session, make_account):
    """A unit without a block (stored before blocks existed) or a block of another
    field list: the blocks do not make up the job, and the rows are read."""
    jid, records = _job(client, session, make_account)
    n = len(records)
    first = session.scalars(select(ResultBlock).where(ResultBlock.job_id == jid)).first()
    assert first is not None
    data = first.data
    session.delete(first)
    session.flush()
    assert block_columns(session, jid, n) is None
    _same_columns(
        load_columns(session, jid, matrices=False), Columns.from_records(records, matrices=False)
    )
    size = int.from_bytes(data[:4], "little")
    foreign = data[4 : 4 + size].replace(b'"rep"', b'"rap"')
    session.add(
        ResultBlock(
            job_id=jid,
            unit_id=first.unit_id,
            n_rows=first.n_rows,
            data=len(foreign).to_bytes(4, "little") + foreign + data[4 + size :],
        )
    )
    session.flush()
    assert block_columns(session, jid, n) is None
    assert block_columns(session, jid, n + 1) is None  # rows stored after the count


def test_blocks_go_with_the_stored_report_the_pruned_rows_and_the_job(
    client, session, make_account
):
    from service.db import retention
    from service.db.job_delete import delete_job

    jid, records = _job(client, session, make_account)
    assert _blocks(session, jid) > 0
    store_report(session, jid, "<html></html>", len(records), 1)
    assert _blocks(session, jid) == 0
    jid, _ = _job(client, session, make_account)
    retention.prune_job(session, jid)
    assert _blocks(session, jid) == 0
    jid, _ = _job(client, session, make_account)
    counts = delete_job(session, session.get(Job, jid))
    assert counts["result_blocks"] > 0 and _blocks(session, jid) == 0


_column = st.one_of(
    st.lists(st.sampled_from([0.0, -0.0, 1.5, math.nan, None]), min_size=1, max_size=9),
    st.lists(st.floats(allow_nan=True, allow_infinity=False), min_size=1, max_size=9),
)


@settings(max_examples=150, deadline=None)
@given(data=st.data())
def test_a_block_holds_every_column_as_given(data):
    """encode_block -> the block's columns: each value's bits (a column of one repeated
    value stored once), None as NaN, texts as codes into the block's list of values;
    SQLite's -0.0 stored as 0.0."""
    k = data.draw(st.integers(1, 9))
    stored: dict[str, list] = {}
    for f in BLOCK_FIELDS:
        if f in ("system", "estimator", "bounds_method", "sls_status"):
            pool = st.sampled_from(["a", "b", "É", None])
            stored[f] = data.draw(st.lists(pool, min_size=k, max_size=k))
        elif f == "notes":
            ids = st.lists(st.sampled_from([None, 1, 7]), min_size=k, max_size=k)
            stored["notes_id"] = data.draw(ids)
        else:
            col = data.draw(_column)
            stored[f] = (col * k)[:k]
    signed = data.draw(st.booleans())
    header, body = _parse(encode_block(stored, signed_zeros=signed), k)
    pos = 0
    for f, run in zip(BLOCK_FIELDS, header["runs"], strict=True):
        got = np.broadcast_to(body[pos : pos + run], (k,))
        pos += run
        if f in header["text"]:
            assert [header["text"][f][int(c)] for c in got] == stored[f], f
            continue
        if f == "notes":
            want = np.array([-1 if v is None else v for v in stored["notes_id"]], dtype=float)
        else:
            want = np.array([math.nan if v is None else v for v in stored[f]], dtype=float)
            want = want if signed else want + 0.0
        assert want.view(np.int64).tolist() == np.ascontiguousarray(got).view(np.int64).tolist(), f
    assert pos == body.size


def test_a_first_report_reads_the_blocks_not_the_rows(client, session, make_account, monkeypatch):
    """The page of a finished job built from its blocks is the one built from its
    records, and storing it drops the blocks."""
    from svrobs_lab.report_html import job_report_html

    acc_job, records = _job(client, session, make_account)
    monkeypatch.setattr(reports, "MATRIX_CELLS_LIMIT", 0)  # as for a job of many cells
    with monkeypatch.context() as m:
        _no_other_read(m)
        cols = load_columns(session, acc_job)
    spec = session.get(Job, acc_job).spec
    page = job_report_html(spec, cols, {"job_id": acc_job}, name="b")
    oracle = job_report_html(
        spec, Columns.from_records(records, matrices=False), {"job_id": acc_job}, name="b"
    )
    assert page == oracle


def test_the_block_read_checks_the_blocks_against_the_units_count_not_the_rows(
    client, session, make_account
):
    """Counting a large job's rows reads every row's index entry: the blocks are
    checked against the cells its done units counted instead."""
    from sqlalchemy import event

    jid, records = _job(client, session, make_account)
    seen: list[str] = []
    conn = session.connection()

    def record(conn, cursor, statement, *args):
        seen.append(statement.lower())

    event.listen(conn, "before_cursor_execute", record)
    try:
        cols = load_columns(session, jid, matrices=False)
    finally:
        event.remove(conn, "before_cursor_execute", record)
    _same_columns(cols, Columns.from_records(records, matrices=False))
    assert any("result_blocks" in q for q in seen)
    assert not [q for q in seen if "count(" in q and "from results" in q]


def test_a_driver_error_in_the_block_read_is_reported_as_sqlalchemy_reports_it(
    client, session, make_account, monkeypatch
):
    """PostgreSQL's blocks are fetched by psycopg in binary: its error comes out as
    SQLAlchemy's DBAPIError, as the row read's would (the API maps those to 503)."""
    if session.get_bind().dialect.name != "postgresql":
        pytest.skip("the binary fetch is PostgreSQL's")
    from sqlalchemy.exc import ProgrammingError

    from service.db import result_blocks

    jid, records = _job(client, session, make_account)
    monkeypatch.setattr(result_blocks, "_SELECT", "SELECT n_rows, data FROM no_such_table")
    with pytest.raises(ProgrammingError, match="no_such_table"):
        block_columns(session, jid, len(records))


def test_a_core_units_block_is_made_before_its_write_and_equals_its_rows(
    client, session, make_account, monkeypatch
):
    """A unit computed by the core (a UnitResult) has its block drafted from its
    columns before the write transaction, the notes' ids filled in after: the block
    read equals the rows' (notes included), and the draft is the one store_block
    gets."""
    from service.db import jobs, result_blocks, units
    from svrobs_core.parsing import parse_spec
    from svrobs_core.runner import run_unit_result
    from tests.service.test_service_reads import REAL_SPEC

    drafts = []
    real = result_blocks.store_block

    def spy(*args, draft=None, **kw):
        drafts.append(draft)
        return real(*args, draft=draft, **kw)

    monkeypatch.setattr(units, "store_block", spy)
    acc = make_account()
    jid = client.post(f"{API}/jobs", json=REAL_SPEC, headers=acc.headers).json()["id"]
    for uid in jobs.unit_ids_of_job(session, jid, pending_only=False):  # as a worker does
        spec, payload = units.start_unit(session, uid, "test", 60, max_attempts=0)
        units.complete_unit(session, uid, run_unit_result(parse_spec(spec), payload))
        session.commit()
    assert drafts and all(d is not None for d in drafts)
    records = load_records(session, jid)
    assert any(r["notes"] for r in records)
    with monkeypatch.context() as m:
        _no_other_read(m)
        cols = load_columns(session, jid, matrices=False)
    _same_columns(cols, Columns.from_records(records, matrices=False))


def test_text_fields_of_dict_records_are_stored_as_text(client, session, make_account):
    """A dict record whose bounds_method, sls_status or notes is not a string (5):
    stored as its text on both databases, so the row read and the block read agree
    (SQLite turned 5 into '5' in the row while the block kept 5, and the block read
    failed comparing 5 with text)."""

    def numbered(spec, payload):
        out = _odd_records(spec, payload)
        for i, r in enumerate(out):
            r["bounds_method"] = 5 if i % 2 else "dean"
            r["sls_status"] = 7 if i % 3 == 0 else None
            r["notes"] = [1, "two"] if i % 4 == 0 else None
        return out

    jid, records = _finished_fake_job(client, session, make_account, make=numbered)
    assert {r["bounds_method"] for r in records} == {"5", "dean"}
    assert "1; two" in {r["notes"] for r in records}
    cols = load_columns(session, jid, matrices=False)
    _same_columns(cols, Columns.from_records(records, matrices=False))


def test_blocks_of_few_rows_each_send_the_read_to_the_rows(
    client, session, make_account, monkeypatch
):
    """Blocks that hold fewer than MIN_ROWS_PER_BLOCK rows on average are slower to
    read than the rows: the rows (or the COPY) are read, with the same columns."""
    from service.db import result_blocks

    jid, records = _job(client, session, make_account)
    n_blocks = _blocks(session, jid)
    assert block_columns(session, jid, len(records)) is not None
    monkeypatch.setattr(result_blocks, "MIN_ROWS_PER_BLOCK", len(records) // n_blocks + 1)
    assert block_columns(session, jid, len(records)) is None
    cols = load_columns(session, jid, matrices=False)
    _same_columns(cols, Columns.from_records(records, matrices=False))


def test_two_block_reads_may_overlap_in_one_transaction(client, session, make_account):
    """PostgreSQL's binary fetch names a server-side cursor per read: a read that
    starts while another's cursor is open (a generator not yet exhausted) works."""
    from service.db import result_blocks

    jid, records = _job(client, session, make_account)
    first = result_blocks._stored(session, jid)
    next(first)  # its cursor is open
    second = list(result_blocks._stored(session, jid))
    assert len(second) == _blocks(session, jid)
    assert 1 + sum(1 for _ in first) == len(second)
