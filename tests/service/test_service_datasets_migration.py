"""Migration 0008 on both dialects: jobs made before it keep every row and column
through the upgrade (on SQLite the jobs table is rebuilt to add the foreign key) and
the downgrade; the foreign key refuses a job on a missing dataset; the downgrade
refuses while a job runs on a dataset."""

from __future__ import annotations

from datetime import UTC, datetime

import pytest
import sqlalchemy as sa

from service.db.migrate import current_revision, downgrade, upgrade
from service.db.session import create_db_engine
from tests.service.test_service_storage_migration import url  # noqa: F401 - the fixture

NOW = datetime(2026, 12, 1, tzinfo=UTC)


def _jobs(conn) -> list[tuple]:
    cols = "id, team_id, name, status, n_cells, cells_done, spec, tags"
    return conn.execute(sa.text(f"SELECT {cols} FROM jobs ORDER BY id")).all()


def _team_and_two_jobs(conn) -> None:
    conn.execute(
        sa.text("INSERT INTO teams (id, name, created_at) VALUES (1, 'lab', :t)"), {"t": NOW}
    )
    for i in (1, 2):
        conn.execute(
            sa.text(
                "INSERT INTO jobs (id, team_id, name, tags, spec, status, progress_done, "
                "progress_total, n_cells, cells_done, provenance, timings, created_at) "
                "VALUES (:i, 1, :n, '[]', '{\"seed\": 1}', 'succeeded', 1, 1, 8, 8, '{}', '{}', :t)"
            ),
            {"i": i, "n": f"job {i}", "t": NOW},
        )


def test_0008_keeps_the_jobs_and_goes_back(url):  # noqa: F811 - the fixture
    upgrade(url, "0007")
    engine = create_db_engine(url)
    with engine.begin() as c:
        _team_and_two_jobs(c)
        count = c.execute(sa.text("SELECT count(*) FROM jobs")).scalar()
        before = _jobs(c)
    assert count == 2
    upgrade(url)
    with engine.begin() as c:
        assert _jobs(c) == before
        assert c.execute(sa.text("SELECT dataset_id FROM jobs")).scalars().all() == [None, None]
        c.execute(
            sa.text(
                "INSERT INTO datasets (id, team_id, name, format, sha256, arrays_sha256, "
                "size_bytes, n, m, rollouts, samples, t_min, t_max, lengths, state_names, "
                "input_names, stats, created_at) VALUES (5, 1, 'd', 'csv', 'a', 'b', 3, 1, 0, 1, "
                "2, 2, 2, '[2]', "
                "'[\"x1\"]', '[]', '{}', :t)"
            ),
            {"t": NOW},
        )
        c.execute(sa.text("UPDATE jobs SET dataset_id = 5 WHERE id = 2"))
    with pytest.raises(sa.exc.IntegrityError), engine.begin() as c:
        c.execute(sa.text("UPDATE jobs SET dataset_id = 6 WHERE id = 1"))
    with pytest.raises(sa.exc.IntegrityError), engine.begin() as c:
        c.execute(sa.text("DELETE FROM datasets WHERE id = 5"))
    engine.dispose()
    head = current_revision(url)
    for target in ("0007", "base", "-9"):  # -9 from 0016 is 0007
        with pytest.raises(RuntimeError, match="1 job.s. run on uploaded datasets"):
            downgrade(url, target)  # the older schema cannot hold job 2
    # refused before any step: on SQLite each revision commits on its own
    assert current_revision(url) == head
    engine = create_db_engine(url)
    with engine.begin() as c:
        assert {"result_blocks", "sessions", "job_validations"} <= set(
            sa.inspect(c).get_table_names()
        )
        assert c.execute(sa.text("SELECT count(*) FROM datasets")).scalar() == 1
        c.execute(sa.text("DELETE FROM jobs WHERE id = 2"))
    engine.dispose()
    downgrade(url, "0007")
    engine = create_db_engine(url)
    with engine.begin() as c:
        assert _jobs(c) == before[:1]
        tables = set(sa.inspect(c).get_table_names())
        assert "datasets" not in tables and "dataset_chunks" not in tables
        assert "dataset_id" not in {col["name"] for col in sa.inspect(c).get_columns("jobs")}
    engine.dispose()


def test_0016_keeps_every_row_and_never_hands_an_id_out_twice(url):  # noqa: F811
    """On SQLite the tables are rebuilt with AUTOINCREMENT: rows, foreign keys and
    the next ids survive, and the id of the newest job, once deleted, is not reused."""
    upgrade(url, "0015")
    engine = create_db_engine(url)
    with engine.begin() as c:
        _team_and_two_jobs(c)
        before = _jobs(c)
    engine.dispose()
    upgrade(url)
    engine = create_db_engine(url)

    def new_job(c) -> int:
        return c.execute(
            sa.text(
                "INSERT INTO jobs (team_id, name, tags, spec, status, progress_done, "
                "progress_total, n_cells, cells_done, provenance, timings, created_at) "
                "VALUES (1, 'n', '[]', '{}', 'queued', 0, 1, 8, 0, '{}', '{}', :t) RETURNING id"
            ),
            {"t": NOW},
        ).scalar_one()

    with engine.begin() as c:
        assert _jobs(c) == before
        if c.dialect.name == "postgresql":  # the ids above were given, not drawn
            c.execute(sa.text("SELECT setval(pg_get_serial_sequence('jobs', 'id'), 2)"))
        first = new_job(c)
        c.execute(sa.text("DELETE FROM jobs WHERE id = :i"), {"i": first})
        second = new_job(c)
        assert first == 3 and second == 4
        with pytest.raises(sa.exc.IntegrityError), c.begin_nested():
            c.execute(sa.text("UPDATE jobs SET team_id = 7 WHERE id = 1"))
    engine.dispose()
