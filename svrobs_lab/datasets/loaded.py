"""A stored dataset as the core's :class:`~svrobs_core.measured.MeasuredData`, read from
its float64 chunks (``service.db.datasets.load_arrays``: no file is parsed again).

A worker keeps the last dataset it read (``cache=True``), checked by the sha256 of its
arrays, so that the units of one job read it once per process."""

from __future__ import annotations

import os
import threading

from sqlalchemy.orm import Session

from service.db.datasets import load_arrays
from service.db.validations import dataset_digest
from svrobs_core.measured import MeasuredData

from ..errors import DatasetNotFound

_last: dict[tuple[int, str], MeasuredData] = {}
_lock = threading.Lock()


def measured_data(session: Session, dataset_id: int, *, cache: bool = False) -> MeasuredData:
    """The dataset's rollouts (the caller checked that it may read them);
    DatasetNotFound if there is none. ``cache``: keep it for the next call of this
    process."""
    digest = dataset_digest(session, dataset_id)
    if digest is None:
        raise DatasetNotFound(dataset_id)
    key = (dataset_id, digest)
    with _lock:
        hit = _last.get(key)
    if hit is not None:
        return hit
    X, U, meta = load_arrays(session, dataset_id)
    data = MeasuredData(
        X=X,
        U=U,
        sample_time=meta["sample_time"],
        state_names=tuple(meta["state_names"]),
        input_names=tuple(meta["input_names"]),
    )
    if cache:
        with _lock:
            _last.clear()
            _last[key] = data
    return data


def file_data(path, *, max_bytes: int) -> MeasuredData:
    """A dataset file read as an upload is (any format of docs/datasets.md#formats,
    the default column convention), for a local run; BadDatasetFile naming what is
    wrong with it."""
    from .reader import parse_dataset

    with open(path, "rb") as f:
        parsed = parse_dataset(f, filename=os.path.basename(str(path)), max_bytes=max_bytes)
    return MeasuredData(
        X=list(parsed.X),
        U=list(parsed.U),
        sample_time=parsed.sample_time,
        state_names=tuple(parsed.state_names),
        input_names=tuple(parsed.input_names),
    )
