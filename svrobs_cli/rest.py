"""The REST commands of ``svrobs``: a small HTTP client of the API.

    svrobs submit SPEC.json [--wait] [--name N] [--tag T]...
    svrobs status [JOB]
    svrobs results JOB --format csv|jsonl|json [--out FILE]
    svrobs compare --jobs 1,2 --metric rmse_A --by N,estimator

The REST commands read the base URL and key from ``SVROBS_URL`` /
``SVROBS_API_KEY`` or ``~/.config/svrobs/config.json`` (``{"url", "api_key"}``).
Errors are :class:`~svrobs_cli.errors.CliError` (one line, exit status 2). The
commands are registered in :mod:`svrobs_cli.app`.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import typer

from svrobs_cli.errors import CliError

DEFAULT_URL = "http://127.0.0.1:8000"
CONFIG_PATH = Path(os.environ.get("SVROBS_CONFIG", "~/.config/svrobs/config.json")).expanduser()
TERMINAL = ("succeeded", "failed", "cancelled")


# --------------------------------------------------------------------------- REST client


def client_config() -> tuple[str, str]:
    """(base URL, API key) from the environment or the config file."""
    cfg: dict = {}
    if CONFIG_PATH.is_file():
        try:
            cfg = json.loads(CONFIG_PATH.read_text())
        except (OSError, ValueError) as exc:
            raise CliError(f"cannot read {CONFIG_PATH}: {exc}") from None
    url = os.environ.get("SVROBS_URL") or cfg.get("url") or DEFAULT_URL
    key = os.environ.get("SVROBS_API_KEY") or cfg.get("api_key")
    if not key:
        raise CliError(f"no API key: set SVROBS_API_KEY or 'api_key' in {CONFIG_PATH}")
    return url.rstrip("/"), key


class Api:
    def __init__(
        self, url: str | None = None, key: str | None = None, timeout: float = 30.0, http=None
    ):
        import httpx

        if http is not None:  # an injected client (tests)
            self.base, self.http = str(http.base_url).rstrip("/"), http
            return
        if url is None or key is None:
            u, k = client_config()
            url, key = url or u, key or k
        self.base = url.rstrip("/")
        self.http = httpx.Client(
            base_url=f"{self.base}/api/v1",
            timeout=timeout,
            headers={"Authorization": f"Bearer {key}"},
        )

    def request(self, method: str, path: str, **kw):
        import httpx

        try:
            r = self.http.request(method, path, **kw)
        except httpx.HTTPError as exc:
            raise CliError(f"cannot reach {self.base}: {exc}") from None
        if r.status_code >= 400:
            raise CliError(_http_error(r))
        return r

    def stream(self, path: str, **kw):
        return self.http.stream("GET", path, **kw)


def _http_error(r) -> str:
    try:
        body = r.json()
        detail, field = body.get("detail"), body.get("field")
    except ValueError:
        detail, field = r.text[:200], None
    where = f"{field}: " if field else ""
    return f"HTTP {r.status_code}: {where}{detail}"


def _load_spec(path: Path) -> dict:
    if str(path) == "-":
        text = sys.stdin.read()
    else:
        try:
            text = path.read_text()
        except OSError as exc:
            raise CliError(f"cannot read {path}: {exc.strerror}") from None
    if path.suffix in (".yaml", ".yml"):
        try:
            import yaml
        except ImportError:
            raise CliError("YAML specs need PyYAML (pip install pyyaml)") from None
        data = yaml.safe_load(text)
    else:
        try:
            data = json.loads(text)
        except ValueError as exc:
            raise CliError(f"{path}: not valid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise CliError(f"{path}: the spec must be a JSON object")
    return data


def _progress_line(job: dict) -> str:
    p = job["progress"]
    return f"job {job['id']} {job['status']} {p['done']}/{p['total']} units"


def wait_for(api: Api, job: dict, interval: float = 1.0) -> dict:
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(
        TextColumn("job {task.fields[job]} {task.fields[status]}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total} units"),
        TimeElapsedColumn(),
        transient=False,
    ) as bar:
        task = bar.add_task(
            "run", total=job["progress"]["total"] or 1, job=job["id"], status=job["status"]
        )
        while job["status"] not in TERMINAL:
            time.sleep(interval)
            job = api.request("GET", f"/jobs/{job['id']}").json()
            bar.update(
                task,
                completed=job["progress"]["done"],
                total=job["progress"]["total"] or 1,
                status=job["status"],
            )
    return job


def submit(
    spec_file: Path = typer.Argument(
        ..., help="a SPEC section 10 JSON (or YAML) file; - for stdin"
    ),
    wait: bool = typer.Option(False, "--wait", help="show progress until the job finishes"),
    name: str | None = typer.Option(None, help="job name"),
    tag: list[str] = typer.Option([], "--tag", help="a tag (repeatable)"),
    idempotency_key: str | None = typer.Option(
        None, help="retrying with the same key returns the same job"
    ),
) -> None:
    """Submit an experiment spec as a job."""
    spec = _load_spec(spec_file)
    if name is not None:
        spec["name"] = name
    if tag:
        spec["tags"] = list(spec.get("tags") or []) + list(tag)
    api = Api()
    headers = {"Idempotency-Key": idempotency_key} if idempotency_key else {}
    job = api.request("POST", "/jobs", json=spec, headers=headers).json()
    typer.echo(
        f"job {job['id']} {job['status']} ({job['n_cells']} cells, "
        f"{job['progress']['total']} units)"
    )
    if wait:
        job = wait_for(api, job)
        typer.echo(_progress_line(job))
        if job["status"] != "succeeded":
            raise CliError(f"job {job['id']} {job['status']}: {job.get('error') or ''}".strip())


def status(
    job: int | None = typer.Argument(None, help="a job id; none lists recent jobs"),
    limit: int = typer.Option(20, help="jobs to list"),
    state: str | None = typer.Option(None, "--status", help="only jobs in this state"),
    tag: str | None = typer.Option(None, help="only jobs with this tag"),
    as_json: bool = typer.Option(False, "--json", help="print JSON"),
) -> None:
    """Show one job, or list the team's recent jobs."""
    api = Api()
    if job is not None:
        data = api.request("GET", f"/jobs/{job}").json()
        if as_json:
            typer.echo(json.dumps(data, indent=2))
            return
        typer.echo(_progress_line(data))
        for key in (
            "name",
            "tags",
            "owner",
            "n_cells",
            "created_at",
            "started_at",
            "finished_at",
            "error",
        ):
            if data.get(key) not in (None, [], ""):
                typer.echo(f"  {key}: {data[key]}")
        if data.get("timings"):
            typer.echo(f"  timings: {data['timings']}")
        return
    params = {"limit": limit}
    if state:
        params["status"] = state
    if tag:
        params["tag"] = tag
    page = api.request("GET", "/jobs", params=params).json()
    if as_json:
        typer.echo(json.dumps(page, indent=2))
        return
    from rich.console import Console
    from rich.table import Table

    table = Table("id", "name", "status", "progress", "cells", "tags", "created")
    for j in page["items"]:
        p = j["progress"]
        table.add_row(
            str(j["id"]),
            j["name"] or "",
            j["status"],
            f"{p['done']}/{p['total']}",
            str(j["n_cells"]),
            ",".join(j["tags"]),
            str(j["created_at"])[:19],
        )
    Console().print(table)
    typer.echo(f"{len(page['items'])} of {page['total']} jobs")


def results(
    job: int = typer.Argument(...),
    fmt: str = typer.Option("csv", "--format", help="csv, jsonl or json"),
    out: Path | None = typer.Option(None, "--out", help="write to this file (default stdout)"),
    system: list[str] = typer.Option([], help="filter (repeatable)"),
    sigma_w: list[float] = typer.Option([], help="filter (repeatable)"),
    n: list[int] = typer.Option([], "--N", help="filter on N (repeatable)"),
    estimator: list[str] = typer.Option([], help="filter (repeatable)"),
    gamma: list[str] = typer.Option([], help="filter, 'null' for ols (repeatable)"),
    rep: list[int] = typer.Option([], help="filter (repeatable)"),
) -> None:
    """Download a job's records (CSV and JSONL stream everything; JSON is every page)."""
    if fmt not in ("csv", "jsonl", "json"):
        raise CliError("--format must be csv, jsonl or json")
    params: dict = {
        "system": system,
        "sigma_w": sigma_w,
        "N": n,
        "estimator": estimator,
        "gamma": gamma,
        "rep": rep,
    }
    params = {k: v for k, v in params.items() if v}
    api = Api(timeout=300)
    sink = open(out, "w", encoding="utf-8", newline="") if out else sys.stdout
    try:
        if fmt == "json":
            items, offset = [], 0
            while True:
                page = api.request(
                    "GET",
                    f"/jobs/{job}/results",
                    params={**params, "limit": 10_000, "offset": offset},
                ).json()
                items += page["items"]
                offset += len(page["items"])
                if not page["items"] or offset >= page["total"]:
                    break
            json.dump(items, sink)
            sink.write("\n")
        else:
            import httpx

            try:
                with api.stream(f"/jobs/{job}/results", params={**params, "format": fmt}) as r:
                    if r.status_code >= 400:
                        r.read()
                        raise CliError(_http_error(r))
                    for chunk in r.iter_text():
                        sink.write(chunk)
            except httpx.HTTPError as exc:
                raise CliError(f"cannot reach {api.base}: {exc}") from None
    finally:
        if out:
            sink.close()
    if out:
        print(f"wrote {out}", file=sys.stderr)


def compare(
    jobs: str = typer.Option(..., help="comma-separated job ids"),
    metric: str = typer.Option("rmse_A", help="a numeric record field"),
    by: str = typer.Option("N,estimator,gamma", help="comma-separated grid fields"),
    as_json: bool = typer.Option(False, "--json", help="print JSON"),
) -> None:
    """One metric across several jobs, grouped by grid coordinates."""
    data = (
        Api().request("GET", "/compare", params={"jobs": jobs, "metric": metric, "by": by}).json()
    )
    if as_json:
        typer.echo(json.dumps(data, indent=2))
        return
    from rich.console import Console
    from rich.table import Table

    cols = ["job_id", *data["by"], "mean", "std", "count"]
    table = Table(*cols, title=f"{data['metric']} by {', '.join(data['by'])}")
    for row in data["rows"]:
        table.add_row(
            *(
                ""
                if row[c] is None
                else (f"{row[c]:.6g}" if isinstance(row[c], float) else str(row[c]))
                for c in cols
            )
        )
    Console().print(table)
