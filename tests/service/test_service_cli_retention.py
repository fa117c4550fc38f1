"""``svrobs admin set-retention`` on a real database."""

from __future__ import annotations

from sqlalchemy import select

from service.config import get_settings
from service.db.models import Team
from service.db.session import session_scope
from tests.service.test_service_cli import own_db, run  # noqa: F401 - the CLI tests' fixtures


def test_admin_set_retention(own_db, run):  # noqa: F811
    def days():
        with session_scope(get_settings().DATABASE_URL) as s:
            return s.scalar(select(Team.retention_days).where(Team.name == "lab"))

    assert run("migrate")[0] == 0
    assert run("admin", "create-team", "lab")[0] == 0
    assert days() is None  # off by default
    code, out, err = run("admin", "set-retention", "lab", "--days", "30")
    assert code == 0 and "30 days" in out, err
    assert days() == 30
    assert run("admin", "set-retention", "lab", "--off")[0] == 0
    assert days() is None
    for bad in (("--days", "0"), ("--days", "3", "--off"), ()):
        code, out, err = run("admin", "set-retention", "lab", *bad)
        assert code != 0 and "Traceback" not in err and err.strip(), bad
    code, out, err = run("admin", "set-retention", "nolab", "--days", "3")
    assert code != 0 and "nolab" in err
