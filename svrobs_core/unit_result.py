"""The records of one work unit as column arrays (docs/spec.md#record-fields).

A unit's results are kept as column arrays (:class:`UnitResult`), one array
per record field over the (repetition, estimator/gamma) grid of each N.
From them ``records()`` builds the record dicts, ``json_lines()`` the
same records as JSON text (identical to ``json.dumps(record)``, built per
field rather than per record) and ``columns()`` the arrays a report reads,
so a large run never has to go through one dict per cell.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import repeat
from typing import Any, cast

import numpy as np
from numpy.typing import ArrayLike

from .array_types import Array, IntArray
from .float_text import json_texts
from .notes import Notes
from .observer_stages import mc_note
from .planning import EstimatorAxis
from .records import (
    CELL_FIELDS,
    COLUMN_MATRIX_FIELDS,
    GROUP_FIELDS,
    MATRIX_FIELDS,
    RECORD_FIELDS,
    SCALAR_FIELDS,
    SUMMARY_FIELDS,
    TEXT_FIELDS,
    json_value,
)


def _flat(arr: ArrayLike, RE: int) -> Array:
    arr = np.asarray(arr)
    return arr.reshape((RE,) + arr.shape[2:])


def _values(arr: ArrayLike, RE: int) -> list[Any]:
    """An (R, E, ...) field -> one plain value per cell (NaN/inf -> None), cell order."""
    return _flat_values(_flat(arr, RE))


def _flat_values(arr: Array) -> list[Any]:
    """:func:`_values` of a field already flat: (cells, ...)."""
    out: list[Any]
    if arr.dtype == object or arr.dtype == bool:
        out = arr.tolist()
        return out
    arr = arr.astype(float, copy=False)
    finite = np.isfinite(arr)
    out = np.where(finite, arr, 0.0).tolist()
    bad = ~finite.reshape(len(arr), -1).all(axis=1)
    for i in np.flatnonzero(bad).tolist():
        out[i] = json_value(arr[i])
    return out


def _floats(arr: ArrayLike, RE: int) -> Array:
    """An (R, E) scalar field -> its RE values as floats in cell order, NaN where the
    record holds null (None, NaN or an infinity); booleans as 0/1."""
    flat = _flat(arr, RE)
    if flat.dtype == object:
        flat = np.array([np.nan if v is None else float(v) for v in flat.tolist()])
    x = flat.astype(float)
    return np.where(np.isfinite(x), x, np.nan)


def _broadcast_row(arr: ArrayLike) -> Array | None:
    """The (E, ...) row of an (R, E, ...) array that is constant along R (stride 0), else None."""
    arr = np.asarray(arr)
    if arr.ndim >= 1 and arr.shape[0] > 1 and arr.strides[0] == 0:
        first: Array = arr[0]
        return first
    return None


def _json_strings(arr: ArrayLike, RE: int) -> list[str]:
    """JSON text of each cell's value, exactly as ``json.dumps`` writes it."""
    arr = np.asarray(arr)
    row = _broadcast_row(arr)
    if row is not None:  # constant along the repetitions: encode one row, repeat it
        E: int = row.shape[0]
        return _json_strings(row[None], E) * (RE // E)
    arr = _flat(arr, RE)
    out: list[str]
    if arr.dtype == bool:
        if arr.ndim == 1:
            out = np.where(arr, "true", "false").tolist()
            return out
        return [json.dumps(row.tolist()) for row in arr]  # a boolean array per cell
    if arr.dtype == object:
        return [json.dumps(v, allow_nan=False) for v in arr.tolist()]
    arr = arr.astype(float, copy=False)
    if arr.size == 0:  # rows without entries: "[]" or "[[], ...]"
        return [json.dumps(json_value(a), allow_nan=False) for a in arr]
    # one orjson pass for the whole field (docs/performance.md#records-as-json-text)
    return json_texts(arr)


@dataclass
class Dataset:
    """One N of a unit: the fields over (reps, E) and their notes.

    ``N0``: the sample count, or one per repetition (measured rollouts of
    different lengths, docs/measured.md#data-model)."""

    N: int
    N0: int | Sequence[int] | IntArray
    fields: dict[str, Array | None]  # None: a field without a value
    note_entries: Notes

    def __post_init__(self) -> None:
        self.notes = self.note_entries.strings()  # object (R, E): str or None

    def n0_column(self, E: int) -> list[int] | None:
        """N0 of every record (repetition-major) when it varies by repetition, else None."""
        if np.ndim(self.N0) == 0:
            return None
        per_rep = cast("Sequence[int] | IntArray", self.N0)  # not 0-d: one per repetition
        return [int(v) for v in per_rep for _ in range(E)]


class UnitResult:
    """The records of one work unit as column arrays.

    ``records()`` -> record dicts; ``json_lines()`` -> the same records as
    JSON text, one string per record (``json.dumps(record)`` to the byte);
    ``columns(matrices)`` -> {field: array} for :class:`svrobs_core.report.Columns`.
    Record order: N ascending, then repetition, then estimator/gamma.
    """

    def __init__(
        self,
        *,
        system: str,
        system_idx: int,
        sigma_w: float,
        sigma_w_idx: int,
        reps: list[int],
        axis: EstimatorAxis,
        datasets: list[Dataset],
        mc_reps: int | None = None,
        n_reps: int | None = None,
    ):
        self.system = system
        self.system_idx = system_idx
        self.sigma_w = sigma_w
        self.sigma_w_idx = sigma_w_idx
        self.reps = list(reps)
        self.axis = axis
        self.datasets = datasets
        self.mc_reps = mc_reps  # the Monte Carlo limit these records were computed with
        self.n_reps = n_reps  # the spec's repetition count (mc_reps = None means all)
        self._strings: dict[
            tuple[Any, ...], list[str]
        ] = {}  # JSON text per (dataset, field[, limit])

    def with_mc_reps(self, mc_reps: int | None) -> UnitResult:
        """The records a spec with this ``mc_reps`` (and otherwise the same) gives.

        ``mc_reps`` changes only J_mc, J_mc_se and the note that says where
        they are null, so they are recomputed from this result when the new
        limit is not above the one it was computed with.
        """

        def lim(x: int | None) -> int:
            # n_reps is None only where neither result limits the Monte Carlo (equal)
            return cast(int, self.n_reps if x is None else x)

        if lim(mc_reps) == lim(self.mc_reps):
            return self
        if lim(mc_reps) > lim(self.mc_reps):
            raise ValueError(f"Monte Carlo was computed for rep < {lim(self.mc_reps)} only")
        rows = np.asarray(self.reps) < lim(mc_reps)
        datasets: list[Dataset] = []
        for ds in self.datasets:
            fields = dict(ds.fields)
            notes = ds.note_entries
            if "mc" in notes.tags:
                for f in ("J_mc", "J_mc_se"):
                    # the Monte Carlo fields hold values wherever its note is
                    fields[f] = np.where(rows[:, None], cast(Array, fields[f]), np.nan)
                notes = notes.replace("mc", ~rows[:, None], mc_note(lim(mc_reps)))
            datasets.append(Dataset(N=ds.N, N0=ds.N0, fields=fields, note_entries=notes))
        new = UnitResult(
            system=self.system,
            system_idx=self.system_idx,
            sigma_w=self.sigma_w,
            sigma_w_idx=self.sigma_w_idx,
            reps=self.reps,
            axis=self.axis,
            datasets=datasets,
            mc_reps=mc_reps,
            n_reps=self.n_reps,
        )
        new._strings = self._strings  # shared: the keys of J_mc, J_mc_se hold the limit
        return new

    def __len__(self) -> int:
        return len(self.reps) * len(self.axis.names) * len(self.datasets)

    # -- per-cell key columns -------------------------------------------------
    def _key_columns(self, ds: Dataset) -> dict[str, Any]:
        R, E = len(self.reps), len(self.axis.names)
        RE = R * E
        return {
            "system": repeat(self.system, RE),
            "sigma_w": repeat(self.sigma_w, RE),
            "N": repeat(ds.N, RE),
            "N0": ds.n0_column(E) or repeat(ds.N0, RE),
            "estimator": self.axis.names * R,
            "gamma": self.axis.gammas * R,
            "rep": [r for r in self.reps for _ in range(E)],
            "seed_key": [
                [self.system_idx, self.sigma_w_idx, ds.N, r] for r in self.reps for _ in range(E)
            ],
        }

    def value_columns(
        self,
        as_json: frozenset[str] | set[str] = frozenset(),
        omit: frozenset[str] | set[str] = frozenset(),
    ) -> dict[str, list[Any]]:
        """{field: one value per record, in record order} for every record field
        not in ``omit``: plain Python values (NaN/inf -> None), and for the fields in
        ``as_json`` their JSON text (as ``json.dumps`` writes it) instead. The
        columnar form the DB layer stores without building a dict per record."""
        R, E = len(self.reps), len(self.axis.names)
        RE = R * E
        out: dict[str, list[Any]] = {f: [] for f in RECORD_FIELDS if f not in omit}
        for ds in self.datasets:
            cols = self._key_columns(ds)
            if "seed_key" in as_json:
                cols["seed_key"] = self._seed_key_strings(ds)
            cols["notes"] = ds.notes.reshape(RE).tolist()
            for f, col in cols.items():
                if f in out:
                    out[f].extend(col)
        for f in CELL_FIELDS:
            if f in omit:
                continue
            if f not in as_json and (whole := self._whole_field(f, RE)) is not None:
                out[f] = _flat_values(whole)  # one pass over every dataset's cells
                continue
            for di, ds in enumerate(self.datasets):
                v = ds.fields.get(f)
                if v is None:
                    out[f].extend(repeat("null" if f in as_json else None, RE))
                elif f in as_json:
                    out[f].extend(self._json_strings(di, f, v, RE))
                else:
                    out[f].extend(_values(v, RE))
        return out

    def _whole_field(self, f: str, RE: int) -> Array | None:
        """A field's cells of every dataset as one flat array, when every dataset has
        it as an array of one dtype (so that :func:`_flat_values` of it is the
        datasets' values one after the other), else None."""
        arrs = [ds.fields.get(f) for ds in self.datasets]
        if len(arrs) < 2 or any(a is None for a in arrs):
            return None
        flats = [_flat(cast(ArrayLike, a), RE) for a in arrs]
        if len({(a.dtype, a.shape[1:]) for a in flats}) != 1:
            return None
        return np.concatenate(flats)

    def plain_fields(self) -> dict[str, str]:
        """{cell field: kind} of the one-value-per-cell fields whose
        :meth:`value_columns` values are plain by construction: ``"float"`` (a
        numeric array in every dataset that has the field: finite floats or None),
        ``"bool"`` (bool arrays: bools) or ``"none"`` (not computed: None). A field
        of object arrays, or of arrays of another kind or shape, is not listed."""
        kinds: dict[str, str] = {}
        for f in CELL_FIELDS:
            seen = set()
            for ds in self.datasets:
                v = ds.fields.get(f)
                if v is not None:
                    v = np.asarray(v)
                    seen.add(v.dtype.kind if v.ndim == 2 else "O")
            if not seen:
                kinds[f] = "none"
            elif seen <= set("fiu"):
                kinds[f] = "float"
            elif seen == {"b"}:
                kinds[f] = "bool"
        return kinds

    def summary_columns(self) -> dict[str, Any]:
        """{field: values in record order} of the group fields (lists) and the summary
        fields (float arrays, NaN where a record holds null): what
        :func:`~svrobs_core.records.summarize_columns` reads, built from the arrays
        without a Python value per cell (docs/spec.md#summaries)."""
        R, E = len(self.reps), len(self.axis.names)
        RE = R * E
        n = RE * len(self.datasets)
        out: dict[str, Any] = {
            "system": [self.system] * n,
            "sigma_w": [self.sigma_w] * n,
            "N": [ds.N for ds in self.datasets for _ in range(RE)],
            "estimator": self.axis.names * (R * len(self.datasets)),
            "gamma": self.axis.gammas * (R * len(self.datasets)),
        }
        assert tuple(out) == GROUP_FIELDS
        for f in SUMMARY_FIELDS:
            parts = [
                np.full(RE, np.nan) if (v := ds.fields.get(f)) is None else _floats(v, RE)
                for ds in self.datasets
            ]
            out[f] = np.concatenate(parts) if parts else np.empty(0)
        return out

    def matrix_blocks(self) -> list[dict[str, Array | None]]:
        """Per dataset (in :meth:`value_columns` order), each matrix field as one
        (records, rows, cols) float array in record order, or None where it was not
        computed (NaN/inf entries are the records' nulls)."""
        RE = len(self.reps) * len(self.axis.names)
        return [
            {f: None if (v := ds.fields.get(f)) is None else _flat(v, RE) for f in MATRIX_FIELDS}
            for ds in self.datasets
        ]

    def records(self) -> list[dict[str, Any]]:
        cols = self.value_columns()
        return [dict(zip(RECORD_FIELDS, vals)) for vals in zip(*(cols[f] for f in RECORD_FIELDS))]

    def _seed_key_strings(self, ds: Dataset) -> list[str]:
        E = len(self.axis.names)
        head = f"[{self.system_idx}, {self.sigma_w_idx}, {ds.N}, "
        return [t for r in self.reps for t in repeat(f"{head}{r}]", E)]

    def _json_strings(self, di: int, f: str, v: Array, RE: int) -> list[str]:
        """``_json_strings`` of a field, cached (J_mc and J_mc_se per Monte Carlo limit)."""
        key = (di, f, self.mc_reps) if f in ("J_mc", "J_mc_se") else (di, f)
        if key not in self._strings:
            self._strings[key] = _json_strings(v, RE)
        return self._strings[key]

    def json_lines(self) -> list[str]:
        """Each record as ``json.dumps(record, allow_nan=False)`` would write it."""
        R, E = len(self.reps), len(self.axis.names)
        RE = R * E
        lines: list[str] = []
        for di, ds in enumerate(self.datasets):
            const: dict[str, str] = {
                "system": json.dumps(self.system),
                "sigma_w": repr(float(self.sigma_w)),
                "N": str(int(ds.N)),
            }
            var: dict[str, list[str]] = {
                "estimator": [json.dumps(x) for x in self.axis.names] * R,
                "gamma": ["null" if g is None else repr(float(g)) for g in self.axis.gammas] * R,
                "rep": [t for r in self.reps for t in repeat(str(r), E)],
                "seed_key": self._seed_key_strings(ds),
            }
            n0 = ds.n0_column(E)
            if n0 is None:
                const["N0"] = str(int(cast(int, ds.N0)))  # n0_column None: one count
            else:
                var["N0"] = [str(v) for v in n0]
            for f in CELL_FIELDS:
                v = ds.fields.get(f)
                if v is None:
                    const[f] = "null"
                else:
                    var[f] = self._json_strings(di, f, v, RE)
            notes = ds.notes.reshape(RE).tolist()
            texts = {t: json.dumps(t) for t in dict.fromkeys(notes)}  # a few distinct
            var["notes"] = list(map(texts.__getitem__, notes))
            parts: list[str] = []
            order: list[list[str]] = []
            for f in RECORD_FIELDS:
                if f in var:
                    parts.append(f'"{f}": %s')
                    order.append(var[f])
                else:
                    parts.append(f'"{f}": ' + const[f].replace("%", "%%"))
            template = "{" + ", ".join(parts) + "}"
            lines += map(template.__mod__, zip(*order))
        return lines

    def columns(self, matrices: bool = True) -> dict[str, Array]:
        """{field: array over the unit's records} as :mod:`svrobs_core.report` reads them:
        numbers as float (NaN = null, booleans 0/1), text as object arrays,
        A_hat/B_hat as (k, n, .) floats if ``matrices``."""

        R, E = len(self.reps), len(self.axis.names)
        RE = R * E
        parts: dict[str, list[Array]] = {}

        def put(f: str, a: Array) -> None:
            parts.setdefault(f, []).append(a)

        gam = np.array([np.nan if g is None else g for g in self.axis.gammas], dtype=float)
        for ds in self.datasets:
            keys = {
                "sigma_w": np.full(RE, float(self.sigma_w)),
                "N": np.full(RE, float(ds.N)),
                "N0": np.asarray(ds.n0_column(E) or np.full(RE, ds.N0), dtype=float),
                "gamma": np.tile(gam, R),
                "rep": np.repeat(np.asarray(self.reps, dtype=float), E),
            }
            for f in SCALAR_FIELDS:
                if f in keys:
                    put(f, keys[f])
                    continue
                v = ds.fields.get(f)
                if v is None:
                    put(f, np.full(RE, np.nan))
                else:
                    a = _flat(v, RE)
                    if a.dtype == object:
                        a = np.array([np.nan if x is None else float(x) for x in a.tolist()])
                    put(f, np.where(np.isfinite(a), a, np.nan).astype(float))
            for f in TEXT_FIELDS:
                if f == "system":
                    col = np.full(RE, self.system, dtype=object)
                elif f == "estimator":
                    col = np.array(self.axis.names * R, dtype=object)
                elif f == "notes":
                    col = ds.notes.reshape(RE)
                else:
                    v = ds.fields.get(f)
                    col = (
                        np.full(RE, None, dtype=object)
                        if v is None
                        else np.asarray(_flat(v, RE), dtype=object)
                    )
                put(f, col)
            if matrices:
                for f in COLUMN_MATRIX_FIELDS:
                    v = ds.fields.get(f)
                    if v is not None:
                        a = _flat(v, RE).astype(float)
                        ok = np.isfinite(a).all(axis=(1, 2))  # (k,): a is (k, rows, cols)
                        # numpy stubs: all(axis=) may be a scalar; here (k,)
                        put(f, np.where(ok[:, None, None], a, np.nan))  # type: ignore[index]
        return {f: np.concatenate(v) for f, v in parts.items()}
