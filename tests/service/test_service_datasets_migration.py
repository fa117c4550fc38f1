"""Migration 0008 on both dialects: jobs made before it keep every row and column
through the upgrade (on SQLite the jobs table is rebuilt to add the foreign key) and
the downgrade; the foreign key refuses a job on a missing dataset."""

from __future__ import annotations

from datetime import UTC, datetime

import pytest
import sqlalchemy as sa

from service.db.migrate import downgrade, upgrade
from service.db.session import create_db_engine
from tests.service.test_service_storage_migration import url  # noqa: F401 - the fixture

NOW = datetime(2026, 12, 1, tzinfo=UTC)


def _jobs(conn) -> list[tuple]:
    cols = "id, team_id, name, status, n_cells, cells_done, spec, tags"
    return conn.execute(sa.text(f"SELECT {cols} FROM jobs ORDER BY id")).all()


def test_0008_keeps_the_jobs_and_goes_back(url):  # noqa: F811 - the fixture
    upgrade(url, "0007")
    engine = create_db_engine(url)
    with engine.begin() as c:
        c.execute(
            sa.text("INSERT INTO teams (id, name, created_at) VALUES (1, 'lab', :t)"), {"t": NOW}
        )
        for i in (1, 2):
            c.execute(
                sa.text(
                    "INSERT INTO jobs (id, team_id, name, tags, spec, status, progress_done, "
                    "progress_total, n_cells, cells_done, provenance, timings, created_at) "
                    "VALUES (:i, 1, :n, '[]', '{\"seed\": 1}', 'succeeded', 1, 1, 8, 8, '{}', '{}', :t)"
                ),
                {"i": i, "n": f"job {i}", "t": NOW},
            )
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
    downgrade(url, "0007")
    engine = create_db_engine(url)
    with engine.begin() as c:
        assert _jobs(c) == before
        tables = set(sa.inspect(c).get_table_names())
        assert "datasets" not in tables and "dataset_chunks" not in tables
        assert "dataset_id" not in {col["name"] for col in sa.inspect(c).get_columns("jobs")}
    engine.dispose()
