"""The records as column arrays, and the helpers every table, figure and finding uses.

:class:`Columns` holds the record fields the report reads as numpy
arrays; :func:`spec_meta` the parts of the spec it needs (δ, seed, γ_ref,
stages, the true system matrices). Then selection (:func:`select`), grouping
(:func:`group_indices`, :func:`by_N`) and number formatting (:func:`fmt_num`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..array_types import Array, BoolArray, FloatArray
from ..paper import STABLE, UNSTABLE
from ..records import (  # noqa: F401 - the report's field lists live with the records
    BOUND_FIELDS,
    COLUMN_MATRIX_FIELDS,
    MATRIX_FIELDS,
    RECORD_FIELDS,
    REPORT_FIELDS,
    SCALAR_FIELDS,
    TEXT_FIELDS,
)
from . import column_wire

# Per stage, the fields that are null in every record when the stage did not run
# (named in the "no data" messages of the figures and findings).
STAGE_FIELDS = {
    "estimate": ("rmse_A", "rmse_B"),
    "bounds": tuple(f for f in BOUND_FIELDS if not f.startswith(("H_", "thm1_holds_"))),
    "gain": ("g_L", "certified", "rho_true"),
    "cost": ("J_exact", "J_star"),
    "cost_bound": ("J_bound", "delta_J"),
    "sls": ("J_opt",),
}

GAMMA_RTOL = 1e-9


# ---------------------------------------------------------------------------
# Columns: the records as arrays
# ---------------------------------------------------------------------------


def _float_array(values: Iterable[Any]) -> FloatArray:
    return np.array([np.nan if v is None else float(v) for v in values], dtype=float)


def _matrix_array(values: Sequence[Any]) -> FloatArray:
    """A list of matrices (lists) or None -> float (k, a, b) with NaN where missing."""
    shape = None
    for v in values:
        if v is not None:
            shape = np.shape(v)
            break
    if shape is None or len(shape) != 2:
        return np.full((len(values), 0, 0), np.nan)
    out = np.full((len(values),) + shape, np.nan)
    for i, v in enumerate(values):
        if v is not None and np.shape(v) == shape:
            out[i] = np.asarray(v, dtype=float)
    return out


class Columns:
    """Record fields as arrays: floats (NaN = null; booleans as 0/1), text as
    object arrays, ``A_hat``/``B_hat`` as (k, n, .) float arrays if kept."""

    def __init__(
        self,
        data: dict[str, Array],
        n: int,
        *,
        codes: dict[str, tuple[Array, list[Any]]] | None = None,
    ) -> None:
        self.data = data
        self.n = n
        self._cache: dict[Any, Any] = {}  # derived arrays (factorised text columns, ...)
        for f, fc in (codes or {}).items():  # factorised by the reader, as codes() would
            self._cache[("codes", f)] = fc

    def codes(self, f: str) -> tuple[Array, list[Any]]:
        """Field ``f`` factorised: integer codes and the value of each code
        (cached; floats as float, NaN as None)."""
        cache = self.cache
        key = ("codes", f)
        if key not in cache:
            cache[key] = _codes(self.data[f])
        codes: tuple[Array, list[Any]] = cache[key]
        return codes

    @property
    def cache(self) -> dict[Any, Any]:
        cache: dict[Any, Any] = self.__dict__.setdefault("_cache", {})
        return cache

    def equals(self, f: str, value: object) -> BoolArray:
        """Boolean mask ``self[f] == value`` for a text field (via the cached codes;
        cached itself, read-only: a report asks for the same few masks many times)."""

        def mask() -> BoolArray:
            codes, values = self.codes(f)
            hit = [i for i, v in enumerate(values) if v == value]
            if not hit:
                return np.zeros(self.n, dtype=bool)
            eq: BoolArray = codes == hit[0]
            return eq

        return self.cached_mask(("equals", f, value), mask)

    def cached_mask(self, key: tuple[Any, ...], make: Callable[[], BoolArray]) -> BoolArray:
        """The mask ``make()`` cached under ``key``, read-only (combine it into a mask
        of your own: ``m &= ...``)."""
        cache = self.cache
        if key not in cache:
            m = make()
            m.flags.writeable = False
            cache[key] = m
        out: BoolArray = cache[key]
        return out

    @classmethod
    def from_records(cls, records: Iterable[dict[str, Any]], matrices: bool = True) -> Columns:
        records = list(records)
        data: dict[str, Array] = {}
        for f in SCALAR_FIELDS:
            data[f] = _float_array([r.get(f) for r in records])
        for f in TEXT_FIELDS:
            data[f] = np.array([r.get(f) for r in records] + [None], dtype=object)[:-1]
        if matrices:
            for f in COLUMN_MATRIX_FIELDS:
                data[f] = _matrix_array([r.get(f) for r in records])
        return cls(data, len(records))

    @classmethod
    def concat(cls, parts: list[Columns]) -> Columns:
        parts = [p for p in parts if p.n]
        if not parts:
            return cls.from_records([])
        keys = set(parts[0].data)
        for p in parts[1:]:
            keys &= set(p.data)
        data = {}
        for k in keys:
            arrs = [p.data[k] for p in parts]
            if arrs[0].ndim == 3 and len({a.shape[1:] for a in arrs}) > 1:
                continue  # inconsistent matrix shapes: drop the field
            data[k] = np.concatenate(arrs)
        return cls(data, sum(p.n for p in parts))

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, f: str) -> Array:
        return self.data[f]

    def has(self, f: str, mask: Array | None = None) -> bool:
        """True when field ``f`` has at least one non-null value (under ``mask``)."""
        a = self.data.get(f)
        if a is None or self.n == 0:
            return False
        if mask is not None and a.dtype != object:
            a = a[mask]
        if a.dtype == object:  # via its codes: whether a non-null value's code occurs
            codes, values = self.codes(f)
            known = np.array([v is not None for v in values], dtype=bool)
            return bool(known[codes if mask is None else codes[mask]].any())
        if a.ndim == 3:
            return a.shape[1] > 0 and bool(np.isfinite(a).all(axis=(1, 2)).any())
        return bool(np.isfinite(a).any())

    def subset(self, mask: Array) -> Columns:
        idx = np.nonzero(mask)[0]
        return Columns({k: v[idx] for k, v in self.data.items()}, int(idx.size))

    def only(self, fields: Iterable[str]) -> Columns:
        """These of the fields (those present), with their cached codes: what a
        figure built in another process is sent (:class:`~.report_figure.FigureJob`).
        Reading any other field of it is a KeyError, not a field without data."""
        data, codes = column_wire.narrow(self.data, self.cache, fields)
        return Columns(data, self.n, codes=codes)

    def __getstate__(self) -> dict[str, Any]:
        """Pickled as :func:`.column_wire.pack` packs it (the masks stay here)."""
        return column_wire.pack(self.data, self.cache, self.n)

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.data, codes, self.n = column_wire.unpack(state)
        self._cache = {("codes", f): fc for f, fc in codes.items()}


def as_columns(records: Columns | Iterable[dict[str, Any]]) -> Columns:
    """Records (an iterable of dicts) or Columns -> Columns."""
    if isinstance(records, Columns):
        return records
    return Columns.from_records(records)


# ---------------------------------------------------------------------------
# spec metadata
# ---------------------------------------------------------------------------


@dataclass
class Meta:
    """The parts of a spec the report reads (these defaults when there is no spec)."""

    delta: float = 0.01
    seed: object = "?"
    gamma_ref: float = 0.1
    stages: tuple[Any, ...] = ()
    truth: dict[str, Any] = field(default_factory=dict)  # system name -> (A, B)
    spec_dict: dict[str, Any] | None = None
    bounds_method: str = "paper"


def spec_meta(spec: Any) -> Meta:
    from ..parsing import parse_spec
    from ..spec import ExperimentSpec
    from ..systems import PRESETS, resolve_system

    if spec is None:
        truth = {
            name: (np.asarray(p["A"], float), np.asarray(p["B"], float))
            for name, p in PRESETS.items()
        }
        return Meta(truth=truth)
    if not isinstance(spec, ExperimentSpec):
        spec = parse_spec(spec)
    truth = {s.name: (np.asarray(s.A), np.asarray(s.B)) for s in spec.systems}
    for name in PRESETS:  # names not in the spec but still presets
        if name not in truth:
            s = resolve_system(name)
            truth[name] = (np.asarray(s.A), np.asarray(s.B))
    return Meta(
        delta=spec.delta,
        seed=spec.seed,
        gamma_ref=spec.gamma_ref,
        stages=tuple(spec.stages),
        truth=truth,
        spec_dict=spec.to_dict(),
        bounds_method=spec.bounds_method,
    )


# ---------------------------------------------------------------------------
# selection, grouping and formatting
# ---------------------------------------------------------------------------


def select(
    cols: Columns,
    *,
    system: str | None = None,
    estimator: str | None = None,
    gamma: float | str | None = "any",
    sigma_w: float | None = None,
) -> BoolArray:
    m = np.ones(cols.n, dtype=bool)
    if system is not None:
        m &= cols.equals("system", system)
    if estimator is not None:
        m &= cols.equals("estimator", estimator)
    if gamma is None:
        m &= np.isnan(cols["gamma"])
    elif gamma != "any":
        m &= _close(cols, "gamma", float(gamma))
    if sigma_w is not None:
        m &= _close(cols, "sigma_w", float(sigma_w))
    return m


def _close(cols: Columns, f: str, value: float) -> BoolArray:
    """``isclose(cols[f], value)`` (rtol GAMMA_RTOL), decided once per distinct value
    (cached, read-only: :meth:`Columns.cached_mask`)."""

    def mask() -> BoolArray:
        codes, values = cols.codes(f)
        distinct = np.array([np.nan if v is None else v for v in values], dtype=float)
        hit: BoolArray = np.isclose(distinct, value, rtol=GAMMA_RTOL, atol=0)[codes]
        return hit

    if value != value:  # NaN: a key no lookup finds again
        return mask()
    return cols.cached_mask(("close", f, value), mask)


def _present(cols: Columns, f: str, mask: Array | None) -> list[Any]:
    """The distinct values of field ``f`` under ``mask``, in code order (a float
    field's ascending, None for NaN last): a count per code, no sort of the rows."""
    codes, values = cols.codes(f)
    counts = np.bincount(codes if mask is None else codes[mask], minlength=len(values))
    return [values[i] for i in np.flatnonzero(counts).tolist()]


def systems_of(cols: Columns, mask: Array | None = None) -> list[str]:
    names = {v for v in _present(cols, "system", mask) if v is not None}
    known = [s for s in (STABLE, UNSTABLE) if s in names]
    return known + sorted(names - set(known))


def _uniq_float(cols: Columns, f: str, mask: Array | None) -> list[float]:
    """The distinct finite values of float field ``f`` under ``mask``, ascending."""
    return [float(v) for v in _present(cols, f, mask) if v is not None and math.isfinite(v)]


def gammas_of(cols: Columns, mask: Array | None = None, estimator: str = "svr") -> list[float]:
    m = select(cols, estimator=estimator)
    if mask is not None:
        m &= mask
    return _uniq_float(cols, "gamma", m)


def sigmas_of(cols: Columns, mask: Array | None = None) -> list[float]:
    return _uniq_float(cols, "sigma_w", mask)


def _key(v: Any) -> Any:
    if isinstance(v, (float, np.floating)):
        return None if math.isnan(v) else float(v)
    return v


class FirstCodes(dict[Any, int]):
    """value -> its code: the next free one the first time a value is looked up (so
    codes number the values in order of first appearance, as :meth:`Columns.codes`
    does for text; readers that factorise as they read use it too)."""

    def __missing__(self, value: Any) -> int:
        code = self[value] = len(self)
        return code

    def encode(self, values: Any) -> Array:
        """The codes of ``values`` (a sequence), adding the values not seen yet."""
        return np.fromiter(map(self.__getitem__, values), dtype=np.int64, count=len(values))


def _codes(col: Array) -> tuple[Array, list[Any]]:
    """Factorise a column: integer codes and the key value of each code
    (floats as float, NaN as None; objects as themselves)."""
    if col.dtype == object:
        lut = FirstCodes()
        return lut.encode(col), list(lut)
    a = col.astype(float)
    u = np.unique(a)  # sorted, NaNs as one value, last (where searchsorted puts a NaN)
    return np.searchsorted(u, a).astype(np.int64), [_key(v) for v in u.tolist()]


def group_indices(
    cols: Columns, keys: tuple[str, ...], mask: Array | None = None
) -> dict[tuple[Any, ...], Array]:
    """key tuple -> indices (ascending); NaN keys (gamma of ols) become None.
    Groups are ordered by their keys (None last)."""
    idx = np.arange(cols.n) if mask is None else np.nonzero(mask)[0]
    if idx.size == 0:
        return {}
    combined = np.zeros(idx.size, dtype=np.int64)
    values = []
    for k in keys:
        c, u = cols.codes(k)
        combined = combined * len(u) + c[idx]
        values.append(u)
    order = np.argsort(combined, kind="stable")  # members stay ascending in each group
    ordered = combined[order]
    bounds = np.flatnonzero(np.diff(ordered)) + 1
    uc = ordered[np.concatenate(([0], bounds))]
    groups = np.split(idx[order], bounds)
    parts = []  # each key's code in each group
    for u in reversed(values):
        uc, j = np.divmod(uc, len(u))
        parts.append(j)
    parts.reverse()
    # the groups in key order, None last: each key's codes ranked by their values
    by_key = np.lexsort([_ranks(u)[p] for u, p in zip(reversed(values), reversed(parts))])
    columns = [[u[j] for j in p.tolist()] for u, p in zip(values, parts)]
    return {tuple(c[g] for c in columns): groups[g] for g in by_key.tolist()}


def _ranks(values: list[Any]) -> Array:
    """The rank of each code's value among ``values`` (ascending, None last)."""

    def key(i: int) -> tuple[bool, Any]:
        v = values[i]
        return (v is None, v if v is not None else 0)

    order = sorted(range(len(values)), key=key)
    ranks = np.empty(len(values), dtype=np.int64)
    ranks[order] = np.arange(len(values))
    return ranks


def by_N(
    cols: Columns, mask: Array, values: Array, fn: Callable[[Array], float]
) -> tuple[FloatArray, FloatArray, FloatArray, Array]:
    """Group ``values`` (full-length array) by N under ``mask`` (a boolean mask, or
    the rows' indices, ascending); NaNs dropped.

    -> (N0 array, N array, stat array, count array)
    """
    idx = np.nonzero(mask)[0] if mask.dtype == bool else mask
    if idx.size == 0:
        e = np.array([])
        return e, e, e, e
    codes, distinct = cols.codes("N")  # N's distinct values, sorted; keep those under mask
    present = np.zeros(len(distinct), dtype=bool)
    present[codes[idx]] = True
    inv = (np.cumsum(present) - 1)[codes[idx]]
    uN = np.array([np.nan if v is None else v for v in distinct], dtype=float)[present]
    k = uN.size
    n0 = cols["N0"][idx]
    f0 = np.isfinite(n0)
    c0 = np.bincount(inv[f0], minlength=k)
    with np.errstate(invalid="ignore", divide="ignore"):
        x0 = np.where(
            c0 > 0, np.bincount(inv[f0], weights=n0[f0], minlength=k) / c0, uN.astype(float)
        )
    v = values[idx]
    fv = np.isfinite(v)
    cnt = np.bincount(inv[fv], minlength=k)
    if fn is mean_of:  # the common case, vectorised
        with np.errstate(invalid="ignore", divide="ignore"):
            ys = np.where(cnt > 0, np.bincount(inv[fv], weights=v[fv], minlength=k) / cnt, np.nan)
    else:
        order = np.argsort(inv[fv], kind="stable")
        groups = np.split(v[fv][order], np.cumsum(cnt)[:-1])
        ys = np.array([fn(g) if g.size else np.nan for g in groups], dtype=float)
    return x0.astype(float), uN.astype(float), ys.astype(float), cnt


def mean_of(v: Array) -> float:
    return float(np.mean(v))


def n0_ratio(cols: Columns, mask: Array | None = None) -> float | None:
    m = np.ones(cols.n, bool) if mask is None else mask
    N, N0 = cols["N"][m], cols["N0"][m]
    ok = np.isfinite(N) & np.isfinite(N0) & (N > 0)
    if not ok.any():
        return None
    r = N0[ok] / N[ok]
    return float(r[0]) if np.allclose(r, r[0]) else None


def fmt_num(v: Any, digits: int = 4) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    if isinstance(v, (bool, np.bool_)):
        return str(bool(v))
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    return f"{float(v):.{digits}g}"


def gamma_label(estimator: str, gamma: float | None) -> str:
    if estimator == "ols" or gamma is None:
        return "OLS"
    name = "SVR" if estimator == "svr" else estimator
    return f"{name} γ={fmt_num(gamma)}"
