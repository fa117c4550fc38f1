"""The ``svrobs share`` commands (read-only links to a job), through :mod:`svrobs_client`.

svrobs share create JOB [--days 7]   prints the link (shown only this once)
svrobs share list JOB [--json]
svrobs share revoke ID
"""

from __future__ import annotations

import sys

import typer

from svrobs_cli.errors import CliError, plain_message
from svrobs_cli.rest import client, print_json, print_table
from svrobs_client import ValidationError


def create(
    job: int = typer.Argument(...),
    days: float = typer.Option(7.0, help="the link expires after this many days"),
    label: str | None = typer.Option(None, help="what the link is for (shown in the list)"),
) -> None:
    """Create a read-only link to the job's report and charts (opened without a key);
    its URL is printed only now."""
    with client() as c:
        try:
            share = c.share(job, days=days, label=label)
        except ValidationError as exc:
            raise CliError(plain_message(exc)) from None
    typer.echo(share.url)
    print(
        f"share {share.id} of job {share.job_id}, expires {share.raw.get('expires_at')}",
        file=sys.stderr,
    )


def list_shares(
    job: int = typer.Argument(...),
    as_json: bool = typer.Option(False, "--json", help="print JSON"),
) -> None:
    """The job's share links, newest first (their URLs are not kept)."""
    with client() as c:
        items = c.shares(job)
    if as_json:
        return print_json([s.raw for s in items])
    print_table(
        ["id", "label", "created", "expires", "revoked", "live"],
        [
            [
                s.id,
                s.label,
                s.raw.get("created_at"),
                s.raw.get("expires_at"),
                s.raw.get("revoked_at"),
                s.live,
            ]
            for s in items
        ],
    )


def revoke(share: int = typer.Argument(..., help="a share id (svrobs share list JOB)")) -> None:
    """Revoke a share link: opening it is a 404 from now on."""
    with client() as c:
        c.revoke_share(share)
    typer.echo(f"share {share} revoked")
