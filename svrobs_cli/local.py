"""The in-process commands: ``svrobs run-local`` and ``svrobs reproduce``.

``svrobs run-local SPEC.json --out DIR`` runs the core in process and writes
``DIR/records.jsonl`` (one section 10 record per line, null never NaN) and
``DIR/summary.json`` (mean/std/count per group), with a progress bar on stderr.
``svrobs reproduce`` runs the paper's Section 6 (:mod:`service.reports.reproduce`).
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


def run_local(spec_obj: dict, out: Path, *, quiet: bool = False) -> dict:
    """Run a spec in process; returns ``{"records": n, "out": str}``."""
    from rich.console import Console

    from service.progress import progress_bar
    from svrobs_core import parse_spec, plan_units, summarize
    from svrobs_core.runner import run_unit_result

    spec = parse_spec(spec_obj)
    units = plan_units(spec)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    records: list[dict] = []
    console = Console(stderr=True)
    with progress_bar(console, quiet=quiet) as bar:
        task = bar.add_task("work units", total=len(units))
        with open(out / "records.jsonl", "w") as fh:
            for unit in units:
                result = run_unit_result(spec, unit)
                lines = result.json_lines()  # = json.dumps(record) per record, built per field
                if lines:
                    fh.write("\n".join(lines) + "\n")
                records += result.records()
                bar.advance(task)
    summary = {"spec": spec.to_dict(), "groups": summarize(records)}
    (out / "summary.json").write_text(json.dumps(summary, indent=1, allow_nan=False))
    return {"records": len(records), "out": str(out)}


def run_local_command(
    spec_path: Path = typer.Argument(..., help="section 10 spec (JSON)"),
    out: Path = typer.Option(Path("out"), "--out", help="output folder"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
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
        res = run_local(spec_obj, out, quiet=quiet)
    except SpecError as exc:
        raise CliError(f"invalid spec: {exc.field}: {exc.message}") from None
    typer.echo(f"{res['records']} records -> {res['out']}/records.jsonl, summary.json")


def reproduce_command(
    out: Path = typer.Option(Path("paper-section-6"), "--out", help="output folder"),
    scale: str = typer.Option("full", "--scale", help="full | reduced"),
    quiet: bool = typer.Option(False, "--quiet"),
) -> None:
    """The paper's Section 6 (E1-E4) in process: tables, figures, report.md."""
    from service.reports.reproduce import reproduce

    if scale not in ("full", "reduced"):
        raise CliError("--scale must be 'full' or 'reduced'")
    reproduce(out, scale=scale, quiet=quiet)
    typer.echo(f"report -> {out}/report.md")
