"""``svrobs migrate`` and ``svrobs admin ...``: the database directly, no API.

The operations are :mod:`service.db.accounts`; each command runs in one committed
transaction.
"""

from __future__ import annotations

import sys
from typing import Any

import typer

from svrobs_cli.errors import CliError


def migrate(
    url: str | None = typer.Option(None, help="database URL [SVROBS_DATABASE_URL]"),
) -> None:
    """Create or upgrade the database tables (alembic upgrade head)."""
    from service.config import get_settings
    from service.db.migrate import upgrade

    upgrade(url or get_settings().DATABASE_URL)
    typer.echo("database is at the latest revision")


def _admin_call(fn):
    """``fn(session, accounts)`` in one committed transaction; an AdminError is one line."""
    from service.config import get_settings
    from service.db import accounts
    from service.db.migrate import missing_database
    from service.db.session import session_scope
    from svrobs_lab.errors import AdminError

    url = get_settings().DATABASE_URL
    missing = missing_database(url)
    if missing is not None:
        raise CliError(
            f"{missing}: run svrobs admin from the checkout that runs `make run` (its ./var), "
            "or set SVROBS_DATABASE_URL to the service's database"
        )
    try:
        with session_scope(url) as session:
            return fn(session, accounts)
    except AdminError as exc:
        raise CliError(str(exc)) from None


def admin_create_team(name: str) -> None:
    """Create a team."""
    team_id = _admin_call(lambda s, a: a.create_team(s, name).id)
    typer.echo(f"team {name!r} created (id {team_id})")


def admin_create_user(
    team: str = typer.Argument(..., help="team name or id"),
    email: str = typer.Argument(...),
    is_admin: bool = typer.Option(False, "--admin", help="team administrator"),
) -> None:
    """Create a user in a team."""
    t: Any = int(team) if team.isdigit() else team
    user_id = _admin_call(lambda s, a: a.create_user(s, t, email, is_admin=is_admin).id)
    typer.echo(f"user {email} created (id {user_id})")


def admin_create_key(
    user: str = typer.Argument(..., help="user email or id"),
    name: str | None = typer.Option(None, help="a label for the key"),
    expires_days: float | None = typer.Option(None, help="expire after this many days"),
) -> None:
    """Create an API key; the key is printed once and never stored."""
    u: Any = int(user) if user.isdigit() else user

    def make(session, a):
        row, key = a.create_key(session, u, name=name, expires_in_days=expires_days)
        return row.prefix, key

    prefix, key = _admin_call(make)
    typer.echo(key)
    print(f"(key prefix {prefix}; store it now, it is shown only once)", file=sys.stderr)


def admin_revoke_key(
    key: str | None = typer.Argument(None, help="key prefix or full key (digits too)"),
    key_id: int | None = typer.Option(None, "--id", help="the key's id (see list-keys)"),
) -> None:
    """Revoke an API key (it gets 401 from now on): by prefix or full key, or by --id N.

    A key argument is always a prefix (or the whole key), whatever it looks like:
    an id is given only with --id."""
    if (key is None) == (key_id is None):
        raise CliError("give a key prefix or --id N (exactly one)")
    prefix = _admin_call(lambda s, a: a.revoke_key(s, key if key_id is None else key_id).prefix)
    typer.echo(f"key {prefix} revoked")


def admin_list_keys(team: str | None = typer.Argument(None)) -> None:
    """List API keys (prefix, team, user, created, expires, revoked)."""
    t: Any = int(team) if team and team.isdigit() else team

    def rows(session, a):
        return [
            (
                k.id,
                k.prefix,
                k.team_id,
                k.user.email if k.user else "",
                k.created_at,
                k.expires_at,
                k.revoked_at,
            )
            for k in a.list_keys(session, t)
        ]

    for r in _admin_call(rows):
        typer.echo("\t".join("" if v is None else str(v) for v in r))


def admin_set_retention(
    team: str = typer.Argument(..., help="team name or id"),
    days: int | None = typer.Option(None, "--days", help="drop cell rows this many days on"),
    off: bool = typer.Option(False, "--off", help="keep every row (the default)"),
) -> None:
    """Retention of the team's scheduled jobs: keep summaries and the report, drop the
    cell rows K days after a job finished (applied by the beat tick)."""
    from service.db.retention import set_retention

    if off == (days is not None):
        raise CliError("give exactly one of --days K and --off")
    t: Any = int(team) if team.isdigit() else team
    name = _admin_call(lambda s, a: set_retention(s, t, None if off else days).name)
    if off:
        typer.echo(f"team {name!r}: retention off (every cell row is kept)")
    else:
        typer.echo(
            f"team {name!r}: the cell rows of scheduled jobs are dropped {days} days after "
            "they finish (summaries and reports are kept)"
        )
