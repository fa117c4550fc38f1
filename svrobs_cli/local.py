"""The in-process commands: ``svrobs run-local`` and ``svrobs reproduce``.

``svrobs run-local SPEC.json --out DIR`` runs the core in process and writes
``DIR/records.jsonl`` (one section 10 record per line, null never NaN) and
``DIR/summary.json`` (mean/std/count per group), with a progress bar on stderr.
Before anything runs, the service's admission (:func:`service.db.jobs.admit`, the
cost model :func:`svrobs_core.workload.admit`) refuses a spec over
``--max-cpu-seconds`` (default SVROBS_MAX_JOB_CPU_SECONDS) or whose smallest work
unit is over ``--max-memory-mb`` (SVROBS_MAX_UNIT_MEMORY_MB), and plans the units
under that memory cap; the records
file appears only once every unit has run.
``svrobs reproduce`` runs the paper's Section 6 (:mod:`svrobs_cli.reproduce`).
"""

from __future__ import annotations

import json
from pathlib import Path

import typer

from svrobs_cli.errors import CliError


def load_spec_file(path: Path) -> dict:
    """Read a JSON (or YAML, if PyYAML is installed) spec file."""
    text = Path(path).read_text()
    if Path(path).suffix in (".yaml", ".yml"):
        import yaml  # optional

        return yaml.safe_load(text)
    return json.loads(text)


def run_local(
    spec_obj: dict,
    out: Path,
    *,
    quiet: bool = False,
    max_cpu_seconds: float | None = None,
    max_memory_mb: float | None = None,
) -> dict:
    """Run a spec in process; returns ``{"records": n, "out": str}``.

    The service's job limits apply (:func:`svrobs_lab.jobs.admit_spec`; None:
    SVROBS_MAX_JOB_CPU_SECONDS, SVROBS_MAX_UNIT_MEMORY_MB): a spec over one raises
    its SpecError before anything is written."""
    from rich.console import Console

    from service.config import get_settings
    from svrobs_cli.progress import progress_bar
    from svrobs_core import parse_spec, summarize
    from svrobs_core.runner import run_unit_result
    from svrobs_lab.jobs import admit_spec

    settings = get_settings()
    overrides = {"MAX_JOB_CPU_SECONDS": max_cpu_seconds, "MAX_UNIT_MEMORY_MB": max_memory_mb}
    settings = settings.model_copy(update={k: v for k, v in overrides.items() if v is not None})
    spec = parse_spec(spec_obj)
    units = admit_spec(spec, settings)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    records: list[dict] = []
    console = Console(stderr=True)
    partial = out / "records.jsonl.partial"
    try:
        with progress_bar(console, quiet=quiet) as bar:
            task = bar.add_task("work units", total=len(units))
            with open(partial, "w") as fh:
                for unit in units:
                    result = run_unit_result(spec, unit)
                    lines = result.json_lines()  # = json.dumps(record) per record, per field
                    if lines:
                        fh.write("\n".join(lines) + "\n")
                    records += result.records()
                    bar.advance(task)
        partial.replace(out / "records.jsonl")
    finally:
        partial.unlink(missing_ok=True)  # a failed or interrupted run leaves no records file
    summary = {"spec": spec.to_dict(), "groups": summarize(records)}
    (out / "summary.json").write_text(json.dumps(summary, indent=1, allow_nan=False))
    return {"records": len(records), "out": str(out)}


def run_local_command(
    spec_path: Path = typer.Argument(..., help="section 10 spec (JSON)"),
    out: Path = typer.Option(Path("out"), "--out", help="output folder"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
    max_cpu_seconds: float | None = typer.Option(
        None,
        "--max-cpu-seconds",
        help="refuse a spec estimated above this [SVROBS_MAX_JOB_CPU_SECONDS, 3600]",
    ),
    max_memory_mb: float | None = typer.Option(
        None,
        "--max-memory-mb",
        help="peak memory of one work unit [SVROBS_MAX_UNIT_MEMORY_MB, 2048]",
    ),
) -> None:
    """Run a spec in process: DIR/records.jsonl and DIR/summary.json."""
    from svrobs_core import SpecError

    try:
        spec_obj = load_spec_file(spec_path)
    except FileNotFoundError:
        raise CliError(f"{spec_path}: no such file") from None
    except ValueError as exc:
        raise CliError(f"{spec_path}: not valid JSON ({exc})") from None
    try:
        res = run_local(
            spec_obj,
            out,
            quiet=quiet,
            max_cpu_seconds=max_cpu_seconds,
            max_memory_mb=max_memory_mb,
        )
    except SpecError as exc:
        raise CliError(f"invalid spec: {exc.field}: {exc.message}") from None
    typer.echo(f"{res['records']} records -> {res['out']}/records.jsonl, summary.json")


def reproduce_command(
    out: Path = typer.Option(Path("paper-section-6"), "--out", help="output folder"),
    scale: str = typer.Option("full", "--scale", help="full | reduced"),
    only: str = typer.Option(
        None, "--only", help="experiments to run, e.g. E1,E2 (default: E1-E4, A1, A2)"
    ),
    rng: str = typer.Option(
        None, "--rng", help="generator of every draw: pcg64 (the preset's) or sfc64 (faster)"
    ),
    jobs: int = typer.Option(None, "--jobs", help="worker processes (default: CPUs)"),
    quiet: bool = typer.Option(False, "--quiet"),
) -> None:
    """The paper's Section 6 (E1-E4) and the audits A1, A2 in process: tables, figures, report.md."""
    from svrobs_cli.reproduce import ReproduceError, reproduce
    from svrobs_core.rollouts import RNGS

    if scale not in ("full", "reduced"):
        raise CliError("--scale must be 'full' or 'reduced'")
    if rng is not None and rng not in RNGS:
        raise CliError(f"--rng must be one of {', '.join(sorted(RNGS))}")
    if jobs is not None and jobs < 1:
        raise CliError("--jobs must be >= 1")
    try:
        reproduce(out, scale=scale, quiet=quiet, only=only, rng=rng, n_jobs=jobs)
    except ReproduceError as exc:
        raise CliError(f"reproduce: {exc}") from None
    typer.echo(f"report -> {out}/report.md")
