"""One cell of a job as a model file: JSON, NPZ or MATLAB (docs/datasets.md#model-export).

The estimate (A_hat, B_hat), the output matrix C, the uncertainty set (radii_A,
radii_B, r_A, r_B, eps_A, eps_B), the certified gain L with g(L), the Kalman gain
K, delta and sigma_w, with the cell's coordinates and the provenance: the job's
id, spec and the version and commit that computed it, and the dataset it ran on
(sha256 of the upload and of its arrays, sample time, channel names) or null for
a simulated job. A null of the record is left out of NPZ and MAT files (and is
null in JSON); a non-finite matrix entry is NaN there.
"""

from __future__ import annotations

import importlib.metadata
import io
import json
import re

import numpy as np
from sqlalchemy.orm import Session

from service.db import cells
from service.db import datasets as dataset_store
from service.db.models import JOB_ACTIVE, Job
from svrobs_core import parse_spec
from svrobs_core.errors import SpecError
from svrobs_core.measured import SIGMA_W_ESTIMATED
from svrobs_core.records import json_value
from svrobs_core.systems import resolve_system

from .. import json_text
from ..errors import Conflict
from ..params import int32_problem, number_problem
from ..results import not_pruned
from .parsed import name_refused, printable, shown

FORMATS = ("json", "npz", "mat")
MEDIA_TYPES = {
    "json": "application/json",
    "npz": "application/octet-stream",
    "mat": "application/x-matlab-data",
}
MATRICES = ("A_hat", "B_hat", "C", "radii_A", "radii_B", "L", "K")
SCALARS = ("r_A", "r_B", "eps_A", "eps_B", "g_L", "delta", "sigma_w", "rho_upper_bound")
FLAGS = ("stable_certified", "certified", "sigma_w_estimated")
TEXTS = ("system", "estimator", "bounds_method", "notes")
COORDINATES = cells.CELL_COORDINATES
AMBIGUOUS_SHOWN = 1000  # cells looked at to say which coordinates still vary


def parse_cell(cell: str | dict | None) -> dict:
    """A cell's coordinates from ``system=S,sigma_w=W,N=50,estimator=svr,gamma=0.05,rep=0``
    (any subset; ``gamma=null`` for OLS) or a JSON object of them; SpecError('cell')."""
    if cell is None or cell == "":
        return {}
    if isinstance(cell, str) and cell.lstrip().startswith("{"):
        try:  # the object as its pairs: a coordinate given twice is refused below
            cell = json_text.loads(cell, object_pairs_hook=_Pairs)
        except ValueError:
            raise SpecError("cell", "not a JSON object of coordinates") from None
    if isinstance(cell, _Pairs):
        items = list(cell)
    elif isinstance(cell, str):
        items = []
        for part in cell.split(","):
            key, eq, value = part.partition("=")
            if not eq:
                raise SpecError("cell", f"{part.strip()!r} is not KEY=VALUE")
            items.append((key.strip(), value.strip()))
    elif isinstance(cell, dict):
        items = list(cell.items())
    else:
        raise SpecError("cell", "must be KEY=VALUE pairs or a JSON object")
    out: dict = {}
    for key, value in items:
        if key not in COORDINATES:
            raise SpecError("cell", f"unknown coordinate {key!r}; one of {', '.join(COORDINATES)}")
        if key in out:
            raise SpecError("cell", f"{key} given twice")
        out[key] = _coordinate(key, value)
    return out


class _Pairs(list):
    """A JSON object's (key, value) pairs, in order, duplicates kept."""


def _coordinate(key: str, value):
    text = value if isinstance(value, str) else json.dumps(value)
    if key in ("system", "estimator"):
        if not isinstance(value, str) or not value:
            raise SpecError("cell", f"{key} must be a name")
        if not printable(value):
            raise SpecError("cell", f"{key}: {name_refused(value)}")
        return value
    if key == "gamma" and (value is None or text.lower() in ("null", "none", "ols")):
        return None
    if key in ("N", "rep"):  # a 32-bit column: a larger integer would overflow the driver
        problem = int32_problem(text)
        if problem is not None:
            raise SpecError("cell", f"{key} {problem}, got {shown(text)}")
        return int(text)
    if number_problem(text) is not None:
        raise SpecError("cell", f"{key} must be a finite number, got {shown(text)}")
    return float(text)


def find_cell(session: Session, job: Job, cell: str | dict | None) -> dict:
    """The record of the job's one cell at ``cell``; SpecError('cell') when none or
    several match (naming the coordinates that still vary), Conflict('cell') when none
    matches and the job is queued or running (its cells are not all computed), Gone
    when retention dropped the job's cell rows (as for its results)."""
    coords = parse_cell(cell)
    not_pruned(job)
    keys = cells.matching_keys(session, job.id, coords, AMBIGUOUS_SHOWN)
    shown = ", ".join(f"{k}={'null' if v is None else v}" for k, v in coords.items()) or "any"
    if not keys:
        raise _no_cell(job, shown)
    if len(keys) > 1:
        varying = []
        for c in COORDINATES:
            values = list(dict.fromkeys(k[c] for k in keys))
            if len(values) > 1:
                listed = ", ".join("null" if v is None else str(v) for v in values[:5])
                varying.append(f"{c} ({listed}{', ...' if len(values) > 5 else ''})")
        many = f"{len(keys)}" if len(keys) < AMBIGUOUS_SHOWN else f"at least {len(keys)}"
        raise SpecError(
            "cell", f"{many} cells of job {job.id} have {shown}; give {'; '.join(varying)}"
        )
    record = cells.cell_record(session, job.id, keys[0])
    if record is None:  # deleted between the two reads
        raise SpecError("cell", f"no cell of job {job.id} has {shown}")
    return record


def _no_cell(job: Job, shown: str) -> Exception:
    """No computed cell of ``job`` has the coordinates ``shown``: a Conflict while the
    job is queued or running (the cell may come), else a SpecError naming ``cell``,
    with the job's status when it did not succeed."""
    done = f"{job.cells_done or 0} of {job.n_cells or 0} cells computed"
    if job.status in JOB_ACTIVE:
        return Conflict(
            f"job {job.id} is {job.status} ({done}): no computed cell has {shown} yet;"
            " export it once the job has computed it",
            field="cell",
        )
    if job.status in ("failed", "cancelled"):
        ended = "was cancelled" if job.status == "cancelled" else "failed"
        return SpecError("cell", f"no cell of job {job.id} has {shown} (it {ended} with {done})")
    return SpecError("cell", f"no cell of job {job.id} has {shown}")


def _output_matrix(spec: dict, system: str, n: int, dataset: dict | None):
    """C of the cell: the spec's system's (a simulated job), or for a job on a dataset
    the spec's ``C`` or its default (I, or the rows that pick y_k of the ARX state),
    else the identity (every state measured)."""
    for i, s in enumerate(spec.get("systems") or []):
        resolved = resolve_system(s, field=f"systems[{i}]")
        if resolved.name == system:
            return resolved.C.tolist()
    if spec.get("dataset") is not None and dataset is not None:
        measured = parse_spec(spec).measured
        return measured.C_matrix(dataset["n"], dataset["m"]).tolist()
    return np.eye(n).tolist()


def _version() -> str | None:
    try:
        return importlib.metadata.version("svrobs")
    except importlib.metadata.PackageNotFoundError:  # pragma: no cover
        return None


def model_payload(record: dict, *, job: Job, dataset: dict | None) -> dict:
    """The export's content: record fields, C, delta and the provenance (JSON values)."""
    spec = job.spec or {}
    A = record.get("A_hat")
    n = len(A) if A is not None else 0
    out = {"format": "svrobs-model", "format_version": 1}
    out.update({c: record.get(c) for c in COORDINATES})
    for f in MATRICES:
        out[f] = _output_matrix(spec, record["system"], n, dataset) if f == "C" else record.get(f)
    out.update({f: record.get(f) for f in SCALARS if f != "delta"})
    out["delta"] = spec.get("delta")
    out.update({f: record.get(f) for f in FLAGS + TEXTS[2:]})
    # a dataset job's sigma_w "estimate": the key -1 is no level (the note has the
    # estimate and its upper bound, docs/measured.md#records)
    out["sigma_w_estimated"] = bool(
        spec.get("dataset") is not None and record.get("sigma_w") == SIGMA_W_ESTIMATED
    )
    if out["sigma_w_estimated"]:
        out["sigma_w"] = None
    out["sample_time"] = dataset["sample_time"] if dataset else None
    prov = job.provenance or {}
    out["provenance"] = {
        "job_id": job.id,
        "spec": spec,
        "version": prov.get("version"),
        "git_commit": prov.get("git_commit"),
        "exported_by": f"svrobs {_version()}",
        "dataset": None
        if dataset is None
        else {
            k: dataset[k]
            for k in ("id", "name", "sha256", "arrays_sha256", "sample_time")
            + ("state_names", "input_names")
        },
    }
    return json_value(out)


def _arrays(payload: dict) -> dict:
    """The payload as named arrays for NPZ / MAT (nulls left out)."""
    out: dict = {}
    for f in MATRICES:
        if payload.get(f) is not None:
            out[f] = np.array(payload[f], dtype=np.float64)  # None entries -> NaN
    for f in SCALARS + ("N", "rep", "gamma", "sample_time"):
        if payload.get(f) is not None:
            out[f] = np.float64(payload[f])
    for f in FLAGS:
        if payload.get(f) is not None:
            out[f] = np.bool_(payload[f])
    for f in TEXTS:
        if payload.get(f) is not None:
            out[f] = np.str_(payload[f])
    out["provenance"] = np.str_(json.dumps(payload["provenance"], sort_keys=True))
    return out


def encode_model(payload: dict, fmt: str) -> bytes:
    """The payload as a JSON, NPZ or MAT (v5) file's bytes."""
    if fmt == "json":
        return json.dumps(payload, indent=1, allow_nan=False).encode()
    buf = io.BytesIO()
    if fmt == "npz":
        np.savez(buf, **_arrays(payload))
    elif fmt == "mat":
        import scipy.io

        scipy.io.savemat(buf, _arrays(payload), do_compression=True)
    else:
        raise SpecError("format", f"must be one of {', '.join(FORMATS)}, got {fmt!r}")
    return buf.getvalue()


def export_model(session: Session, job: Job, *, cell, fmt: str) -> tuple[bytes, str, str]:
    """(bytes, media type, file name) of the job's cell at ``cell`` in ``fmt``."""
    if fmt not in FORMATS:
        raise SpecError("format", f"must be one of {', '.join(FORMATS)}, got {fmt!r}")
    record = find_cell(session, job, cell)
    dataset = None
    if job.dataset_id is not None:
        row = dataset_store.team_dataset(session, job.team_id, job.dataset_id)
        dataset = dataset_store.dataset_meta(row) if row is not None else None
    payload = model_payload(record, job=job, dataset=dataset)
    gamma = "" if record.get("gamma") is None else f"-g{record['gamma']:g}"
    stem = f"job-{job.id}-{record['system']}-N{record['N']}-{record['estimator']}{gamma}"
    stem = re.sub(r"[^A-Za-z0-9._-]+", "_", f"{stem}-rep{record['rep']}")
    return encode_model(payload, fmt), MEDIA_TYPES[fmt], f"{stem}.{fmt}"
