"""Migrations 0006 (compact results) and 0007 (radius matrices as their scalars) on
both dialects: rows written in the JSON
format (matrices and seed_key as JSON text, notes inline) by the 0002 schema are
upgraded and read back as the core's records, bit for bit; the downgrade gives
back the 0002 rows with the same values."""

from __future__ import annotations

import json
import math
import os
from datetime import UTC, datetime

import numpy as np
import pytest
import sqlalchemy as sa

from service.db.migrate import downgrade, upgrade
from service.db.results_store import gamma_key, load_records
from service.db.session import create_db_engine, dispose_all
from svrobs_core.parsing import parse_spec
from svrobs_core.planning import plan_units
from svrobs_core.records import MATRIX_FIELDS, RECORD_FIELDS, json_value
from svrobs_core.runner import run_unit_result
from tests.service.conftest import PG_ENV, _pg_private_db

CUSTOM = {  # n=2, m=1, p=1: every matrix has its own shape
    "name": "custom",
    "A": [[0.9, 0.2], [0.0, 0.7]],
    "B": [[1.0], [0.5]],
    "C": [[1.0, 0.0]],
}
SPEC = {
    "systems": ["paper-unstable", CUSTOM],
    "sigma_w": [1.0, 0.1],
    "N": [20, 40],
    "gamma": [0.05, 0.1],
    "estimators": ["ols", "svr"],
    "reps": 2,
    "stages": ["estimate", "bounds", "gain", "cost", "sls"],
    "mc_reps": 1,
    "mc_runs": 20,
    "horizon": 30,
}


@pytest.fixture(params=["sqlite", "postgresql"])
def url(request, tmp_path):
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'm.db'}"
        return
    if not os.environ.get(PG_ENV):
        pytest.skip(f"{PG_ENV} not set")
    url, cleanup = _pg_private_db(os.environ[PG_ENV])
    if cleanup is None:
        pytest.skip("no CREATEDB right for a private database")
    yield url
    dispose_all()
    admin, name = cleanup
    with admin.connect() as c:
        c.execute(sa.text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
    admin.dispose()


def _records() -> list[dict]:
    spec = parse_spec(SPEC)
    out = [r for u in plan_units(spec) for r in run_unit_result(spec, u).records()]
    out = [{k: json_value(v) for k, v in r.items()} for r in out]
    out[0]["seed_key"] = [7, 7, 7, 7]  # not the one the spec gives: stored as is
    out[1]["A_hat"][0][1] = None  # a non-finite entry (null in the record)
    out[2]["L"] = None  # an absent matrix
    return out


def _insert_job(conn, job_id: int, n_cells: int) -> None:
    now = datetime.now(UTC)
    if job_id == 1:
        conn.execute(
            sa.text("INSERT INTO teams (id, name, created_at) VALUES (1, 't', :now)"), {"now": now}
        )
    jobs = sa.table(
        "jobs",
        *[sa.column(c) for c in ("id", "team_id", "status", "created_at")],
        *[sa.column(c) for c in ("progress_done", "progress_total", "n_cells")],
        *[sa.column(c, sa.JSON()) for c in ("spec", "tags", "provenance", "timings")],
    )
    conn.execute(
        jobs.insert(),
        {
            "id": job_id,
            "team_id": 1,
            "status": "succeeded",
            "created_at": now,
            "progress_done": 0,
            "progress_total": 0,
            "n_cells": n_cells,
            "spec": parse_spec(SPEC).to_dict(),
            "tags": [],
            "provenance": {},
            "timings": {},
        },
    )


def _write_json_rows(conn, records: list[dict]) -> int:
    """Insert a team, a job and its records exactly as the JSON-format writer stored them."""
    _insert_job(conn, 1, len(records))
    text_json = ("seed_key",) + MATRIX_FIELDS
    fields = [f for f in RECORD_FIELDS if f not in text_json]
    results = sa.table(
        "results",
        *[sa.column(c) for c in ["job_id", "gamma_key", *fields]],
        *[sa.column(c, sa.JSON()) for c in text_json],
    )
    rows = [{"job_id": 1, "gamma_key": gamma_key(r["gamma"]), **r} for r in records]
    conn.execute(results.insert(), rows)
    return len(rows)


def _key(r):
    return (r["system"], r["sigma_w"], r["N"], r["estimator"], r["gamma"], r["rep"])


def _bits(rec: dict) -> dict:
    """A record with every float as its 64-bit pattern (so -0.0 != 0.0, NaN never)."""

    def b(v):
        if isinstance(v, float):
            return np.float64(v).view(np.int64).item()
        if isinstance(v, list):
            return [b(x) for x in v]
        return v

    return {k: b(v) for k, v in rec.items()}


def test_json_rows_upgrade_to_the_same_records_and_back(url):
    """Job 1: written in the JSON format (0002), upgraded. Job 2: stored by the worker's write
    path after the upgrade (K once per (system, sigma_w) in result_constants). Both
    read back as the core's records, and both downgrade to them."""
    from sqlalchemy.orm import Session

    from service.db.results_store import upsert_results

    records = _records()
    upgrade(url, "0005")
    engine = create_db_engine(url)
    with engine.begin() as conn:
        n = _write_json_rows(conn, records)
    upgrade(url)  # 0005: JSON -> float64 bytes, notes dictionary, derived seed_key
    spec = parse_spec(SPEC)
    with engine.begin() as conn:
        _insert_job(conn, 2, n)
    with Session(engine) as s, s.begin():
        for u in plan_units(spec):
            upsert_results(s, 2, run_unit_result(spec, u))
    with engine.connect() as conn:
        shared = conn.execute(sa.text("SELECT count(*) FROM result_constants")).scalar()
        assert shared == 4  # K of each (system, sigma_w)
        empty = 'SELECT count(*) FROM results WHERE job_id = 2 AND length("K") = 0'
        assert conn.execute(sa.text(empty)).scalar() == n
        # the paper's bounds: each radius matrix is its row's scalar radius, stored as
        # zero bytes (0007) whether written so (job 2) or converted (job 1)
        for job in (1, 2):
            for m, r in (("radii_A", "r_A"), ("radii_B", "r_B")):
                scalar = (
                    f'SELECT count(*) FROM results WHERE job_id = {job} AND length("{m}") = 0 '
                    f'AND "{r}" IS NOT NULL'
                )
                assert conn.execute(sa.text(scalar)).scalar() == n, (job, m)
    want2 = {
        _key(r): {k: json_value(v) for k, v in r.items()}
        for u in plan_units(spec)
        for r in run_unit_result(spec, u).records()
    }
    with Session(engine) as s:
        back2 = load_records(s, 2)
    assert len(back2) == n and all(_bits(r) == _bits(want2[_key(r)]) for r in back2)
    with engine.connect() as conn:
        assert conn.execute(sa.text("SELECT count(*) FROM results")).scalar() == 2 * n
        derived = conn.execute(
            sa.text("SELECT count(*) FROM results WHERE seed_key IS NULL")
        ).scalar()
        assert derived == 2 * n - 1  # only the record whose seed_key the spec does not give
        assert conn.execute(sa.text("SELECT count(*) FROM result_notes")).scalar() < n / 4
    with Session(engine) as s:
        back = {_key(r): r for r in load_records(s, 1)}
    assert len(back) == n
    for rec in records:
        assert _bits(back[_key(rec)]) == _bits(rec)
    assert back[_key(records[1])]["A_hat"][0][1] is None
    assert back[_key(records[2])]["L"] is None
    downgrade(url, "0005")
    with engine.connect() as conn:
        text = [sa.cast(sa.column(c), sa.Text).label(c) for c in ("seed_key",) + MATRIX_FIELDS]
        others = [sa.column(c) for c in RECORD_FIELDS if c not in ("seed_key",) + MATRIX_FIELDS]
        rows = conn.execute(
            sa.select(sa.column("job_id"), *others, *text).select_from(sa.table("results"))
        ).mappings()
        old = {}
        for r in rows:
            rec = {
                k: (json.loads(v) if k in ("seed_key",) + MATRIX_FIELDS and v else v)
                for k, v in r.items()
            }
            rec = {
                k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in rec.items()
            }
            old[(rec.pop("job_id"),) + _key(rec)] = rec
    engine.dispose()
    assert len(old) == 2 * n
    for rec in records:
        assert _bits(old[(1,) + _key(rec)]) == _bits(rec)
    for key, rec in want2.items():
        assert _bits(old[(2,) + key]) == _bits(rec)


def test_downgrade_to_the_first_format_keeps_every_row(url):
    """Down to 0002 (through 0005-0003, whose SQLite batch mode rebuilds ``jobs`` by
    copy, drop and rename): no row of ``results`` is lost. With SQLite's foreign keys
    on during the migration, dropping the old ``jobs`` cascade-deleted them all."""
    from sqlalchemy.orm import Session

    from service.db.results_store import upsert_results

    spec = parse_spec(SPEC)
    upgrade(url)
    engine = create_db_engine(url)
    with engine.begin() as conn:
        _insert_job(conn, 1, spec.n_cells)
    with Session(engine) as s, s.begin():
        for u in plan_units(spec):
            upsert_results(s, 1, run_unit_result(spec, u))
    engine.dispose()
    downgrade(url, "0002")
    engine = create_db_engine(url)
    with engine.connect() as conn:
        count = "SELECT count(*) FROM results WHERE job_id = 1"
        assert conn.execute(sa.text(count)).scalar() == spec.n_cells
        assert conn.execute(sa.text("SELECT count(*) FROM jobs")).scalar() == 1
    engine.dispose()
