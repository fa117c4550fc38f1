"""The client's dataset, model-export and system-file calls (docs/client.md#datasets),
mixed into :class:`svrobs_client.Client`.

A dataset is uploaded from a file path (streamed), from arrays ``(X, U)`` (sent as
an NPZ) or from a pandas DataFrame in long form (sent as CSV). A job cell's model
comes back as a :class:`Model` of numpy arrays, or as a ``control.StateSpace`` when
python-control is installed (:meth:`DatasetCalls.model`). numpy is needed only
for arrays.
"""

from __future__ import annotations

import io
import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from .files import write_atomic
from .models import Dataset, DatasetPage, answer, ident

MODEL_FORMATS = ("json", "npz", "mat")
_MATRICES = ("A_hat", "B_hat", "C", "radii_A", "radii_B", "L", "K")


def _names(value: str | Sequence[str] | None) -> str | None:
    """A list form field: comma-separated, or a JSON list when a name holds a comma."""
    if value is None or isinstance(value, str):
        return value
    names = [str(v) for v in value]
    return json.dumps(names) if any("," in v for v in names) else ",".join(names)


def _npz_of_arrays(X: Any, U: Any) -> bytes:
    """(X, U) as an NPZ of X_0, U_0, ... (rollouts may differ in length; U None: m = 0)."""
    import numpy as np

    xs = list(X) if not hasattr(X, "ndim") or X.ndim == 3 else [X]
    arrays: dict[str, Any] = {f"X_{i}": np.asarray(x, dtype=np.float64) for i, x in enumerate(xs)}
    if U is not None:
        us = list(U) if not hasattr(U, "ndim") or U.ndim == 3 else [U]
        if len(us) != len(xs):
            raise ValueError(f"U has {len(us)} rollouts and X {len(xs)}")
        arrays.update({f"U_{i}": np.asarray(u, dtype=np.float64) for i, u in enumerate(us)})
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def _is_frame(obj: object) -> bool:
    return type(obj).__name__ == "DataFrame" and hasattr(obj, "to_csv")


@dataclass(frozen=True)
class Model:
    """One job cell exported (``GET /jobs/{id}/model``): ``arrays`` holds A_hat, B_hat,
    C, radii_A, radii_B, L and K (those the cell has) as numpy arrays; ``values`` the
    scalars (r_A, r_B, eps_A, eps_B, g_L, delta, sigma_w, ...) and texts; the cell's
    ``provenance`` (job, spec, version, dataset sha256)."""

    arrays: dict[str, Any] = field(repr=False)
    values: dict[str, Any]
    provenance: dict[str, Any] = field(repr=False)

    def __getitem__(self, name: str) -> Any:
        return self.arrays[name] if name in self.arrays else self.values[name]

    @property
    def sample_time(self) -> float | None:
        value: float | None = self.values.get("sample_time")
        return value

    def to_statespace(self) -> Any:
        """``control.StateSpace(A_hat, B_hat, C, 0, dt)``: dt the dataset's sample time
        (``True``, a discrete system of unknown step, when there is none), states and
        inputs named after the dataset's channels. Needs python-control."""
        import control
        import numpy as np

        A, B, C = self.arrays["A_hat"], self.arrays["B_hat"], self.arrays["C"]
        dataset = self.provenance.get("dataset") or {}
        names: dict[str, list[str]] = {}
        if dataset.get("state_names") and len(dataset["state_names"]) == A.shape[0]:
            names["states"] = list(dataset["state_names"])
        if dataset.get("input_names") and len(dataset["input_names"]) == B.shape[1]:
            names["inputs"] = list(dataset["input_names"])
        dt = self.sample_time if self.sample_time else True
        return control.ss(A, B, C, np.zeros((C.shape[0], B.shape[1])), dt=dt, **names)


class DatasetCalls:
    """Datasets, model exports and system files (methods of :class:`Client`)."""

    request: Any  # Client.request
    request_json: Any
    _stream: Any

    # ------------------------------------------------------------------ datasets
    def upload_dataset(
        self,
        source: Any,
        *,
        name: str,
        description: str | None = None,
        sample_time: float | None = None,
        state_columns: str | Sequence[str] | None = None,
        input_columns: str | Sequence[str] | None = None,
        state_names: str | Sequence[str] | None = None,
        input_names: str | Sequence[str] | None = None,
        filename: str | None = None,
        timeout: float = 600.0,
    ) -> Dataset:
        """Upload a dataset: ``source`` is a file path (CSV, NPZ, .mat v5/v7.3, JSON;
        streamed), a binary file object, arrays ``(X, U)`` (X of shape (N, T+1, n) or a
        list of (T_i+1, n) arrays; U likewise, or None for no inputs; sent as NPZ) or a
        pandas DataFrame in long form (columns rollout, k, x1.., u1..; sent as CSV).
        ``state_columns`` / ``input_columns`` name the CSV columns; ``state_names`` /
        ``input_names`` the channels of the other formats. A bad file raises
        :class:`ValidationError` naming the row, column or variable."""
        fields = {
            "name": name,
            "description": description,
            "sample_time": None if sample_time is None else repr(float(sample_time)),
            "state_columns": _names(state_columns),
            "input_columns": _names(input_columns),
            "state_names": _names(state_names),
            "input_names": _names(input_names),
        }
        data = {k: v for k, v in fields.items() if v is not None}
        if isinstance(source, (str, os.PathLike)):
            path = Path(source)
            with path.open("rb") as fh:
                files = {"file": (filename or path.name, fh, "application/octet-stream")}
                body = self.request_json(
                    "POST", "/datasets", files=files, data=data, timeout=timeout
                )
        else:
            if _is_frame(source):
                content, default = source.to_csv(index=False).encode(), "dataset.csv"
            elif hasattr(source, "read"):
                content, default = source, "dataset"
            elif isinstance(source, tuple) and len(source) == 2:
                content, default = _npz_of_arrays(*source), "dataset.npz"
            else:
                raise TypeError(
                    "source is a path, a binary file, (X, U) arrays or a pandas DataFrame, "
                    f"not {type(source).__name__}"
                )
            files = {"file": (filename or default, content, "application/octet-stream")}
            body = self.request_json("POST", "/datasets", files=files, data=data, timeout=timeout)
        return Dataset.from_json(body)

    def datasets(self, *, limit: int = 50, offset: int = 0) -> DatasetPage:
        """The team's datasets, newest first (without lengths and statistics)."""
        body = answer(
            self.request_json("GET", "/datasets", params={"limit": limit, "offset": offset}),
            "a page of datasets",
            rows="items",
            counts=("total", "limit", "offset"),
        )
        return DatasetPage(
            items=[Dataset.from_json(d) for d in body["items"]],
            total=body["total"],
            limit=body["limit"],
            offset=body["offset"],
        )

    def dataset(self, dataset: Dataset | int) -> Dataset:
        """One dataset with every rollout's length and the per-channel statistics."""
        return Dataset.from_json(self.request_json("GET", f"/datasets/{ident(dataset)}"))

    def delete_dataset(self, dataset: Dataset | int) -> None:
        """Delete a dataset; :class:`Conflict` (naming them) while jobs use it."""
        self.request("DELETE", f"/datasets/{ident(dataset)}")

    def download_dataset(
        self, dataset: Dataset | int, out: str | os.PathLike[str] | IO[bytes] | None = None
    ) -> bytes | Path | IO[bytes]:
        """The file as uploaded: its bytes, or written to ``out`` (a path, written whole
        or not at all; a folder: the upload's file name in it; a binary stream)."""
        return self._download(f"/datasets/{ident(dataset)}/file", {}, out)

    def _download(
        self, path: str, params: dict[str, Any], out: str | os.PathLike[str] | IO[bytes] | None
    ) -> bytes | Path | IO[bytes]:
        with self._stream(path, params, expect="attachment") as r:
            if out is None:
                data: bytes = r.read()
                return data
            if not isinstance(out, (str, os.PathLike)):  # a binary stream
                for chunk in r.iter_bytes():
                    out.write(chunk)
                return out
            target = Path(out)
            if target.is_dir():
                target = target / _filename(r.headers.get("content-disposition", ""), path)
            write_atomic(target, lambda f: [f.write(c) for c in r.iter_bytes()])
            return target

    # ------------------------------------------------------------------ models
    def download_model(
        self,
        job: object,
        cell: str | Mapping[str, Any] | None = None,
        *,
        format: str = "npz",
        out: str | os.PathLike[str] | IO[bytes] | None = None,
    ) -> bytes | Path | IO[bytes]:
        """One job cell's model file (``json``, ``npz`` or ``mat``): its bytes, or
        written to ``out``. ``cell``: coordinates that pick one cell,
        ``"system=S,N=50,estimator=svr,gamma=0.05,rep=0"`` or a dict (gamma None: ols)."""
        if format not in MODEL_FORMATS:
            raise ValueError(f"format must be one of {list(MODEL_FORMATS)}, got {format!r}")
        params: dict[str, Any] = {"format": format}
        if cell is not None:
            params["cell"] = cell if isinstance(cell, str) else json.dumps(dict(cell))
        return self._download(f"/jobs/{ident(job)}/model", params, out)

    def model_data(self, job: object, cell: str | Mapping[str, Any] | None = None) -> Model:
        """One job cell's model as numpy arrays (read from its NPZ export)."""
        import numpy as np

        raw = self.download_model(job, cell, format="npz")
        assert isinstance(raw, bytes)  # out=None: the bytes
        npz = np.load(io.BytesIO(raw), allow_pickle=False)
        arrays: dict[str, Any] = {}
        values: dict[str, Any] = {}
        for key in npz.files:
            a = npz[key]
            if key in _MATRICES:
                arrays[key] = a
            elif a.dtype.kind == "U":
                values[key] = str(a)
            elif a.dtype.kind == "b":
                values[key] = bool(a)
            else:
                values[key] = float(a)
        provenance = json.loads(values.pop("provenance"))
        for key in ("N", "rep"):
            if key in values:
                values[key] = int(values[key])
        return Model(arrays=arrays, values=values, provenance=provenance)

    def model(self, job: object, cell: str | Mapping[str, Any] | None = None) -> Any:
        """One job cell's identified model: a ``control.StateSpace`` (A_hat, B_hat, C,
        D = 0, dt = the dataset's sample time) when python-control is installed, else
        the :class:`Model` of numpy arrays (radii, eps, L, K... are in
        :meth:`model_data`'s result either way)."""
        data = self.model_data(job, cell)
        try:
            import control  # noqa: F401
        except ImportError:
            return data
        return data.to_statespace()

    def validation(self, job: object) -> dict[str, Any]:
        """A dataset job's validation on its held-out rollouts, as the API sends it
        (``GET /jobs/{id}/validation``): per estimator and gamma the fitted model, the
        fit, whiteness and cross-correlation statistics; the excitation check."""
        body: dict[str, Any] = self.request_json("GET", f"/jobs/{ident(job)}/validation")
        return body

    # ------------------------------------------------------------------ systems
    def system_from_file(
        self, path: str | os.PathLike[str], *, name: str | None = None
    ) -> dict[str, Any]:
        """A spec's custom system (``{name, A, B, C, sigma_u, sigma_v}``) from an NPZ,
        .mat or JSON file holding A, B and optionally C, sigma_u, sigma_v; checked by
        the server as a spec's system is."""
        path = Path(path)
        with path.open("rb") as fh:
            files = {"file": (path.name, fh, "application/octet-stream")}
            data = {"name": name} if name else {}
            system: dict[str, Any] = self.request_json(
                "POST", "/systems/from-file", files=files, data=data
            )
            return system


def _filename(disposition: str, path: str) -> str:
    """The file name of a Content-Disposition (the ASCII one), else the path's last part."""
    for part in disposition.split(";"):
        key, _, value = part.strip().partition("=")
        if key == "filename" and value:
            name = os.path.basename(value.strip('"'))
            if name:
                return name
    return path.rstrip("/").rsplit("/", 1)[-1]
