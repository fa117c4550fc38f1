"""The in-process commands: ``svrobs run-local`` and ``svrobs reproduce``.

``svrobs run-local SPEC.json --out DIR`` runs the core in process and writes
``DIR/records.jsonl`` (one record per line, docs/spec.md#record-fields; null never NaN) and
``DIR/summary.json`` (mean/std/count per group), with a progress bar on stderr.
A dataset spec runs on a file (``--dataset FILE``, or the spec's ``"dataset"`` given
as a path, relative to the spec's folder; its records' system is then
``dataset-1``) and also writes ``DIR/validation.json`` (docs/datasets.md#run-local).
Before anything runs, the service's admission (:func:`service.db.jobs.admit`, the
cost model :func:`svrobs_core.admission.admit`) refuses a spec over
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

LOCAL_DATASET_ID = 1  # the id of a dataset given as a path (the records' dataset-1)


def _local_dataset(spec_obj: dict, dataset: Path | None, base: Path, max_bytes: int):
    """(the spec with a dataset id, the dataset's rollouts or None): ``dataset`` is a
    file given beside the spec, else the spec's "dataset" may be a path."""
    from svrobs_core.errors import SpecError
    from svrobs_lab.datasets.loaded import file_data
    from svrobs_lab.errors import BadDatasetFile

    named = spec_obj.get("dataset") if isinstance(spec_obj, dict) else None
    if dataset is None and not isinstance(named, str):
        return spec_obj, None
    path = Path(dataset) if dataset is not None else base / str(named)
    if not path.is_file():
        raise SpecError("dataset", f"{path}: no such file")
    ident = named if isinstance(named, int) and not isinstance(named, bool) else LOCAL_DATASET_ID
    try:
        data = file_data(path, max_bytes=max_bytes)
    except BadDatasetFile as exc:
        raise SpecError("dataset", f"{path}: {exc.message}") from None
    return {**spec_obj, "dataset": ident}, data


def run_local(
    spec_obj: dict,
    out: Path,
    *,
    quiet: bool = False,
    max_cpu_seconds: float | None = None,
    max_memory_mb: float | None = None,
    dataset: Path | None = None,
    base: Path = Path("."),
) -> dict:
    """Run a spec in process; returns ``{"records": n, "out": str, "validation": bool}``.

    The service's job limits apply (:func:`svrobs_lab.jobs.admit_spec`; None:
    SVROBS_MAX_JOB_CPU_SECONDS, SVROBS_MAX_UNIT_MEMORY_MB): a spec over one raises
    its SpecError before anything is written. A dataset spec runs on the file
    ``dataset`` (or the path in its "dataset", relative to ``base``)."""
    from rich.console import Console

    from service.config import get_settings
    from svrobs_cli.progress import progress_bar
    from svrobs_core import SpecError, parse_spec, summarize
    from svrobs_core.measured import check_against_data, run_measured_unit
    from svrobs_core.runner import run_unit_result
    from svrobs_core.workload import DataShape
    from svrobs_lab.jobs import admit_spec
    from svrobs_lab.validation import summarize as validation

    settings = get_settings()
    overrides = {"MAX_JOB_CPU_SECONDS": max_cpu_seconds, "MAX_UNIT_MEMORY_MB": max_memory_mb}
    settings = settings.model_copy(update={k: v for k, v in overrides.items() if v is not None})
    spec_obj, data = _local_dataset(spec_obj, dataset, base, settings.MAX_DATASET_MB * 2**20)
    spec = parse_spec(spec_obj)
    shape = None
    if spec.measured is not None:
        if data is None:
            raise SpecError("dataset", "run-local needs the file: --dataset FILE (or a path)")
        check_against_data(spec, data.n, data.m, data.rollouts, lengths=data.lengths)
        shape = DataShape(n=data.n, m=data.m, lengths=tuple(int(t) for t in data.lengths))
    elif data is not None:
        raise SpecError("dataset", "--dataset is for a dataset spec (one without systems)")
    units = admit_spec(spec, settings, data=shape)
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
                    if data is None:
                        result = run_unit_result(spec, unit)
                    else:
                        result = run_measured_unit(spec, unit, data)
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
    if data is not None:
        checks = validation(spec.to_dict(), data)
        (out / "validation.json").write_text(json.dumps(checks, indent=1, allow_nan=False))
    return {"records": len(records), "out": str(out), "validation": data is not None}


def run_local_command(
    spec_path: Path = typer.Argument(..., help="a spec (JSON, docs/spec.md#spec-fields)"),
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
    dataset: Path | None = typer.Option(
        None,
        "--dataset",
        help="the file of a dataset spec (CSV, NPZ, .mat, JSON: docs/datasets.md#formats)",
    ),
) -> None:
    """Run a spec in process: DIR/records.jsonl and DIR/summary.json (a dataset spec:
    also DIR/validation.json)."""
    from svrobs_cli.rest import load_spec
    from svrobs_core import SpecError

    spec_obj = load_spec(spec_path)
    try:
        res = run_local(
            spec_obj,
            out,
            quiet=quiet,
            max_cpu_seconds=max_cpu_seconds,
            max_memory_mb=max_memory_mb,
            dataset=dataset,
            base=spec_path.parent,
        )
    except SpecError as exc:
        raise CliError(f"invalid spec: {exc.field}: {exc.message}") from None
    extra = ", validation.json" if res["validation"] else ""
    typer.echo(f"{res['records']} records -> {res['out']}/records.jsonl, summary.json{extra}")


def reproduce_command(
    out: Path = typer.Option(Path("paper-section-6"), "--out", help="output folder"),
    scale: str = typer.Option("full", "--scale", help="full | reduced"),
    only: str = typer.Option(
        None, "--only", help="experiments to run, e.g. E1,E2 (default: E1-E4, A1, A2)"
    ),
    rng: str = typer.Option(
        None, "--rng", help="generator of every draw: pcg64 (the preset's) or sfc64 (faster)"
    ),
    draws: str = typer.Option(
        None, "--draws", help="datasets drawn as wishart (the preset's) or rollouts (same law)"
    ),
    jobs: int = typer.Option(None, "--jobs", help="worker processes (default: CPUs)"),
    quiet: bool = typer.Option(False, "--quiet"),
) -> None:
    """The paper's Section 6 (E1-E4) and the audits A1, A2 in process: tables, figures, report.md."""
    from svrobs_cli.reproduce import ReproduceError, reproduce
    from svrobs_core.seeding import RNGS
    from svrobs_core.wishart_draws import DRAWS

    if scale not in ("full", "reduced"):
        raise CliError("--scale must be 'full' or 'reduced'")
    if rng is not None and rng not in RNGS:
        raise CliError(f"--rng must be one of {', '.join(sorted(RNGS))}")
    if draws is not None and draws not in DRAWS:
        raise CliError(f"--draws must be one of {', '.join(DRAWS)}")
    if jobs is not None and jobs < 1:
        raise CliError("--jobs must be >= 1")
    try:
        reproduce(out, scale=scale, quiet=quiet, only=only, rng=rng, draws=draws, n_jobs=jobs)
    except ReproduceError as exc:
        raise CliError(f"reproduce: {exc}") from None
    typer.echo(f"report -> {out}/report.md")
