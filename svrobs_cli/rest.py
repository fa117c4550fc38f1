"""The REST commands of ``svrobs`` on jobs and results, through :mod:`svrobs_client`.

    svrobs submit SPEC.json [--wait] [--name N] [--tag T]... [--idempotency-key K] [--print-id]
    svrobs status [JOB] [--status S] [--tag T] [--owner me|EMAIL] [--json]
    svrobs results JOB --format csv|jsonl|json [--out FILE] [filters]
                   [--sort -rmse_A,N] [--where rmse_A_lt=0.01]...
    svrobs summary JOB [--field rmse_A]... [--json]
    svrobs compare --jobs J1,J2 --metric rmse_A --by N,estimator [--json]
    svrobs report JOB [--out FOLDER]
    svrobs cancel JOB
    svrobs delete JOB [--yes]

The base URL and key come from ``SVROBS_URL`` / ``SVROBS_API_KEY`` or
``~/.config/svrobs/config.json`` (``{"url", "api_key"}``), as for
:class:`svrobs_client.Client`. Errors are one line (:mod:`svrobs_cli.errors`); a
file or folder is written whole or not at all. The commands are registered in
:mod:`svrobs_cli.app`.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import typer

from svrobs_cli.errors import CliError, plain_message
from svrobs_cli.system_files import resolve_system_files
from svrobs_client import RESULT_FILTERS, Client, Job, ValidationError
from svrobs_client.params import results_params
from svrobs_lab import json_text


def client(*, timeout: float = 30.0) -> Client:
    """The client of the configured server (the one HTTP code path of the CLI)."""
    return Client(timeout=timeout)


def load_spec(path: Path) -> dict:
    """A spec file (JSON, or YAML with PyYAML installed); ``-`` reads stdin. Every
    problem with the file is a :class:`CliError` naming it."""
    try:
        text = sys.stdin.read() if str(path) == "-" else path.read_text(encoding="utf-8")
    except OSError as exc:
        raise CliError(f"cannot read {path}: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise CliError(f"cannot read {path}: not a text file (not UTF-8)") from None
    if path.suffix in (".yaml", ".yml"):
        try:
            import yaml
        except ImportError:
            raise CliError("YAML specs need PyYAML (pip install pyyaml)") from None
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None)
            where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
            problem = getattr(exc, "problem", None) or "cannot be parsed"
            raise CliError(f"{path}: not valid YAML: {problem}{where}") from None
    else:
        try:
            data = json_text.loads(text)
        except ValueError as exc:
            raise CliError(f"{path}: {exc}") from None
    if not isinstance(data, dict):
        raise CliError(f"{path}: the spec must be a JSON object")
    return data


def fmt(value) -> str:
    """A table cell: blank for null, 6 significant digits for a float."""
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, list):
        return ",".join(map(str, value))
    return str(value)


def print_table(columns: list[str], rows: list[list], *, title: str | None = None) -> None:
    """A rich table in a terminal; tab-separated lines (header first, nothing cut) when
    stdout is a pipe or a file."""
    if not sys.stdout.isatty():
        for line in [columns, *rows]:
            typer.echo("\t".join(fmt(v) for v in line))
        return
    from rich.console import Console
    from rich.table import Table

    table = Table(*columns, title=title)
    for row in rows:
        table.add_row(*(fmt(v) for v in row))
    Console().print(table)


def print_json(data) -> None:
    typer.echo(json.dumps(data, indent=2))


def _count(n: int, word: str) -> str:
    return f"{n} {word}" if n == 1 else f"{n} {word}s"


def submitted_line(job: Job) -> str:
    """``job 3 queued (30 cells, 1 unit)``: what ``svrobs submit`` made."""
    return f"job {job.id} {job.status} ({_count(job.n_cells, 'cell')}, {_count(job.progress.total, 'unit')})"


def progress_line(job: Job) -> str:
    return f"job {job.id} {job.status} {job.progress.done}/{job.progress.total} units"


def finish(c: Client, job: Job, *, err: bool = False) -> None:
    """Wait for ``job`` with a progress bar, print its last state (on stderr with
    ``err``); an error unless it succeeded. Ctrl-C stops the waiting, not the job:
    one line says so and how to follow or cancel it (then KeyboardInterrupt)."""
    try:
        job = c.wait(job)
    except KeyboardInterrupt:
        typer.echo(
            f"interrupted: job {job.id} keeps running (svrobs status {job.id}; "
            f"svrobs cancel {job.id} stops it)",
            err=True,
        )
        raise
    typer.echo(progress_line(job), err=err)
    if job.status != "succeeded":
        raise CliError(f"job {job.id} {job.status}: {job.error or ''}".strip())


def submit(
    spec_file: Path = typer.Argument(
        ...,
        help="a spec (docs/spec.md#spec-fields) as a JSON (or YAML) file; - for stdin. A system "
        'may be {"file": "plant.mat"} (A, B, optionally C in an NPZ, .mat or JSON file)',
    ),
    wait: bool = typer.Option(False, "--wait", help="show progress until the job finishes"),
    name: str | None = typer.Option(None, help="job name"),
    tag: list[str] = typer.Option([], "--tag", help="a tag (repeatable)"),
    idempotency_key: str | None = typer.Option(
        None, help="retrying with the same key returns the same job"
    ),
    print_id: bool = typer.Option(
        False,
        "--print-id",
        help="print only the job id on stdout (the rest on stderr): job=$(svrobs submit ...)",
    ),
) -> None:
    """Submit an experiment spec as a job."""
    spec = load_spec(spec_file)
    with client() as c:
        base = Path.cwd() if str(spec_file) == "-" else spec_file.parent
        spec = resolve_system_files(c, spec, base)
        try:
            job = c.submit(spec, name=name, tags=tag, idempotency_key=idempotency_key, wait=False)
        except ValidationError as exc:
            raise CliError(f"invalid spec: {plain_message(exc)}") from None
        typer.echo(submitted_line(job), err=print_id)
        if wait:
            try:
                finish(c, job, err=print_id)
            except KeyboardInterrupt:
                if print_id:  # job=$(svrobs submit ... --print-id): the id all the same
                    typer.echo(job.id)
                raise typer.Exit(130) from None
        if print_id:
            typer.echo(job.id)


def status(
    job: int | None = typer.Argument(None, help="a job id; none lists recent jobs"),
    limit: int = typer.Option(20, help="jobs to list"),
    offset: int = typer.Option(0, help="skip this many jobs (newest first)"),
    state: str | None = typer.Option(None, "--status", help="only jobs in this state"),
    tag: str | None = typer.Option(None, help="only jobs with this tag"),
    owner: str | None = typer.Option(None, help="only jobs of this owner: an email or 'me'"),
    as_json: bool = typer.Option(False, "--json", help="print JSON"),
) -> None:
    """Show one job, or list the team's recent jobs."""
    with client() as c:
        if job is not None:
            j = c.job(job)
            if as_json:
                return print_json(j.raw)
            typer.echo(progress_line(j))
            for key in ("name", "tags", "owner", "n_cells", "created_at", "started_at"):
                if j.raw.get(key) not in (None, [], ""):
                    typer.echo(f"  {key}: {j.raw[key]}")
            for key in ("finished_at", "error", "timings"):
                if j.raw.get(key) not in (None, {}, ""):
                    typer.echo(f"  {key}: {j.raw[key]}")
            return
        page = c.jobs(status=state, tag=tag, owner=owner, limit=limit, offset=offset)
    if as_json:
        return print_json(
            {
                **{k: getattr(page, k) for k in ("total", "limit", "offset")},
                "items": [j.raw for j in page],
            }
        )
    print_table(
        ["id", "name", "status", "progress", "cells", "tags", "created"],
        [
            [
                j.id,
                j.name,
                j.status,
                f"{j.progress.done}/{j.progress.total}",
                j.n_cells,
                j.tags,
                str(j.raw.get("created_at"))[:19],
            ]
            for j in page
        ],
    )
    typer.echo(f"{len(page)} of {page.total} jobs")


def results(
    job: int = typer.Argument(...),
    format: str = typer.Option("csv", "--format", help="csv, jsonl or json"),
    out: Path | None = typer.Option(
        None, "--out", help="write to this file (default, or -: stdout)"
    ),
    system: list[str] = typer.Option([], help="filter (repeatable)"),
    sigma_w: list[float] = typer.Option([], help="filter (repeatable)"),
    n: list[int] = typer.Option([], "--N", help="filter on N (repeatable)"),
    estimator: list[str] = typer.Option([], help="filter (repeatable)"),
    gamma: list[str] = typer.Option([], help="filter, 'null' for ols (repeatable)"),
    rep: list[int] = typer.Option([], help="filter (repeatable)"),
    sort: str | None = typer.Option(
        None, help="numeric fields, - for descending: --sort=-rmse_A,N"
    ),
    where: list[str] = typer.Option(
        [], help="a range: FIELD_lt|_lte|_gt|_gte=NUMBER, e.g. rmse_A_lt=0.01 (repeatable)"
    ),
) -> None:
    """Download a job's records (CSV and JSONL stream everything; JSON is one array).
    A file given by --out is written whole or not at all."""
    if format not in ("csv", "jsonl", "json"):
        raise CliError("--format must be csv, jsonl or json")
    if out is not None and str(out) == "-":  # as `svrobs submit -` reads stdin
        out = None
    ranges = {}
    for item in where:
        name, eq, value = item.partition("=")
        if not eq or not name.strip() or name.strip() in ("limit", "offset", *RESULT_FILTERS):
            raise CliError(f"--where takes FIELD_lt=NUMBER (or _lte, _gt, _gte), not {item!r}")
        ranges[name.strip()] = value.strip()
    filters = {
        "system": system,
        "sigma_w": sigma_w,
        "N": n,
        "estimator": estimator,
        "gamma": gamma,
        "rep": rep,
    }
    filters = {k: v for k, v in filters.items() if v}
    try:  # checked before any request or file
        results_params({**filters, **ranges}, sort)
    except (TypeError, ValueError) as exc:
        text = str(exc).replace("unknown results filter", "unknown range")
        raise CliError(f"--{text}" if text.startswith("sort") else f"--where: {text}") from None
    with client(timeout=300) as c:
        c.download_results(
            job,
            out if out is not None else sys.stdout,
            format=format,
            sort=sort,
            **filters,
            **ranges,
        )
    if out is not None:
        print(f"wrote {out}", file=sys.stderr)


def summary(
    job: int = typer.Argument(...),
    field: list[str] = typer.Option(
        ["rmse_A", "rmse_B"], "--field", help="a numeric record field to show (repeatable)"
    ),
    as_json: bool = typer.Option(False, "--json", help="print the API's JSON (every field)"),
) -> None:
    """Mean and std of record fields per (system, sigma_w, N, estimator, gamma)."""
    with client() as c:
        data = c.summary_json(job)
    if as_json:
        return print_json(data)
    groups = data["groups"]
    known = set(groups[0]["stats"]) if groups else set(field)
    unknown = [f for f in field if f not in known]
    if unknown:
        raise CliError(
            f"--field: {', '.join(unknown)} not a summarised field; one of "
            f"{', '.join(sorted(known))}"
        )
    cols = ["system", "sigma_w", "N", "estimator", "gamma", "count"]
    rows = [
        [g[k] for k in cols] + [g["stats"][f][s] for f in field for s in ("mean", "std")]
        for g in groups
    ]
    if data["partial"]:
        print(f"note: job {job} has not succeeded; the summary is partial", file=sys.stderr)
    header = cols + [f"{f} {s}" for f in field for s in ("mean", "std")]
    print_table(header, rows, title=f"job {data['job_id']} summary")


def compare(
    jobs: str = typer.Option(..., help="comma-separated job ids"),
    metric: str = typer.Option("rmse_A", help="a numeric record field"),
    by: str = typer.Option("N,estimator,gamma", help="comma-separated grid fields"),
    as_json: bool = typer.Option(False, "--json", help="print JSON"),
) -> None:
    """One metric across several jobs, grouped by grid coordinates."""
    ids = [j.strip() for j in jobs.split(",") if j.strip()]
    with client() as c:
        data = c.compare_json(ids, metric, by)
    if as_json:
        return print_json(data)
    cols = ["job_id", *data["by"], "mean", "std", "count"]
    print_table(
        cols,
        [[r[k] for k in cols] for r in data["rows"]],
        title=f"{data['metric']} by {', '.join(data['by'])}",
    )


def report(
    job: int = typer.Argument(...),
    out: Path | None = typer.Option(None, "--out", help="folder (default job-ID-report)"),
) -> None:
    """Write a job's HTML report and its figures (PNG) into a folder."""
    folder = out or Path(f"job-{job}-report")
    with client(timeout=300) as c:
        rep = c.report(job, folder)
    typer.echo(f"wrote {rep.html} and {len(rep.figures)} figures in {folder / 'figures'}")


def cancel(job: int = typer.Argument(...)) -> None:
    """Cancel a queued or running job (units not yet started never run)."""
    with client() as c:
        typer.echo(progress_line(c.cancel(job)))


def delete(
    job: int = typer.Argument(...),
    yes: bool = typer.Option(False, "--yes", "-y", help="delete without asking"),
) -> None:
    """Delete a job with its results and summaries (a queued or running job: cancel it
    first)."""
    if not yes:
        if not sys.stdin.isatty():
            raise CliError("not deleted: give --yes to delete without a prompt")
        if not typer.confirm(f"delete job {job} with all its results?"):
            raise CliError("not deleted")
    with client() as c:
        c.delete(job)
    typer.echo(f"job {job} deleted")
