"""The `svrobs` console script: REST/admin commands plus the in-process ones.

``service.cli`` holds the REST client and admin commands; this module adds
``run-local``, ``reproduce`` and ``serve`` to the same Typer app.
"""

from __future__ import annotations

from pathlib import Path

import typer

from .cli import app

__all__ = ["app"]


def _fail(message: str) -> None:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(2)


@app.command("run-local")
def run_local_cmd(
    spec_path: Path = typer.Argument(..., help="section 10 spec (JSON)"),
    out: Path = typer.Option(Path("out"), "--out", help="output folder"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
) -> None:
    """Run a spec in process: DIR/records.jsonl and DIR/summary.json."""
    from svrobs_core import SpecError

    from .run_local import load_spec_file, run_local

    try:
        spec_obj = load_spec_file(spec_path)
    except FileNotFoundError:
        _fail(f"{spec_path}: no such file")
    except ValueError as exc:
        _fail(f"{spec_path}: not valid JSON ({exc})")
    try:
        res = run_local(spec_obj, out, quiet=quiet)
    except SpecError as exc:
        _fail(f"invalid spec: {exc.field}: {exc.message}")
    typer.echo(f"{res['records']} records -> {res['out']}/records.jsonl, summary.json")


@app.command()
def reproduce(
    out: Path = typer.Option(Path("paper-section-6"), "--out", help="output folder"),
    scale: str = typer.Option("full", "--scale", help="full | reduced"),
    quiet: bool = typer.Option(False, "--quiet"),
) -> None:
    """The paper's Section 6 (E1-E4) in process: tables, figures, report.md."""
    from .reports.reproduce import reproduce as _reproduce

    if scale not in ("full", "reduced"):
        _fail("--scale must be 'full' or 'reduced'")
    _reproduce(out, scale=scale, quiet=quiet)
    typer.echo(f"report -> {out}/report.md")


@app.command()
def serve(
    workers: int = typer.Option(1, "--workers", help="worker processes"),
    concurrency: int | None = typer.Option(
        None, "--concurrency", help="pool processes per worker (default: one per CPU, at most 4)"
    ),
    no_beat: bool = typer.Option(False, "--no-beat", help="do not start the scheduler"),
) -> None:
    """Migrate, then run API + worker + scheduler (embedded default: SQLite + filesystem broker)."""
    from .serve import main

    argv = ["--workers", str(workers)]
    if concurrency is not None:
        argv += ["--concurrency", str(concurrency)]
    main(argv + (["--no-beat"] if no_beat else []))


if __name__ == "__main__":
    app()
