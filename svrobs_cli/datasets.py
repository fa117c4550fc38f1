"""The ``svrobs datasets``, ``svrobs model`` and ``svrobs systems`` commands, through
:mod:`svrobs_client` (docs/datasets.md#cli).

    svrobs datasets upload FILE --name N [--description D] [--sample-time DT]
                           [--state-columns x1,x2] [--input-columns u1]
                           [--state-names a,b] [--input-names u] [--json] [--print-id]
    svrobs datasets list [--limit 20] [--offset 0] [--json]
    svrobs datasets show ID [--json]
    svrobs datasets delete ID [--yes]
    svrobs datasets download ID [--out FILE]
    svrobs model JOB --cell system=S,N=50,estimator=svr,gamma=0.05,rep=0
                 [--format json|npz|mat] [--out FILE]
    svrobs systems from-file FILE [--name N]

A file given by ``--out`` is written whole or not at all; errors are one line.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import typer

from svrobs_cli.errors import CliError, plain_message
from svrobs_cli.rest import client, print_json, print_table
from svrobs_client import Dataset, ValidationError
from svrobs_client.files import write_atomic, writer


def _summary(d: Dataset) -> str:
    lengths = d.raw.get("T_min"), d.raw.get("T_max")
    steps = f"T {lengths[0]}" if lengths[0] == lengths[1] else f"T {lengths[0]}..{lengths[1]}"
    return (
        f"dataset {d.id} {d.name!r}: {d.rollouts} rollouts ({steps}), n={d.n}, m={d.m}, "
        f"{d.format}, sha256 {d.sha256[:12]}"
    )


def _check_file(file: Path) -> None:
    """A file to send: a CliError saying so when ``file`` is missing or a folder."""
    if not file.is_file():
        raise CliError(f"cannot read {file}: {'a folder' if file.is_dir() else 'no such file'}")


def upload(
    file: Path = typer.Argument(..., help="CSV (long form), NPZ, .mat (v5 or v7.3) or JSON"),
    name: str = typer.Option(..., help="the dataset's name"),
    description: str | None = typer.Option(None, help="a description"),
    sample_time: float | None = typer.Option(None, help="seconds between two time steps"),
    state_columns: str | None = typer.Option(None, help="CSV: the state columns, x1,x2,..."),
    input_columns: str | None = typer.Option(None, help="CSV: the input columns ('' for none)"),
    state_names: str | None = typer.Option(None, help="NPZ/MAT/JSON: the states' names"),
    input_names: str | None = typer.Option(None, help="NPZ/MAT/JSON: the inputs' names"),
    as_json: bool = typer.Option(False, "--json", help="print the API's JSON"),
    print_id: bool = typer.Option(
        False,
        "--print-id",
        help="print only the dataset id on stdout (the summary on stderr): "
        "ds=$(svrobs datasets upload ...)",
    ),
) -> None:
    """Upload a file of measured rollouts as a dataset."""
    _check_file(file)
    with client(timeout=600) as c:
        try:
            d = c.upload_dataset(
                file,
                name=name,
                description=description,
                sample_time=sample_time,
                state_columns=state_columns,
                input_columns=input_columns,
                state_names=state_names,
                input_names=input_names,
            )
        except ValidationError as exc:
            raise CliError(f"{file.name}: {plain_message(exc)}") from None
    if print_id:
        typer.echo(_summary(d), err=True)
        return typer.echo(d.id)
    if as_json:
        return print_json(d.raw)
    typer.echo(_summary(d))


def list_datasets(
    limit: int = typer.Option(20, help="datasets to list"),
    offset: int = typer.Option(0, help="skip this many (newest first)"),
    as_json: bool = typer.Option(False, "--json", help="print JSON"),
) -> None:
    """The team's datasets, newest first."""
    with client() as c:
        page = c.datasets(limit=limit, offset=offset)
    if as_json:
        return print_json(
            {
                "items": [d.raw for d in page],
                "total": page.total,
                "limit": page.limit,
                "offset": page.offset,
            }
        )
    print_table(
        ["id", "name", "format", "rollouts", "T", "n", "m", "bytes", "created"],
        [
            [
                d.id,
                d.name,
                d.format,
                d.rollouts,
                f"{d.raw.get('T_min')}..{d.raw.get('T_max')}",
                d.n,
                d.m,
                d.size_bytes,
                str(d.raw.get("created_at"))[:19],
            ]
            for d in page
        ],
    )
    typer.echo(f"{len(page)} of {page.total} datasets")


def show(
    dataset: int = typer.Argument(...),
    as_json: bool = typer.Option(False, "--json", help="print JSON"),
) -> None:
    """One dataset: shapes, names and per-channel statistics."""
    with client() as c:
        d = c.dataset(dataset)
    if as_json:
        return print_json(d.raw)
    typer.echo(_summary(d))
    for key in ("description", "filename", "sample_time", "owner", "created_at"):
        if d.raw.get(key) not in (None, ""):
            typer.echo(f"  {key}: {d.raw[key]}")
    rows = []
    for kind in ("states", "inputs"):
        for channel, s in (d.stats.get(kind) or {}).items():
            rows.append([channel, kind[:-1], s["mean"], s["std"], s["min"], s["max"]])
    print_table(["channel", "kind", "mean", "std", "min", "max"], rows)


def delete(
    dataset: int = typer.Argument(...),
    yes: bool = typer.Option(False, "--yes", "-y", help="delete without asking"),
) -> None:
    """Delete a dataset (refused while jobs use it)."""
    if not yes:
        if not sys.stdin.isatty():
            raise CliError("not deleted: give --yes to delete without a prompt")
        if not typer.confirm(f"delete dataset {dataset}?"):
            raise CliError("not deleted")
    with client() as c:
        c.delete_dataset(dataset)
    typer.echo(f"dataset {dataset} deleted")


def download(
    dataset: int = typer.Argument(...),
    out: Path | None = typer.Option(None, "--out", help="file or folder (default: here)"),
) -> None:
    """Download a dataset's file as it was uploaded (its sha256 checked)."""
    with client(timeout=600) as c:
        d = c.dataset(dataset)
        path = c.download_dataset(d, out if out is not None else Path.cwd())
    assert isinstance(path, Path)  # written to a file: its path
    digest = hashlib.sha256()
    with Path(path).open("rb") as f:
        while chunk := f.read(1 << 20):
            digest.update(chunk)
    if digest.hexdigest() != d.sha256:
        Path(path).unlink(missing_ok=True)
        raise CliError(f"dataset {dataset}: the download's sha256 is not the dataset's")
    typer.echo(f"wrote {path} ({d.size_bytes} bytes, sha256 {d.sha256[:12]} checked)")


def model(
    job: int = typer.Argument(...),
    cell: str | None = typer.Option(
        None, help="system=S,sigma_w=W,N=50,estimator=svr,gamma=0.05,rep=0 (enough to pick one)"
    ),
    format: str = typer.Option("npz", "--format", help="json, npz or mat"),
    out: Path | None = typer.Option(None, "--out", help="file or folder (default: here)"),
) -> None:
    """Export one cell of a job as a model file (A_hat, B_hat, C, radii, eps, L, K,
    delta, sigma_w and the provenance)."""
    if format not in ("json", "npz", "mat"):
        raise CliError("--format must be json, npz or mat")
    with client(timeout=120) as c:
        try:
            path = c.download_model(job, cell, format=format, out=out or Path.cwd())
            assert isinstance(path, Path)  # written to a file: its path
        except ValidationError as exc:
            raise CliError(plain_message(exc)) from None
    typer.echo(f"wrote {path}")


def validation(
    job: int = typer.Argument(...),
    out: Path | None = typer.Option(None, "--out", help="write the JSON to this file"),
) -> None:
    """A dataset job's validation: each estimator's fit (on the first max(N) training
    rollouts) on the held-out rollouts, the whiteness and cross-correlation tests, the
    excitation of the training data (the dataset's page shows that of all its rollouts)."""
    with client(timeout=120) as c:
        body = c.validation(job)
    if out is not None:
        write_atomic(out, writer(json.dumps(body, indent=1).encode()))
        return typer.echo(f"wrote {out}")
    for m in body["models"]:
        gamma = "" if m["gamma"] is None else f" gamma={m['gamma']:g}"
        v = m["validation"]
        if v is None:
            typer.echo(f"{m['estimator']}{gamma}: no held-out rollouts")
            continue
        fits = ", ".join(f"{ch} {_pct(f)}" for ch, f in zip(v["channels"], v["one_step_fit"]))
        lb = ", ".join(_p(p) for p in v["ljung_box_p"])
        typer.echo(f"{m['estimator']}{gamma}: one-step fit {fits}; Ljung-Box p {lb}")
    ex = body["excitation"]
    lam = _g(ex["lambda_min"], null="none")  # none: beyond the double range (a note says so)
    typer.echo(
        f"excitation of the {body['N']} training rollouts ({ex['N0']} transitions): "
        f"lambda_min {lam}, condition number {_g(ex['cond'])}"
    )
    for note in ex["notes"] + body["notes"]:
        typer.echo(f"note: {note}")


def _pct(v) -> str:
    return "null" if v is None else f"{v:.1f} %"


def _p(v) -> str:
    return "null" if v is None else f"{v:.3g}"


def _g(v, null: str = "inf") -> str:
    return null if v is None else f"{v:.3g}"


def system_from_file(
    file: Path = typer.Argument(..., help="NPZ, .mat or JSON with A, B, optionally C"),
    name: str | None = typer.Option(None, help="the system's name (default: the file's)"),
) -> None:
    """Print a spec's custom system ({name, A, B, C, sigma_u, sigma_v}) read from a file."""
    _check_file(file)
    with client() as c:
        try:
            system = c.system_from_file(file, name=name)
        except ValidationError as exc:
            raise CliError(f"{file.name}: {plain_message(exc)}") from None
    print_json(system)
