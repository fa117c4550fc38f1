"""The ``svrobs`` console script: every command is registered here, in one place.

    svrobs migrate                         alembic upgrade head on SVROBS_DATABASE_URL
    svrobs admin create-team|create-user|create-key|revoke-key|list-keys|set-retention
    svrobs submit|status|results|summary|compare|report|cancel|delete
                                           REST commands (svrobs_cli.rest)
    svrobs schedules list|show|create|enable|disable|delete|runs
    svrobs presets list|run                REST commands (svrobs_cli.schedules)
    svrobs share create|list|revoke        share links (svrobs_cli.shares)
    svrobs datasets upload|list|show|delete|download, svrobs model, svrobs validation,
    svrobs systems from-file
                                           measured data (svrobs_cli.datasets)
    svrobs run-local|reproduce             the core in process (svrobs_cli.local)
    svrobs serve                           API + worker + beat (svrobs_cli.serve)

Every error prints one line and exits with status 2, never a traceback
(:class:`~svrobs_cli.errors.SvrobsTyper`).
"""

from __future__ import annotations

from importlib.metadata import version

import typer

from svrobs_cli import admin, datasets, local, rest, schedules, serve, shares
from svrobs_cli.errors import SvrobsTyper

__all__ = ["app"]

app = SvrobsTyper(
    name="svrobs",
    help="SVR-based observer design experiments as a service.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)


def _print_version(asked: bool) -> None:
    if asked:
        typer.echo(f"svrobs {version('svrobs')}")
        raise typer.Exit()


@app.callback()
def _options(
    _version: bool = typer.Option(
        False, "--version", callback=_print_version, is_eager=True, help="print the version"
    ),
) -> None:
    """SVR-based observer design experiments as a service."""


def _group(name: str, help: str) -> SvrobsTyper:
    """A command group ``svrobs <name> ...`` registered on :data:`app`."""
    group = SvrobsTyper(help=help, no_args_is_help=True, pretty_exceptions_enable=False)
    app.add_typer(group, name=name)
    return group


admin_app = _group("admin", "Teams, users and API keys (direct database access).")
schedules_app = _group(
    "schedules", "Cron schedules that turn a spec template into a job at every due time."
)
presets_app = _group("presets", "The system presets, and the paper's Section 6 preset.")
share_app = _group("share", "Read-only links to a job's report and charts, opened without a key.")
datasets_app = _group(
    "datasets", "Datasets of measured rollouts: upload, list, show, delete, download."
)
systems_app = _group("systems", "Custom systems for a spec, read from files.")

COMMANDS = (
    (app, "migrate", admin.migrate),
    (admin_app, "create-team", admin.admin_create_team),
    (admin_app, "create-user", admin.admin_create_user),
    (admin_app, "create-key", admin.admin_create_key),
    (admin_app, "revoke-key", admin.admin_revoke_key),
    (admin_app, "list-keys", admin.admin_list_keys),
    (admin_app, "set-retention", admin.admin_set_retention),
    (app, "submit", rest.submit),
    (app, "status", rest.status),
    (app, "results", rest.results),
    (app, "summary", rest.summary),
    (app, "compare", rest.compare),
    (app, "report", rest.report),
    (app, "cancel", rest.cancel),
    (app, "delete", rest.delete),
    (schedules_app, "list", schedules.list_schedules),
    (schedules_app, "show", schedules.show),
    (schedules_app, "create", schedules.create),
    (schedules_app, "enable", schedules.enable),
    (schedules_app, "disable", schedules.disable),
    (schedules_app, "delete", schedules.delete),
    (schedules_app, "runs", schedules.runs),
    (presets_app, "list", schedules.list_presets),
    (presets_app, "run", schedules.run_preset),
    (share_app, "create", shares.create),
    (share_app, "list", shares.list_shares),
    (share_app, "revoke", shares.revoke),
    (datasets_app, "upload", datasets.upload),
    (datasets_app, "list", datasets.list_datasets),
    (datasets_app, "show", datasets.show),
    (datasets_app, "delete", datasets.delete),
    (datasets_app, "download", datasets.download),
    (app, "model", datasets.model),
    (app, "validation", datasets.validation),
    (systems_app, "from-file", datasets.system_from_file),
    (app, "run-local", local.run_local_command),
    (app, "reproduce", local.reproduce_command),
    (app, "serve", serve.serve_command),
)
for group, name, command in COMMANDS:
    group.command(name)(command)

if __name__ == "__main__":
    app()
