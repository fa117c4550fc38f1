"""Datasets in the database (docs/datasets.md#storage): the row, the original bytes and
the float64 arrays in chunks of at most :data:`CHUNK_BYTES`, so that a worker on any
host reads them without a shared filesystem and without parsing the file again.

The arrays are stored as every X_i, then every U_i, little-endian float64,
row-major; the shapes come from the row (n, m, lengths). :func:`load_arrays` reads
them into one buffer and returns views of it. Every function takes an open
session and never commits.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable, Iterator

import numpy as np
from sqlalchemy import delete, func, insert, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, defer, joinedload

from svrobs_core.measured import check_against_data
from svrobs_core.workload import DataShape
from svrobs_lab.errors import DatasetInUse, DatasetNotFound, DatasetScheduled, NotFound

from .models import Dataset, DatasetChunk, Job, Schedule

CHUNK_BYTES = 1 << 20
DTYPE = np.dtype("<f8")
CHUNKS = DatasetChunk.__table__
# how many job ids a DatasetInUse message names (svrobs_lab.errors)
NAMED_JOBS = 20


def team_dataset(session: Session, team_id: int | None, dataset_id: int) -> Dataset | None:
    """The dataset if it exists (and belongs to ``team_id`` when given), else None."""
    q = select(Dataset).where(Dataset.id == dataset_id)
    if team_id is not None:
        q = q.where(Dataset.team_id == team_id)
    return session.scalar(q)


def spec_dataset_id(spec: dict) -> int | None:
    """The dataset id a job spec names (``"dataset": ID``), or None."""
    value = spec.get("dataset") if isinstance(spec, dict) else None
    if isinstance(value, dict):  # a normalised spec may keep it as {"id": ...}
        value = value.get("id")
    return value if isinstance(value, int) and not isinstance(value, bool) else None


def linked_dataset(session: Session, team_id: int, spec, field: str = "dataset") -> int | None:
    """The id of the team's dataset a job spec runs on (None for a simulated spec):
    :func:`spec_data`'s id."""
    return spec_data(session, team_id, spec, field)[0]


def spec_data(
    session: Session, team_id: int, spec, field: str = "dataset"
) -> tuple[int | None, DataShape | None]:
    """(id, shape) of the team's dataset a job spec runs on ((None, None) for a
    simulated spec); DatasetNotFound naming ``field`` when the team has no such
    dataset. ``spec``: the spec dict, or the parsed
    :class:`~svrobs_core.spec.ExperimentSpec`, whose checks that need the data's
    shape (N and holdout against the rollouts, the ARX lags against their lengths:
    ``svrobs_core.measured.check_against_data``) then run too, raising SpecError
    naming the spec field."""
    parsed = None if isinstance(spec, dict) else spec
    dataset_id = spec_dataset_id(spec) if parsed is None else parsed.dataset
    if dataset_id is None:
        return None, None
    shape = dataset_shape(session, dataset_id, team_id)
    if shape is None:
        raise DatasetNotFound(dataset_id, field)
    if parsed is not None:
        check_against_data(
            parsed, shape.n, shape.m, len(shape.lengths), lengths=list(shape.lengths)
        )
    return dataset_id, shape


def dataset_shape(
    session: Session, dataset_id: int, team_id: int | None = None
) -> DataShape | None:
    """n, m and every rollout's length of a stored dataset (of ``team_id``'s when
    given), or None."""
    q = select(Dataset.n, Dataset.m, Dataset.lengths).where(Dataset.id == dataset_id)
    if team_id is not None:
        q = q.where(Dataset.team_id == team_id)
    row = session.execute(q).first()
    if row is None:
        return None
    return DataShape(n=row.n, m=row.m, lengths=tuple(int(t) for t in row.lengths))


def list_datasets(
    session: Session, team_id: int, *, limit: int, offset: int
) -> tuple[list[Dataset], int]:
    """The team's datasets, newest first (without their lengths and statistics), and
    how many the team has."""
    q = select(Dataset).where(Dataset.team_id == team_id)
    total = session.scalar(select(func.count()).select_from(q.subquery())) or 0
    page = q.options(
        defer(Dataset.lengths),
        defer(Dataset.stats),
        defer(Dataset.excitation),
        joinedload(Dataset.user),
    )
    rows = session.scalars(page.order_by(Dataset.id.desc()).limit(limit).offset(offset)).all()
    return list(rows), total


def array_values(n, m, rollouts, samples):
    """How many numbers a dataset's arrays hold: every X_i of T_i + 1 states and every
    U_i of T_i inputs (``samples`` = the sum of the T_i). Numbers or columns alike."""
    return samples * (n + m) + rollouts * n


def stored_bytes(n: int, m: int, rollouts: int, samples: int, size_bytes: int) -> int:
    """What a dataset holds in the store: its upload's bytes and its float64 arrays."""
    return size_bytes + DTYPE.itemsize * array_values(n, m, rollouts, samples)


def team_usage(session: Session, team_id: int) -> tuple[int, int]:
    """(how many datasets the team has, the bytes they hold: :func:`stored_bytes`)."""
    d = Dataset
    held = d.size_bytes + DTYPE.itemsize * array_values(d.n, d.m, d.rollouts, d.samples)
    q = select(func.count(), func.coalesce(func.sum(held), 0)).where(d.team_id == team_id)
    count, total = session.execute(q).one()
    return int(count), int(total)


def add_dataset(session: Session, **values) -> Dataset:
    row = Dataset(**values)
    session.add(row)
    session.flush()
    return row


def add_chunks(session: Session, dataset_id: int, part: str, chunks: Iterable[bytes]) -> int:
    """Insert ``chunks`` (each at most CHUNK_BYTES) in order, one statement per chunk
    (never more than one chunk in flight); returns how many."""
    seq = 0
    for seq, data in enumerate(chunks, start=1):
        session.execute(
            insert(CHUNKS), {"dataset_id": dataset_id, "part": part, "seq": seq - 1, "data": data}
        )
    return seq


def array_chunks(arrays: Iterable[np.ndarray], size: int = CHUNK_BYTES) -> Iterator[bytes]:
    """The arrays' little-endian float64 bytes, row-major, back to back, in pieces of
    ``size`` bytes (the last one shorter)."""
    buf = bytearray()
    for a in arrays:
        view = _bytes_view(a)
        while len(view):
            take = size - len(buf)
            buf += view[:take]
            view = view[take:]
            if len(buf) == size:
                yield bytes(buf)
                buf.clear()
    if buf:
        yield bytes(buf)


def arrays_digest(arrays: Iterable[np.ndarray]) -> str:
    """sha256 of :func:`array_chunks` of the arrays: equal for equal data in any format."""
    h = hashlib.sha256()
    for a in arrays:
        h.update(_bytes_view(a))
    return h.hexdigest()


def _bytes_view(a: np.ndarray) -> memoryview:
    """The array's little-endian float64 bytes, row-major (no copy when it is already)."""
    flat = np.ascontiguousarray(a, dtype=DTYPE).reshape(-1)
    return flat.data.cast("B")


def iter_chunks(session: Session, dataset_id: int, part: str = "file") -> Iterator[bytes]:
    """The stored bytes of one part, chunk by chunk (one chunk read at a time)."""
    for seq in chunk_seqs(session, dataset_id, part):
        yield read_chunk(session, dataset_id, part, seq)


def chunk_seqs(session: Session, dataset_id: int, part: str = "file") -> list[int]:
    """The numbers of the stored chunks of one part, in order."""
    c = CHUNKS.c
    q = select(c.seq).where(c.dataset_id == dataset_id, c.part == part).order_by(c.seq)
    return list(session.scalars(q))


def read_chunk(session: Session, dataset_id: int, part: str, seq: int) -> bytes:
    """One stored chunk (NotFound when the dataset was deleted since it was listed)."""
    c = CHUNKS.c
    data = session.scalar(
        select(c.data).where(c.dataset_id == dataset_id, c.part == part, c.seq == seq)
    )
    if data is None:
        raise NotFound(f"dataset {dataset_id} was deleted while it was read")
    return data


def dataset_meta(row: Dataset) -> dict:
    """What a worker needs beside the arrays."""
    return {
        "id": row.id,
        "name": row.name,
        "format": row.format,
        "sha256": row.sha256,
        "arrays_sha256": row.arrays_sha256,
        "n": row.n,
        "m": row.m,
        "rollouts": row.rollouts,
        "lengths": list(row.lengths),
        "sample_time": row.sample_time,
        "state_names": list(row.state_names),
        "input_names": list(row.input_names),
        "stats": row.stats,
    }


def load_arrays(
    session: Session, dataset_id: int, team_id: int | None = None
) -> tuple[list[np.ndarray], list[np.ndarray], dict]:
    """``(X_list, U_list, meta)`` of a stored dataset: X_i (T_i+1, n) and U_i (T_i, m)
    float64, views of one buffer read from the chunks (no file parsed). DatasetNotFound
    when it does not exist (or is not ``team_id``'s)."""
    row = team_dataset(session, team_id, dataset_id)
    if row is None:
        raise DatasetNotFound(dataset_id)
    lengths = np.asarray(row.lengths, dtype=np.int64)
    n, m = row.n, row.m
    nx = int((lengths + 1).sum()) * n
    nu = int(lengths.sum()) * m
    buf = bytearray((nx + nu) * DTYPE.itemsize)
    at = 0
    for data in iter_chunks(session, dataset_id, "arrays"):
        if at + len(data) > len(buf):
            break
        buf[at : at + len(data)] = data
        at += len(data)
    if at != len(buf):
        raise ValueError(f"stored arrays of dataset {dataset_id} hold {at} bytes, not {len(buf)}")
    flat = np.frombuffer(buf, dtype=DTYPE)
    X_all = flat[:nx].reshape(-1, n)
    U_all = flat[nx:].reshape(-1, m) if m else np.zeros((int(lengths.sum()), 0))
    X = np.split(X_all, np.cumsum(lengths + 1)[:-1])
    U = np.split(U_all, np.cumsum(lengths)[:-1])
    return X, U, dataset_meta(row)


def _byte_ranges(session: Session, dataset_id: int, ranges: list[tuple[int, int]]) -> list[bytes]:
    """Bytes ``start:stop`` of a dataset's stored arrays for each range, reading each
    chunk they fall in once, in one query."""
    spans = [(a // CHUNK_BYTES, max(a, b - 1) // CHUNK_BYTES) for a, b in ranges if b > a]
    seqs = sorted({s for first, last in spans for s in range(first, last + 1)})
    c = CHUNKS.c
    chunks = dict(
        session.execute(
            select(c.seq, c.data).where(
                c.dataset_id == dataset_id, c.part == "arrays", c.seq.in_(seqs)
            )
        ).all()
        if seqs
        else []
    )
    out = []
    for a, b in ranges:
        if b <= a:
            out.append(b"")
            continue
        first, last = a // CHUNK_BYTES, (b - 1) // CHUNK_BYTES
        data = b"".join(bytes(chunks[s]) for s in range(first, last + 1))
        out.append(data[a - first * CHUNK_BYTES : b - first * CHUNK_BYTES])
    return out


def load_rollouts(
    session: Session, dataset_id: int, count: int, *, max_steps: int | None = None
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The first ``count`` rollouts of a stored dataset, each cut to its first
    ``max_steps`` steps (X_i (min(T_i, max_steps) + 1, n), U_i (min(T_i, max_steps), m);
    None: whole), reading only the chunks that hold them (a page's plot of a large
    dataset). DatasetNotFound when it does not exist."""
    row = session.execute(
        select(Dataset.n, Dataset.m, Dataset.lengths).where(Dataset.id == dataset_id)
    ).first()
    if row is None:
        raise DatasetNotFound(dataset_id)
    lengths = np.asarray(row.lengths, dtype=np.int64)
    n, m, k = row.n, row.m, max(0, min(int(count), len(lengths)))
    size = DTYPE.itemsize
    # where each X_i and U_i starts: every X_i, then every U_i
    x_starts = np.concatenate([[0], np.cumsum((lengths[:k] + 1) * n)])[:k] * size
    u_part = int((lengths + 1).sum()) * n * size
    u_starts = u_part + np.concatenate([[0], np.cumsum(lengths[:k] * m)])[:k] * size
    steps = (lengths[:k] if max_steps is None else np.minimum(lengths[:k], max_steps)).tolist()
    x_ranges = [(a, a + (t + 1) * n * size) for a, t in zip(x_starts.tolist(), steps)]
    u_ranges = [(a, a + t * m * size) for a, t in zip(u_starts.tolist(), steps)]
    data = _byte_ranges(session, dataset_id, x_ranges + u_ranges)
    X = [np.frombuffer(x, dtype=DTYPE).reshape(t + 1, n) for x, t in zip(data[:k], steps)]
    U = [np.frombuffer(u, dtype=DTYPE).reshape(t, m) for u, t in zip(data[k:], steps)]
    return X, U


def jobs_using(session: Session, dataset_id: int) -> tuple[list[int], int]:
    """(the first NAMED_JOBS ids of the jobs on the dataset, how many there are)."""
    ids = session.scalars(
        select(Job.id).where(Job.dataset_id == dataset_id).order_by(Job.id).limit(NAMED_JOBS)
    ).all()
    total = session.scalar(select(func.count(Job.id)).where(Job.dataset_id == dataset_id))
    return list(ids), total or 0


def schedules_naming(session: Session, team_id: int, dataset_id: int) -> list[str]:
    """The names of the team's schedules whose template runs on the dataset."""
    rows = session.execute(
        select(Schedule.name, Schedule.spec_template)
        .where(Schedule.team_id == team_id)
        .order_by(Schedule.name)
    ).all()
    return [name for name, template in rows if spec_dataset_id(template) == dataset_id]


def delete_dataset(session: Session, row: Dataset) -> None:
    """Delete the dataset and its chunks; DatasetInUse while jobs refer to it (also
    when a job referring to it is created concurrently: the foreign key refuses) or
    a schedule's template names it (its next run would find no data)."""
    ids, total = jobs_using(session, row.id)
    if total:
        raise DatasetInUse(row.id, ids, total)
    scheduled = schedules_naming(session, row.team_id, row.id)
    if scheduled:
        raise DatasetScheduled(row.id, scheduled)
    dataset_id = row.id
    try:
        with session.begin_nested():
            session.execute(delete(DatasetChunk).where(DatasetChunk.dataset_id == dataset_id))
            session.execute(delete(Dataset).where(Dataset.id == dataset_id))
    except IntegrityError:
        ids, total = jobs_using(session, dataset_id)
        raise DatasetInUse(dataset_id, ids, total) from None
    session.expunge(row)
