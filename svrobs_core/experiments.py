"""Grid -> work units -> section 10 records (SPEC sections 1-10).

``plan_units(spec)`` splits the grid into JSON-able work units (all
repetitions and gammas of one system, sigma_w and N; all N at once when
``reuse_gain`` couples them); ``run_unit(spec, unit)`` is the one pure
function a worker calls; ``run_spec`` runs every unit in process (or in
``n_jobs`` processes). Records do not depend on how the grid is split
(SPEC section 1).

A unit's results are kept as column arrays (:class:`UnitResult`), one array
per record field over the (repetition, estimator/gamma) grid of each N.
From them ``records()`` builds the section 10 dicts, ``json_lines()`` the
same records as JSON text (identical to ``json.dumps(record)``, built per
field rather than per record) and ``columns()`` the arrays a report reads,
so a large run never has to go through one dict per cell.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from itertools import repeat
from typing import Any

import numpy as np

from . import bounds as _bounds
from . import estimators as _est
from .records import MATRIX_FIELDS, RECORD_FIELDS, json_value
from .rollouts import gram_data, seed_key
from .spec import STAGES, ExperimentSpec

MAX_CELLS_PER_UNIT = 20_000
TARGET_CELLS_PER_UNIT = 2_000  # ~0.1-1 s of work: amortises a worker's per-unit cost


def plan_units(
    spec: ExperimentSpec,
    max_cells: int = MAX_CELLS_PER_UNIT,
    target_cells: int = TARGET_CELLS_PER_UNIT,
) -> list[dict]:
    """Work units ``{"system", "sigma_w", "N": [...], "reps": [start, stop]}``.

    Consecutive N values of one (system, sigma_w) are packed into a unit
    while it stays within ``target_cells`` (all N at once when ``reuse_gain``
    couples them); a single N over ``max_cells`` is split by repetitions.
    The records do not depend on the split.
    """
    per_N = spec.cells_per_rep * spec.reps
    if spec.reuse_gain:
        n_groups = [list(spec.N)]
    else:
        n_groups, group = [], []
        for N in sorted(spec.N):
            if group and per_N * (len(group) + 1) > target_cells:
                n_groups.append(group)
                group = []
            group.append(N)
        n_groups.append(group)
    units = []
    for si in range(len(spec.systems)):
        for wi in range(len(spec.sigma_w)):
            for Ns in n_groups:
                per_rep = spec.cells_per_rep * len(Ns)
                chunk = max(1, min(spec.reps, max_cells // per_rep))
                for r0 in range(0, spec.reps, chunk):
                    units.append(
                        {
                            "system": si,
                            "sigma_w": wi,
                            "N": list(Ns),
                            "reps": [r0, min(spec.reps, r0 + chunk)],
                        }
                    )
    return units


@dataclass
class _Axis:
    """The estimator axis E of one dataset: (estimator name, gamma or None)."""

    names: list[str]
    gammas: list[float | None]

    @property
    def gamma_array(self) -> np.ndarray:  # 0 for ols: the bounds use gamma = 0
        return np.array([0.0 if g is None else g for g in self.gammas])


def _estimator_axis(spec: ExperimentSpec) -> _Axis:
    names, gammas = [], []
    for e in spec.estimators:
        if e == "ols":
            names.append(e)
            gammas.append(None)
        else:
            names += [e] * len(spec.gamma)
            gammas += list(spec.gamma)
    return _Axis(names, gammas)


def _estimate(spec: ExperimentSpec, G, P, Z, F, N0, axis: _Axis) -> np.ndarray:
    """Theta for every (rep, estimator/gamma): (R, E, n, d); SPEC section 2.

    SVR needs only the sufficient statistics G = Z Z^T, P = F Z^T; OLS (and
    shrunk OLS) use the data themselves (iterative refinement, QR fallback).
    """
    parts = []
    theta_ols = None
    for e in spec.estimators:
        if e == "ols":
            theta_ols = _est.fit_ols(Z, F) if theta_ols is None else theta_ols
            parts.append(theta_ols[:, None])
        elif e == "svr":
            parts.append(_est.svr_from_gram(G, P, N0, spec.gamma, spec.loss_scale))
        else:  # shrunk-ols
            theta_ols = _est.fit_ols(Z, F) if theta_ols is None else theta_ols
            parts.append(_est.shrunk_ols(theta_ols, spec.gamma))
    return np.concatenate(parts, axis=1)


def _rmse(X, X_true) -> np.ndarray:
    return np.sqrt(np.mean((X - X_true) ** 2, axis=(-2, -1)))


class _Notes:
    """Per-cell reasons for null fields over the (R, E) grid, vectorised.

    ``add(mask, text)`` records one (text, cell mask) entry; a cell's notes
    are the texts of the entries that hold for it, in the order they were
    added, each text once, joined by "; " (None when there is none).
    """

    def __init__(self, shape):
        self.shape = tuple(shape)
        self._entries: list[tuple[str, np.ndarray]] = []
        self.tags: dict[str, int] = {}

    def add(self, mask, text: str, tag: str | None = None):
        """``tag``: name the entry (kept even when its mask is empty) so that
        :meth:`replace` can change it later."""
        m = np.broadcast_to(np.asarray(mask, dtype=bool), self.shape)
        if tag is not None:
            self.tags[tag] = len(self._entries)
            self._entries.append((text, m))
        elif m.any():
            self._entries.append((text, m))

    def replace(self, tag: str, mask, text: str) -> _Notes:
        """A copy with the tagged entry's mask and text replaced (same position)."""
        new = _Notes(self.shape)
        new._entries = list(self._entries)
        new.tags = dict(self.tags)
        new._entries[self.tags[tag]] = (
            text,
            np.broadcast_to(np.asarray(mask, dtype=bool), self.shape),
        )
        return new

    def add_reasons(self, reasons, prefix: str | None):
        """One entry per distinct reason of an object array (or a scalar)
        broadcasting to the grid; empty / None reasons are skipped."""
        r = np.broadcast_to(np.asarray(reasons, dtype=object), self.shape)
        for value in dict.fromkeys(v for v in r.ravel().tolist() if v):
            text = value if prefix is None else f"{prefix}: {value}"
            self.add(r == value, text)

    def strings(self) -> np.ndarray:
        """Object array (R, E) of the joined notes (None where there are none)."""
        out = np.full(self.shape, None, dtype=object)
        if not self._entries:
            return out
        words = []
        for w0 in range(0, len(self._entries), 62):
            code = np.zeros(self.shape, dtype=np.int64)
            for i, (_, m) in enumerate(self._entries[w0 : w0 + 62]):
                code |= m.astype(np.int64) << i
            words.append(code.reshape(-1))
        codes = np.stack(words, axis=1)
        uniq, inv = np.unique(codes, axis=0, return_inverse=True)
        texts: list[Any] = []
        for row in uniq.tolist():
            seen: list[str] = []
            for i, (t, _) in enumerate(self._entries):
                if (row[i // 62] >> (i % 62)) & 1 and t not in seen:
                    seen.append(t)
            texts.append("; ".join(seen) if seen else None)
        table = np.empty(len(texts), dtype=object)
        table[:] = texts
        return table[inv.reshape(-1)].reshape(self.shape)


def _run_dataset(spec, si, wi, N, reps, axis, prev_gain=None):
    """All stages for one (system, sigma_w, N) and a range of reps -> (fields, notes, N0, gain)."""
    system = spec.systems[si]
    sigma_w = spec.sigma_w[wi]
    n = system.n
    keys = [seed_key(si, wi, N, r) for r in reps]
    need_data = any(e in ("ols", "shrunk-ols") for e in spec.estimators)
    G, P, Z, F = gram_data(
        system, sigma_w, N, spec.T0, spec.seed, keys, spec.data, spec.x0_std, keep_data=need_data
    )
    N0 = (spec.T0 - 1) * N if spec.data == "all" else N
    theta = _estimate(spec, G, P, Z, F, N0, axis)
    A_hat, B_hat = theta[..., :n], theta[..., n:]
    R, E = theta.shape[:2]
    out: dict[str, np.ndarray] = {
        "A_hat": A_hat,
        "B_hat": B_hat,
        "rmse_A": _rmse(A_hat, system.A),
        "rmse_B": _rmse(B_hat, system.B),
    }
    notes = _Notes((R, E))
    skipped = [st for st in STAGES if not spec.has(st)]
    if skipped:
        notes.add(True, "stages not run: " + ", ".join(skipped))
    gamma = axis.gamma_array
    stages = _run_stages(
        spec, system, sigma_w, N, N0, keys, A_hat, B_hat, gamma, axis, out, notes, prev_gain
    )
    return out, notes, N0, stages


def _run_stages(
    spec, system, sigma_w, N, N0, keys, A_hat, B_hat, gamma, axis, out, notes, prev_gain
):
    if not spec.has("bounds"):
        return None
    rad = _bounds.radii(
        n=system.n,
        m=system.m,
        N=N,
        N0=N0,
        T0=spec.T0,
        sigma_u=system.sigma_u,
        sigma_w=sigma_w,
        gamma=gamma,
        M=spec.M,
        delta=spec.delta,
    )
    b = _bounds.evaluate_bounds(A_hat, B_hat, gamma, rad, system.A, system.B)
    R, E = A_hat.shape[:2]
    shape = (R, E)
    out.update(
        {
            "H_A": np.broadcast_to(rad.H_A, shape),
            "H_B": np.broadcast_to(rad.H_B, shape),
            "r_A": np.broadcast_to(rad.r_A, shape),
            "r_B": np.broadcast_to(rad.r_B, shape),
            "eps_A": b.eps_A,
            "eps_B": b.eps_B,
            "coverage_A": b.coverage_A,
            "coverage_B": b.coverage_B,
            "thm1_holds_A": b.thm1_holds_A,
            "thm1_holds_B": b.thm1_holds_B,
            "rho_upper_bound": b.rho_upper_bound,
            "stable_certified": b.stable_certified,
        }
    )
    if not spec.has("gain"):
        return None
    from . import gains as _gains
    from .observer_pipeline import design, run_observer_stages

    designed, k_hat_reasons = design(spec, system, sigma_w, A_hat, gamma, rad)
    if k_hat_reasons is not None:
        notes.add_reasons(k_hat_reasons, "K_hat")
    state = (designed.L, A_hat, np.broadcast_to(rad.r_A, shape))
    if prev_gain is not None:  # reuse_gain: keep the previous L while certified (SPEC 4)
        L_prev, A_prev, r_prev = prev_gain
        reuse = _gains.reuse_gains(
            np.stack([L_prev, designed.L]),
            np.stack([A_prev, A_hat]),
            gamma,
            np.stack([r_prev, state[2]]),
            system.C,
        )
        designed = _gains.GainResult(
            L=reuse.L[1], g_L=reuse.g_L[1], certified=reuse.certified[1], feasible=None
        )
        notes.add(reuse.reused[1], "gain: reused from the previous N")
        state = (reuse.L[1], A_hat, state[2])
    run_observer_stages(
        spec, system, sigma_w, keys, A_hat, B_hat, gamma, rad, b, axis, out, notes, designed
    )
    return state


_CELL_FIELDS = (
    "A_hat",
    "B_hat",
    "rmse_A",
    "rmse_B",
    "H_A",
    "H_B",
    "r_A",
    "r_B",
    "eps_A",
    "eps_B",
    "coverage_A",
    "coverage_B",
    "thm1_holds_A",
    "thm1_holds_B",
    "rho_upper_bound",
    "stable_certified",
    "L",
    "g_L",
    "certified",
    "rho_true",
    "K",
    "J_exact",
    "J_stationary",
    "J_mc",
    "J_mc_se",
    "J_star",
    "cost_ratio",
    "J_bound",
    "delta_J",
    "J_opt",
    "J_opt_bound",
    "sls_status",
)


# ---------------------------------------------------------------------------
# column results -> records, JSON lines, report columns
# ---------------------------------------------------------------------------
def _flat(arr, RE: int) -> np.ndarray:
    arr = np.asarray(arr)
    return arr.reshape((RE,) + arr.shape[2:])


def _values(arr, RE: int) -> list:
    """An (R, E, ...) field -> one plain value per cell (NaN/inf -> None), cell order."""
    arr = _flat(arr, RE)
    if arr.dtype == object or arr.dtype == bool:
        return arr.tolist()
    arr = arr.astype(float, copy=False)
    finite = np.isfinite(arr)
    out = np.where(finite, arr, 0.0).tolist()
    bad = ~finite.reshape(RE, -1).all(axis=1)
    for i in np.flatnonzero(bad).tolist():
        out[i] = json_value(arr[i])
    return out


def _broadcast_row(arr) -> np.ndarray | None:
    """The (E, ...) row of an (R, E, ...) array that is constant along R (stride 0), else None."""
    arr = np.asarray(arr)
    if arr.ndim >= 1 and arr.shape[0] > 1 and arr.strides[0] == 0:
        return arr[0]
    return None


def _json_strings(arr, RE: int) -> list[str]:
    """JSON text of each cell's value, exactly as ``json.dumps`` writes it."""
    arr = np.asarray(arr)
    row = _broadcast_row(arr)
    if row is not None:  # constant along the repetitions: encode one row, repeat it
        return _json_strings(row[None], row.shape[0]) * (RE // row.shape[0])
    arr = _flat(arr, RE)
    if arr.dtype == bool:
        return np.where(arr, "true", "false").tolist()
    if arr.dtype == object:
        return [json.dumps(v, allow_nan=False) for v in arr.tolist()]
    arr = arr.astype(float, copy=False)
    finite = np.isfinite(arr)
    if arr.ndim == 1:
        vals = np.where(finite, arr, 0.0)
        # few distinct values (coverage, gamma_ref's ratio 0): repr each once;
        # unique on the bits, so that -0.0 and 0.0 stay apart
        u, first, inv = np.unique(vals.view(np.int64), return_index=True, return_inverse=True)
        if 2 * u.size < vals.size:
            table = np.empty(u.size, dtype=object)
            table[:] = list(map(repr, vals[first].tolist()))
            out = table[inv.reshape(-1)].tolist()
        else:
            out = list(map(repr, vals.tolist()))
        for i in np.flatnonzero(~finite).tolist():
            out[i] = "null"
        return out
    # a matrix per cell: repr of nested lists of floats is the JSON text
    out = list(map(repr, np.where(finite, arr, 0.0).tolist()))
    bad = ~finite.reshape(RE, -1).all(axis=1)
    for i in np.flatnonzero(bad).tolist():
        out[i] = json.dumps(json_value(arr[i]), allow_nan=False)
    return out


@dataclass
class _Dataset:
    """One N of a unit: the fields over (reps, E) and their notes."""

    N: int
    N0: int
    fields: dict[str, np.ndarray]
    note_entries: _Notes

    def __post_init__(self):
        self.notes = self.note_entries.strings()  # object (R, E): str or None


class UnitResult:
    """The records of one work unit as column arrays.

    ``records()`` -> section 10 dicts; ``json_lines()`` -> the same records as
    JSON text, one string per record (``json.dumps(record)`` to the byte);
    ``columns(matrices)`` -> {field: array} for :class:`svrobs_core.report.Columns`.
    Record order: N ascending, then repetition, then estimator/gamma.
    """

    def __init__(
        self,
        system: str,
        system_idx: int,
        sigma_w: float,
        sigma_w_idx: int,
        reps: list[int],
        axis: _Axis,
        datasets: list[_Dataset],
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
        self._strings: dict[tuple, list[str]] = {}  # JSON text per (dataset, field[, limit])

    def with_mc_reps(self, mc_reps: int | None) -> UnitResult:
        """The records a spec with this ``mc_reps`` (and otherwise the same) gives.

        ``mc_reps`` changes only J_mc, J_mc_se and the note that says where
        they are null, so they are recomputed from this result when the new
        limit is not above the one it was computed with.
        """

        def lim(x):
            return self.n_reps if x is None else x

        if lim(mc_reps) == lim(self.mc_reps):
            return self
        if lim(mc_reps) > lim(self.mc_reps):
            raise ValueError(f"Monte Carlo was computed for rep < {lim(self.mc_reps)} only")
        rows = np.asarray(self.reps) < lim(mc_reps)
        datasets = []
        for ds in self.datasets:
            fields = dict(ds.fields)
            notes = ds.note_entries
            if "mc" in notes.tags:
                for f in ("J_mc", "J_mc_se"):
                    fields[f] = np.where(rows[:, None], fields[f], np.nan)
                from .observer_pipeline import mc_note

                notes = notes.replace("mc", ~rows[:, None], mc_note(lim(mc_reps)))
            datasets.append(_Dataset(N=ds.N, N0=ds.N0, fields=fields, note_entries=notes))
        new = UnitResult(
            self.system,
            self.system_idx,
            self.sigma_w,
            self.sigma_w_idx,
            self.reps,
            self.axis,
            datasets,
            mc_reps,
            self.n_reps,
        )
        new._strings = self._strings  # shared: the keys of J_mc, J_mc_se hold the limit
        return new

    def __len__(self) -> int:
        return len(self.reps) * len(self.axis.names) * len(self.datasets)

    # -- per-cell key columns -------------------------------------------------
    def _key_columns(self, ds: _Dataset) -> dict[str, Any]:
        R, E = len(self.reps), len(self.axis.names)
        RE = R * E
        return {
            "system": repeat(self.system, RE),
            "sigma_w": repeat(self.sigma_w, RE),
            "N": repeat(ds.N, RE),
            "N0": repeat(ds.N0, RE),
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
    ) -> dict[str, list]:
        """{field: one value per record, in record order} for every section 10 field
        not in ``omit``: plain Python values (NaN/inf -> None), and for the fields in
        ``as_json`` their JSON text (as ``json.dumps`` writes it) instead. The
        columnar form the DB layer stores without building a dict per record."""
        R, E = len(self.reps), len(self.axis.names)
        RE = R * E
        out: dict[str, list] = {f: [] for f in RECORD_FIELDS if f not in omit}
        for di, ds in enumerate(self.datasets):
            cols = self._key_columns(ds)
            if "seed_key" in as_json:
                cols["seed_key"] = self._seed_key_strings(ds)
            for f in _CELL_FIELDS:
                v = ds.fields.get(f)
                if f in omit:
                    continue
                if v is None:
                    cols[f] = repeat("null" if f in as_json else None, RE)
                elif f in as_json:
                    cols[f] = self._json_strings(di, f, v, RE)
                else:
                    cols[f] = _values(v, RE)
            cols["notes"] = ds.notes.reshape(RE).tolist()
            for f in out:
                out[f].extend(cols[f])
        return out

    def matrix_blocks(self) -> list[dict[str, np.ndarray | None]]:
        """Per dataset (in :meth:`value_columns` order), each matrix field as one
        (records, rows, cols) float array in record order, or None where it was not
        computed (NaN/inf entries are the records' nulls)."""
        RE = len(self.reps) * len(self.axis.names)
        return [
            {
                f: None if ds.fields.get(f) is None else _flat(ds.fields[f], RE)
                for f in MATRIX_FIELDS
            }
            for ds in self.datasets
        ]

    def records(self) -> list[dict]:
        cols = self.value_columns()
        return [dict(zip(RECORD_FIELDS, vals)) for vals in zip(*(cols[f] for f in RECORD_FIELDS))]

    def _seed_key_strings(self, ds: _Dataset) -> list[str]:
        E = len(self.axis.names)
        return [
            f"[{self.system_idx}, {self.sigma_w_idx}, {ds.N}, {r}]"
            for r in self.reps
            for _ in range(E)
        ]

    def _json_strings(self, di: int, f: str, v, RE: int) -> list[str]:
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
                "N0": str(int(ds.N0)),
            }
            var: dict[str, list[str]] = {
                "estimator": [json.dumps(x) for x in self.axis.names] * R,
                "gamma": ["null" if g is None else repr(float(g)) for g in self.axis.gammas] * R,
                "rep": [str(r) for r in self.reps for _ in range(E)],
                "seed_key": self._seed_key_strings(ds),
            }
            for f in _CELL_FIELDS:
                v = ds.fields.get(f)
                if v is None:
                    const[f] = "null"
                else:
                    var[f] = self._json_strings(di, f, v, RE)
            cache: dict[Any, str] = {}
            note_col = []
            for t in ds.notes.reshape(RE).tolist():
                s = cache.get(t)
                if s is None:
                    s = cache[t] = json.dumps(t)
                note_col.append(s)
            var["notes"] = note_col
            parts, order = [], []
            for f in RECORD_FIELDS:
                if f in var:
                    parts.append(f'"{f}": %s')
                    order.append(var[f])
                else:
                    parts.append(f'"{f}": ' + const[f].replace("%", "%%"))
            template = "{" + ", ".join(parts) + "}"
            lines += [template % t for t in zip(*order)]
        return lines

    def columns(self, matrices: bool = True) -> dict[str, np.ndarray]:
        """{field: array over the unit's records} as :mod:`svrobs_core.report` reads them:
        numbers as float (NaN = null, booleans 0/1), text as object arrays,
        A_hat/B_hat as (k, n, .) floats if ``matrices``."""
        from .report import MATRIX_FIELDS as RM
        from .report import SCALAR_FIELDS, TEXT_FIELDS

        R, E = len(self.reps), len(self.axis.names)
        RE = R * E
        parts: dict[str, list[np.ndarray]] = {}

        def put(f, a):
            parts.setdefault(f, []).append(a)

        gam = np.array([np.nan if g is None else g for g in self.axis.gammas], dtype=float)
        for ds in self.datasets:
            keys = {
                "sigma_w": np.full(RE, float(self.sigma_w)),
                "N": np.full(RE, float(ds.N)),
                "N0": np.full(RE, float(ds.N0)),
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
                for f in RM:
                    v = ds.fields.get(f)
                    if v is not None:
                        a = _flat(v, RE).astype(float)
                        put(f, np.where(np.isfinite(a).all(axis=(1, 2))[:, None, None], a, np.nan))
        return {f: np.concatenate(v) for f, v in parts.items()}


def run_unit_result(spec: ExperimentSpec, unit: dict) -> UnitResult:
    """Run one work unit of ``plan_units`` -> its records as a :class:`UnitResult`.

    A unit may carry ``"mc_reps"``: it overrides the spec's for this unit
    (used to compute the Monte Carlo J once for several specs that differ
    only there; see :meth:`UnitResult.with_mc_reps`)."""
    if "mc_reps" in unit and unit["mc_reps"] != spec.mc_reps:
        spec = replace(spec, mc_reps=unit["mc_reps"])
    si, wi = unit["system"], unit["sigma_w"]
    reps = list(range(*unit["reps"]))
    axis = _estimator_axis(spec)
    datasets = []
    prev_gain = None
    with _blas_single_thread():
        for N in sorted(unit["N"]):
            fields, notes, N0, gain = _run_dataset(spec, si, wi, N, reps, axis, prev_gain)
            if spec.reuse_gain:
                prev_gain = gain
            datasets.append(_Dataset(N=int(N), N0=int(N0), fields=fields, note_entries=notes))
    return UnitResult(
        spec.systems[si].name,
        si,
        spec.sigma_w[wi],
        wi,
        reps,
        axis,
        datasets,
        spec.mc_reps,
        spec.reps,
    )


def run_unit(spec: ExperimentSpec, unit: dict) -> list[dict]:
    """Run one work unit of ``plan_units`` -> its section 10 records."""
    return run_unit_result(spec, unit).records()


def _records_of(result: UnitResult) -> list[dict]:
    return result.records()


def run_spec(
    spec: ExperimentSpec,
    progress: Callable[[int, int], None] | None = None,
    units: list[dict] | None = None,
    n_jobs: int = 1,
    post: Callable[[UnitResult], Any] | None = None,
    pool=None,
) -> Iterator[Any]:
    """Run every unit, yielding each unit's records in unit order.

    ``n_jobs > 1`` runs units in that many worker processes (scikit-learn's
    convention); the records are the same to the bit either way. ``pool``:
    an executor from :func:`open_pool` to reuse across calls.
    ``post``: a picklable function applied to each unit's :class:`UnitResult`
    (in the worker process when ``n_jobs > 1``); its value is yielded
    instead of the list of record dicts (e.g. ``UnitResult.json_lines``).
    """
    units = plan_units(spec) if units is None else units
    post = _records_of if post is None else post
    if (n_jobs > 1 or pool is not None) and len(units) > 1:
        if pool is not None:
            yield from _run_parallel(pool, spec, units, progress, post)
        else:
            with open_pool(n_jobs) as own:
                yield from _run_parallel(own, spec, units, progress, post)
        return
    for i, unit in enumerate(units):
        yield post(run_unit_result(spec, unit))
        if progress is not None:
            progress(i + 1, len(units))


def _work(spec, unit, post):
    return post(run_unit_result(spec, unit))


def _worker_init():
    _blas_single_thread.limit_process()


def _noop():
    return None


@contextmanager
def open_pool(n_jobs: int):
    """A process pool of ``n_jobs`` workers for :func:`run_spec` (None for n_jobs <= 1).

    Workers are forked where the platform allows (no re-import) and started
    at once; each limits BLAS to one thread (the products are small and the
    cores are taken by the workers)."""
    if n_jobs <= 1:
        yield None
        return
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    ctx = mp.get_context("fork") if "fork" in mp.get_all_start_methods() else None
    with ProcessPoolExecutor(max_workers=n_jobs, mp_context=ctx, initializer=_worker_init) as pool:
        for f in [pool.submit(_noop) for _ in range(n_jobs)]:
            f.result()
        yield pool


def _run_parallel(pool, spec, units, progress, post):
    futures = {i: pool.submit(_work, spec, u, post) for i, u in enumerate(units)}
    try:
        for i in range(len(units)):
            yield futures.pop(i).result()
            if progress is not None:
                progress(i + 1, len(units))
    finally:
        for f in futures.values():
            f.cancel()


class _BlasSingleThread:
    """Context: BLAS limited to one thread (when threadpoolctl is installed).

    The pipeline makes many small matrix products; OpenBLAS threads only add
    synchronisation to them (2-3x slower on a busy 2-core machine), and with
    ``n_jobs`` worker processes they would oversubscribe the cores."""

    def __init__(self):
        self._controller = None
        self._tried = False

    def _get(self):
        if not self._tried:
            self._tried = True
            try:
                from threadpoolctl import ThreadpoolController

                self._controller = ThreadpoolController()
            except Exception:  # noqa: BLE001 - optional dependency, any failure: no limit
                self._controller = None
        return self._controller

    def __call__(self):
        c = self._get()
        if c is None:
            from contextlib import nullcontext

            return nullcontext()
        return c.limit(limits=1, user_api="blas")

    def limit_process(self):
        c = self._get()
        if c is not None:
            c.limit(limits=1, user_api="blas")


_blas_single_thread = _BlasSingleThread()
