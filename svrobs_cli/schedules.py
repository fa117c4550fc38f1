"""The ``svrobs schedules`` and ``svrobs presets`` commands, through :mod:`svrobs_client`.

svrobs schedules list|show ID|runs ID [--json]
svrobs schedules create NAME --cron '0 2 * * *' (--spec FILE | --from-job ID)
                        [--timezone Europe/Berlin] [--tag T]... [--disabled]
                        [--seed-policy fixed|due-time]
svrobs schedules enable|disable|delete ID
svrobs presets list [--json]
svrobs presets run [--scale full|reduced] [--experiment E1]... [--wait]
"""

from __future__ import annotations

from pathlib import Path

import typer

from svrobs_cli.errors import CliError
from svrobs_cli.rest import client, finish, load_spec, print_json, print_table
from svrobs_client import SEED_POLICIES, Job, Schedule


def _line(s: Schedule) -> str:
    state = f"enabled, next run {s.raw.get('next_run_at')}" if s.enabled else "disabled"
    return f"schedule {s.id} {s.name!r} {s.cron!r} {s.timezone} ({state})"


def list_schedules(as_json: bool = typer.Option(False, "--json", help="print JSON")) -> None:
    """The team's schedules."""
    with client() as c:
        items = c.schedules()
    if as_json:
        return print_json([s.raw for s in items])
    print_table(
        ["id", "name", "cron", "timezone", "enabled", "next run", "tags", "seed policy"],
        [
            [
                *(s.id, s.name, s.cron, s.timezone, s.enabled, s.raw.get("next_run_at")),
                *(s.tags, s.seed_policy),
            ]
            for s in items
        ],
    )


def show(
    schedule: int = typer.Argument(...),
    as_json: bool = typer.Option(False, "--json", help="print JSON"),
) -> None:
    """One schedule, with its spec template."""
    with client() as c:
        s = c.schedule(schedule)
    if as_json:
        return print_json(s.raw)
    typer.echo(_line(s))
    typer.echo(f"  tags: {s.tags}\n  seed_policy: {s.seed_policy}")
    typer.echo(f"  spec_template: {s.spec_template}")


def create(
    name: str = typer.Argument(...),
    cron: str = typer.Option(..., help="5 fields (minute hour day month weekday) or @daily etc."),
    spec: Path | None = typer.Option(None, help="the spec template (a JSON or YAML file)"),
    from_job: int | None = typer.Option(
        None, help="use this job's spec as the template (and its tags, without --tag)"
    ),
    timezone: str = typer.Option("UTC", help="an IANA time zone, e.g. Europe/Berlin"),
    tag: list[str] = typer.Option(
        [], "--tag", help="a tag of every job (repeatable; default: --from-job's tags)"
    ),
    disabled: bool = typer.Option(False, "--disabled", help="create it disabled"),
    seed_policy: str = typer.Option(
        "fixed", help="fixed (the template's seed) or due-time (fresh repetitions each run)"
    ),
) -> None:
    """Create a schedule: the spec template runs at every due time of the cron. Made
    from a job, it runs that job's spec with that job's tags unless --tag is given."""
    if (spec is None) == (from_job is None):
        raise CliError("give exactly one of --spec FILE and --from-job ID")
    if seed_policy not in SEED_POLICIES:
        raise CliError(f"--seed-policy must be fixed or due-time, not {seed_policy!r}")
    with client() as c:
        template: dict | Job
        if spec is not None:
            template = load_spec(spec)
        else:
            assert from_job is not None  # exactly one of the two, checked above
            template = c.job(from_job)
            tag = tag or list(template.tags)
        s = c.create_schedule(
            name,
            cron,
            template,
            timezone=timezone,
            tags=tag,
            enabled=not disabled,
            seed_policy=seed_policy,
        )
    typer.echo(_line(s) + " created")


def enable(schedule: int = typer.Argument(...)) -> None:
    """Enable a schedule."""
    with client() as c:
        typer.echo(_line(c.enable_schedule(schedule)))


def disable(schedule: int = typer.Argument(...)) -> None:
    """Disable a schedule (no new jobs; its jobs stay)."""
    with client() as c:
        typer.echo(_line(c.disable_schedule(schedule)))


def delete(schedule: int = typer.Argument(...)) -> None:
    """Delete a schedule (its jobs stay)."""
    with client() as c:
        c.delete_schedule(schedule)
    typer.echo(f"schedule {schedule} deleted")


def runs(
    schedule: int = typer.Argument(...),
    as_json: bool = typer.Option(False, "--json", help="print JSON"),
) -> None:
    """The due times of a schedule already turned into jobs, newest first."""
    with client() as c:
        items = c.schedule_runs(schedule)
    if as_json:
        return print_json([r.raw for r in items])
    print_table(
        ["due at", "job", "error"], [[r.raw.get("due_at"), r.job_id, r.error] for r in items]
    )


def list_presets(as_json: bool = typer.Option(False, "--json", help="print JSON")) -> None:
    """The system presets a spec may name, with their matrices' sizes and noise levels."""
    with client() as c:
        items = c.presets()
    if as_json:
        return print_json(items)
    print_table(
        ["name", "n", "m", "p", "sigma_u", "sigma_v"],
        [
            [
                p["name"],
                len(p["A"]),
                len(p["B"][0]),
                len(p["C"]),
                p.get("sigma_u"),
                p.get("sigma_v"),
            ]
            for p in items
        ],
    )


def run_preset(
    scale: str = typer.Option("full", help="full or reduced"),
    experiment: list[str] = typer.Option(
        [], "--experiment", help="E1-E4, A1, A2 (repeatable; default all)"
    ),
    wait: bool = typer.Option(False, "--wait", help="show progress until every job finishes"),
    idempotency_key: str | None = typer.Option(None, help="a retry returns the same jobs"),
) -> None:
    """Queue the paper's Section 6 (E1-E4 and the audits A1, A2), one job each."""
    with client() as c:
        jobs = c.run_paper_preset(
            scale=scale, experiments=experiment or None, idempotency_key=idempotency_key
        )
        for j in jobs:
            typer.echo(f"job {j.id} {j.status} {j.name} ({j.n_cells} cells)")
        if wait:
            for j in jobs:
                finish(c, j)
