"""Tables, figures, findings and the rendered report, from section 10 records.

Pure: records (or :class:`Columns` built from them) in; rows, strings,
matplotlib ``Figure`` objects and bytes out. Nothing here writes files or
touches the network. Figures are rendered headless with the Agg canvas.

Every number shown comes from the records (and the spec that produced them).
The only typed-in numbers are the paper's *published* values of
``svrobs_core.paper`` (``PUBLISHED_TABLE2``, ``PUBLISHED_CLAIMS``), shown
beside ours and labelled as published.

Public API
----------
* ``Columns``, ``as_columns(records)``: column arrays of the fields used here.
* ``table2(records, gamma=None)``, ``table2_markdown(rows)``, ``table2_csv(rows)``
* ``first_stable_certified(records)``
* Figures: ``fig_rmse``, ``fig2``, ``fig3``, ``fig4``, ``fig5``,
  ``fig_coverage``, ``fig_certified``, ``fig_svr_ols_diff``; each
  ``f(records, spec=None, *, experiment=...) -> matplotlib.figure.Figure``.
* ``figure_bytes(fig, fmt="png" | "svg")``
* ``findings(records, spec) -> list[str]``
* ``build_report(experiments, provenance)``, ``render_markdown(report)``,
  ``render_html(report)``, ``job_report_html(spec, records)``
"""

from __future__ import annotations

import base64
import csv
import html
import io
import json
import math
import sys
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .paper import (
    EXPERIMENTS,
    PRESET_NAME,
    PUBLISHED_CLAIMS,
    STABLE,
    TABLE2_GAMMA,
    UNSTABLE,
    published_table2,
)
from .records import GROUP_FIELDS, RECORD_FIELDS

# Fields the report reads. L, K (matrices) and seed_key are never needed.
MATRIX_FIELDS = ("A_hat", "B_hat")
TEXT_FIELDS = ("system", "estimator", "sls_status", "notes")
REPORT_FIELDS = tuple(f for f in RECORD_FIELDS if f not in ("L", "K", "seed_key"))
SCALAR_FIELDS = tuple(f for f in REPORT_FIELDS if f not in MATRIX_FIELDS + TEXT_FIELDS)

STAGE_FIELDS = {
    "estimate": ("rmse_A", "rmse_B"),
    "bounds": (
        "r_A",
        "r_B",
        "eps_A",
        "eps_B",
        "coverage_A",
        "coverage_B",
        "rho_upper_bound",
        "stable_certified",
    ),
    "gain": ("g_L", "certified", "rho_true"),
    "cost": ("J_exact", "J_star"),
    "cost_bound": ("J_bound", "delta_J"),
    "sls": ("J_opt",),
}

_GAMMA_RTOL = 1e-9


# ---------------------------------------------------------------------------
# Columns: the records as arrays
# ---------------------------------------------------------------------------


def _float_array(values) -> np.ndarray:
    return np.array([np.nan if v is None else float(v) for v in values], dtype=float)


def _matrix_array(values) -> np.ndarray:
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

    def __init__(self, data: dict[str, np.ndarray], n: int):
        self.data = data
        self.n = n
        self._cache: dict = {}  # derived arrays (factorised text columns, ...)

    def codes(self, f: str) -> tuple[np.ndarray, list]:
        """Field ``f`` factorised: integer codes and the value of each code
        (cached; floats as float, NaN as None)."""
        cache = self.cache
        key = ("codes", f)
        if key not in cache:
            cache[key] = _codes(self.data[f])
        return cache[key]

    @property
    def cache(self) -> dict:
        return self.__dict__.setdefault("_cache", {})

    def equals(self, f: str, value) -> np.ndarray:
        """Boolean mask ``self[f] == value`` for a text field (via the cached codes)."""
        codes, values = self.codes(f)
        hit = [i for i, v in enumerate(values) if v == value]
        if not hit:
            return np.zeros(self.n, dtype=bool)
        return codes == hit[0]

    @classmethod
    def from_records(cls, records: Iterable[dict], matrices: bool = True) -> Columns:
        records = list(records)
        data: dict[str, np.ndarray] = {}
        for f in SCALAR_FIELDS:
            data[f] = _float_array([r.get(f) for r in records])
        for f in TEXT_FIELDS:
            data[f] = np.array([r.get(f) for r in records] + [None], dtype=object)[:-1]
        if matrices:
            for f in MATRIX_FIELDS:
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

    def __getitem__(self, f: str) -> np.ndarray:
        return self.data[f]

    def has(self, f: str, mask=None) -> bool:
        """True when field ``f`` has at least one non-null value (under ``mask``)."""
        a = self.data.get(f)
        if a is None or self.n == 0:
            return False
        if mask is not None:
            a = a[mask]
        if a.dtype == object:
            return any(v is not None for v in a)
        if a.ndim == 3:
            return a.shape[1] > 0 and bool(np.isfinite(a).all(axis=(1, 2)).any())
        return bool(np.isfinite(a).any())

    def subset(self, mask) -> Columns:
        idx = np.nonzero(mask)[0]
        return Columns({k: v[idx] for k, v in self.data.items()}, int(idx.size))


def as_columns(records) -> Columns:
    """Records (an iterable of dicts) or Columns -> Columns."""
    if isinstance(records, Columns):
        return records
    return Columns.from_records(records)


# ---------------------------------------------------------------------------
# spec metadata
# ---------------------------------------------------------------------------


@dataclass
class _Meta:
    delta: float = 0.01
    seed: object = "?"
    gamma_ref: float = 0.1
    stages: tuple = ()
    truth: dict = field(default_factory=dict)  # system name -> (A, B)
    spec_dict: dict | None = None


def _meta(spec) -> _Meta:
    from .spec import ExperimentSpec, parse_spec
    from .systems import PRESETS, resolve_system

    if spec is None:
        truth = {
            name: (np.asarray(p["A"], float), np.asarray(p["B"], float))
            for name, p in PRESETS.items()
        }
        return _Meta(truth=truth)
    if not isinstance(spec, ExperimentSpec):
        spec = parse_spec(spec)
    truth = {s.name: (np.asarray(s.A), np.asarray(s.B)) for s in spec.systems}
    for name in PRESETS:  # names not in the spec but still presets
        if name not in truth:
            s = resolve_system(name)
            truth[name] = (np.asarray(s.A), np.asarray(s.B))
    return _Meta(
        delta=spec.delta,
        seed=spec.seed,
        gamma_ref=spec.gamma_ref,
        stages=tuple(spec.stages),
        truth=truth,
        spec_dict=spec.to_dict(),
    )


# ---------------------------------------------------------------------------
# selection and grouping helpers
# ---------------------------------------------------------------------------


def _mask(cols: Columns, *, system=None, estimator=None, gamma="any", sigma_w=None) -> np.ndarray:
    m = np.ones(cols.n, dtype=bool)
    if system is not None:
        m &= cols.equals("system", system)
    if estimator is not None:
        m &= cols.equals("estimator", estimator)
    if gamma is None:
        m &= np.isnan(cols["gamma"])
    elif gamma != "any":
        m &= np.isclose(cols["gamma"], float(gamma), rtol=_GAMMA_RTOL, atol=0)
    if sigma_w is not None:
        m &= np.isclose(cols["sigma_w"], float(sigma_w), rtol=_GAMMA_RTOL, atol=0)
    return m


def _systems(cols: Columns, mask=None) -> list[str]:
    vals = cols["system"] if mask is None else cols["system"][mask]
    names = {v for v in vals if v is not None}
    known = [s for s in (STABLE, UNSTABLE) if s in names]
    return known + sorted(names - set(known))


def _uniq_float(a: np.ndarray) -> list[float]:
    a = a[np.isfinite(a)]
    return [float(v) for v in np.unique(a)]


def _gammas(cols: Columns, mask=None, estimator="svr") -> list[float]:
    m = _mask(cols, estimator=estimator)
    if mask is not None:
        m &= mask
    return _uniq_float(cols["gamma"][m])


def _sigmas(cols: Columns, mask=None) -> list[float]:
    a = cols["sigma_w"] if mask is None else cols["sigma_w"][mask]
    return _uniq_float(a)


def _key(v):
    if isinstance(v, (float, np.floating)):
        return None if math.isnan(v) else float(v)
    return v


def _codes(col: np.ndarray) -> tuple[np.ndarray, list]:
    """Factorise a column: integer codes and the key value of each code
    (floats as float, NaN as None; objects as themselves)."""
    if col.dtype == object:
        lut: dict = {}
        setdefault = lut.setdefault
        codes = np.array([setdefault(v, len(lut)) for v in col.tolist()], dtype=np.int64)
        return codes, list(lut)
    u, inv = np.unique(col.astype(float), return_inverse=True)  # NaNs: one value, last
    return inv.reshape(-1).astype(np.int64), [_key(v) for v in u.tolist()]


def _groupby(cols: Columns, keys: tuple[str, ...], mask=None) -> dict[tuple, np.ndarray]:
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
    uc, inv = np.unique(combined, return_inverse=True)
    inv = inv.reshape(-1)
    order = np.argsort(inv, kind="stable")
    bounds = np.flatnonzero(np.diff(inv[order])) + 1
    groups = np.split(idx[order], bounds)
    out: dict[tuple, np.ndarray] = {}
    for code, members in zip(uc.tolist(), groups):
        key = []
        for u in reversed(values):
            code, j = divmod(code, len(u))
            key.append(u[j])
        out[tuple(reversed(key))] = members
    order_k = sorted(out, key=lambda k: tuple((v is None, v if v is not None else 0) for v in k))
    return {k: out[k] for k in order_k}


def _by_N(cols: Columns, mask, values: np.ndarray, fn: Callable[[np.ndarray], float]):
    """Group ``values`` (full-length array) by N under ``mask``; NaNs dropped.

    -> (N0 array, N array, stat array, count array)
    """
    idx = np.nonzero(mask)[0]
    if idx.size == 0:
        e = np.array([])
        return e, e, e, e
    Ns = cols["N"][idx]
    uN, inv = np.unique(Ns, return_inverse=True)
    inv = inv.reshape(-1)
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
    if fn is _mean:  # the common case, vectorised
        with np.errstate(invalid="ignore", divide="ignore"):
            ys = np.where(cnt > 0, np.bincount(inv[fv], weights=v[fv], minlength=k) / cnt, np.nan)
    else:
        order = np.argsort(inv[fv], kind="stable")
        groups = np.split(v[fv][order], np.cumsum(cnt)[:-1])
        ys = np.array([fn(g) if g.size else np.nan for g in groups], dtype=float)
    return x0.astype(float), uN.astype(float), ys.astype(float), cnt


def _mean(v: np.ndarray) -> float:
    return float(np.mean(v))


def _n0_ratio(cols: Columns, mask=None) -> float | None:
    m = np.ones(cols.n, bool) if mask is None else mask
    N, N0 = cols["N"][m], cols["N0"][m]
    ok = np.isfinite(N) & np.isfinite(N0) & (N > 0)
    if not ok.any():
        return None
    r = N0[ok] / N[ok]
    return float(r[0]) if np.allclose(r, r[0]) else None


def _fmt(v, digits: int = 4) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    if isinstance(v, (bool, np.bool_)):
        return str(bool(v))
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    return f"{float(v):.{digits}g}"


def _gamma_label(estimator: str, gamma) -> str:
    if estimator == "ols" or gamma is None:
        return "OLS"
    name = "SVR" if estimator == "svr" else estimator
    return f"{name} γ={_fmt(gamma)}"


# ---------------------------------------------------------------------------
# Table 2
# ---------------------------------------------------------------------------


def _table_gamma(cols: Columns, gamma) -> float | None:
    if gamma is not None:
        return float(gamma)
    gs = _gammas(cols)
    if not gs:
        return None
    for g in gs:
        if math.isclose(g, TABLE2_GAMMA, rel_tol=_GAMMA_RTOL):
            return g
    return gs[0]


def _avg_over_reps_then_N(cols: Columns, mask, f: str) -> tuple[float | None, int, int]:
    """Mean over repetitions per N, then mean over N (SPEC section 9 Decision)."""
    _, _, means, counts = _by_N(cols, mask, cols[f], _mean)
    ok = np.isfinite(means)
    if not ok.any():
        return None, 0, 0
    return float(means[ok].mean()), int(ok.sum()), int(counts[ok].min())


def table2(records, gamma: float | None = None) -> list[dict]:
    """Table 2 rows: our OLS and SVR RMSE (mean over reps, then over the N grid)
    beside the paper's published values, with the ratio ours / paper.

    ``gamma``: the SVR gamma to tabulate (default 0.05 if present, else the
    first). Published values are attached only for gamma = 0.05 and the
    paper's systems.
    """
    cols = as_columns(records)
    g = _table_gamma(cols, gamma)
    rows = []
    for system in _systems(cols):
        ms = _mask(cols, system=system)
        for sigma_w in _sigmas(cols, ms):
            for mat in ("A", "B"):
                f = f"rmse_{mat}"
                m_ols = ms & _mask(cols, estimator="ols", sigma_w=sigma_w)
                if g is None:
                    m_svr = np.zeros(cols.n, bool)
                else:
                    m_svr = ms & _mask(cols, estimator="svr", gamma=g, sigma_w=sigma_w)
                ols, nN_o, nr_o = _avg_over_reps_then_N(cols, m_ols, f)
                svr, nN_s, nr_s = _avg_over_reps_then_N(cols, m_svr, f)
                pub = None
                if g is not None and math.isclose(g, TABLE2_GAMMA, rel_tol=_GAMMA_RTOL):
                    pub = published_table2(system, sigma_w, mat)
                p_ols = pub["ols"] if pub else None
                p_svr = pub["ours"] if pub else None
                rows.append(
                    {
                        "system": system,
                        "sigma_w": sigma_w,
                        "matrix": mat,
                        "gamma": g,
                        "ols": ols,
                        "svr": svr,
                        "paper_ols": p_ols,
                        "paper_ours": p_svr,
                        "ratio_ols": (ols / p_ols) if (ols is not None and p_ols) else None,
                        "ratio_svr": (svr / p_svr) if (svr is not None and p_svr) else None,
                        "svr_minus_ols": (svr - ols)
                        if (svr is not None and ols is not None)
                        else None,
                        "n_N": max(nN_o, nN_s),
                        "reps_per_N": min((x for x in (nr_o, nr_s) if x), default=0),
                    }
                )
    return rows


TABLE2_COLUMNS = (
    "system",
    "sigma_w",
    "matrix",
    "gamma",
    "ols",
    "svr",
    "paper_ols",
    "paper_ours",
    "ratio_ols",
    "ratio_svr",
    "svr_minus_ols",
    "n_N",
    "reps_per_N",
)


def table2_markdown(rows: list[dict]) -> str:
    head = (
        "| System | σ_w | Matrix | OLS (ours) | SVR (ours) | OLS (paper, published) "
        '| "Ours" SVR (paper, published) | OLS ours/paper | SVR ours/paper '
        "| SVR − OLS (ours) |"
    )
    lines = [head, "|" + "---|" * 10]
    for r in rows:
        lines.append(
            f"| {r['system']} | {_fmt(r['sigma_w'])} | {r['matrix']} | {_fmt(r['ols'])} "
            f"| {_fmt(r['svr'])} | {_fmt(r['paper_ols'])} | {_fmt(r['paper_ours'])} "
            f"| {_fmt(r['ratio_ols'], 3)} | {_fmt(r['ratio_svr'], 3)} "
            f"| {_fmt(r['svr_minus_ols'], 3)} |"
        )
    if rows:
        g = rows[0].get("gamma")
        n_N = max(r["n_N"] for r in rows)
        reps = min((r["reps_per_N"] for r in rows if r["reps_per_N"]), default=0)
        lines.append("")
        lines.append(
            f"RMSE = sqrt(mean of squared entry errors) of one estimate, averaged over the "
            f"{reps} repetitions at each N and then over the {n_N} values of N "
            f"(SPEC section 9); SVR with γ = {_fmt(g)}. The paper columns are the paper's "
            f"published Table 2 values, not results of this run."
        )
    return "\n".join(lines) + "\n"


def table2_csv(rows: list[dict]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(TABLE2_COLUMNS), lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in TABLE2_COLUMNS})
    return buf.getvalue()


# ---------------------------------------------------------------------------
# derived per-record quantities
# ---------------------------------------------------------------------------


def _entry_quantities(cols: Columns, meta: _Meta, mat: str):
    """Per record: max_ij |ΔX_ij|, and the Lemma 2 interval-end envelope
    max_ij(γX̃_ij) + r_X and min_ij(γX̃_ij) − r_X (γ = 0 for OLS), X = A or B.
    NaN where the estimate, the radius or the true system is unknown."""
    n = cols.n
    err = np.full(n, np.nan)
    hi = np.full(n, np.nan)
    lo = np.full(n, np.nan)
    X = cols.data.get(f"{mat}_hat")
    if X is None or X.ndim != 3 or X.shape[1] == 0:
        return err, lo, hi
    g = np.nan_to_num(cols["gamma"], nan=0.0)
    r = cols[f"r_{mat}"]
    for system in _systems(cols):
        truth = meta.truth.get(system)
        if truth is None:
            continue
        T = truth[0] if mat == "A" else truth[1]
        m = cols["system"] == system
        if T.shape != X.shape[1:]:
            continue
        Xs = X[m]
        err[m] = np.abs(T - Xs).max(axis=(1, 2))
        centre = g[m, None, None] * Xs
        hi[m] = centre.max(axis=(1, 2)) + r[m]
        lo[m] = centre.min(axis=(1, 2)) - r[m]
    return err, lo, hi


def _svr_ols_diff(cols: Columns) -> np.ndarray:
    """Per SVR record: max_ij |Ã_svr − Ã_ols| against the OLS estimate of the
    same (system, sigma_w, N, rep), i.e. the same data. NaN elsewhere."""
    if "svr_ols_diff" not in cols.cache:
        cols.cache["svr_ols_diff"] = _svr_ols_diff_calc(cols)
    return cols.cache["svr_ols_diff"].copy()


def _svr_ols_diff_calc(cols: Columns) -> np.ndarray:
    out = np.full(cols.n, np.nan)
    X = cols.data.get("A_hat")
    if X is None or X.ndim != 3 or X.shape[1] == 0:
        return out
    keys = list(
        zip(cols["system"], cols["sigma_w"].tolist(), cols["N"].tolist(), cols["rep"].tolist())
    )
    ols_at = {}
    for i in np.nonzero(cols["estimator"] == "ols")[0]:
        ols_at[keys[i]] = i
    for i in np.nonzero(cols["estimator"] == "svr")[0]:
        j = ols_at.get(keys[i])
        if j is not None:
            out[i] = np.abs(X[i] - X[j]).max()
    return out


def first_stable_certified(records, share: float = 0.5) -> dict[tuple, dict | None]:
    """(system, sigma_w, estimator, gamma) -> {"N", "N0", "share"} of the first N
    at which stable_certified holds in at least ``share`` of the repetitions,
    or None ("never in the grid"); only groups with stable_certified data."""
    cols = as_columns(records)
    out: dict[tuple, dict | None] = {}
    sc = cols["stable_certified"]
    for key, idx in _groupby(
        cols, ("system", "sigma_w", "estimator", "gamma"), np.isfinite(sc)
    ).items():
        m = np.zeros(cols.n, bool)
        m[idx] = True
        x0, Ns, shares, _ = _by_N(cols, m, sc, _mean)
        hit = np.nonzero(shares >= share)[0]
        out[key] = (
            None
            if hit.size == 0
            else {
                "N": int(Ns[hit[0]]),
                "N0": int(round(x0[hit[0]])),
                "share": float(shares[hit[0]]),
                "N_max": int(Ns.max()),
                "N0_max": int(round(x0.max())),
            }
        )
        if out[key] is None:
            out[key] = {
                "N": None,
                "N0": None,
                "share": None,
                "N_max": int(Ns.max()),
                "N0_max": int(round(x0.max())),
            }
    return out


# ---------------------------------------------------------------------------
# figure plumbing
# ---------------------------------------------------------------------------


def _ensure_agg():
    import matplotlib

    if "matplotlib.pyplot" not in sys.modules:  # never switch a user's live pyplot backend
        matplotlib.use("Agg")


def _figure(nrows: int, ncols: int, figsize, sharex=False, sharey=False):
    _ensure_agg()
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False, sharex=sharex, sharey=sharey)
    return fig, axes


def _title(fig, what: str, experiment: str | None, meta: _Meta):
    exp = experiment or "experiment"
    fig.suptitle(f"{what}\n{exp} · seed {meta.seed}", fontsize=11)


def _no_data(ax, msg: str):
    ax.text(
        0.5,
        0.5,
        "no data\n" + msg,
        ha="center",
        va="center",
        transform=ax.transAxes,
        fontsize=9,
        color="0.35",
        wrap=True,
        bbox=dict(boxstyle="round", fc="0.95", ec="0.7"),
    )
    # not set_xticks([]): that would clear the ticks of every axis shared with this one
    ax.tick_params(left=False, bottom=False, labelleft=False, labelbottom=False)


def _x_axis(ax, ratio: float | None):
    if ratio is not None and ratio != 1.0:
        ax.set_xlabel(f"sample length N0 = {ratio:g}·N  (N rollouts)")
    else:
        ax.set_xlabel("sample length N0")


def _reason(cols: Columns, mask, fields: tuple[str, ...], meta: _Meta) -> str:
    """Why a panel has no data: the stage did not run, or its fields are null."""
    need = [s for s, fs in STAGE_FIELDS.items() if any(f in fs for f in fields)]
    missing = [s for s in need if meta.stages and s not in meta.stages]
    if missing:
        return f"stage(s) {', '.join(missing)} not in the spec that ran"
    if cols.n == 0 or (mask is not None and not np.any(mask)):
        return "no records for this selection"
    notes = [v for v in cols["notes"][mask] if v] if mask is not None else []
    text = f"fields {', '.join(fields)} are null in every record"
    if notes:
        text += f"\n(notes: {notes[0][:80]})"
    return text


def figure_bytes(fig, fmt: str = "png", dpi: int = 110) -> bytes:
    """Render a Figure to PNG or SVG bytes in memory (deterministic metadata)."""
    buf = io.BytesIO()
    if fmt == "svg":
        import matplotlib

        with matplotlib.rc_context({"svg.hashsalt": "svrobs", "svg.fonttype": "none"}):
            fig.savefig(buf, format="svg", metadata={"Date": None})
    elif fmt == "png":
        fig.savefig(buf, format="png", dpi=dpi, metadata={"Software": None})
    else:
        raise ValueError(f"fmt must be 'png' or 'svg', got {fmt!r}")
    return buf.getvalue()


def _legend(fig, handles, ncol=4):
    if handles:
        fig.legend(
            handles=handles, loc="outside lower center", ncol=ncol, fontsize=8, frameon=False
        )


def _line(color="0.2", ls="-", label=""):
    from matplotlib.lines import Line2D

    return Line2D([], [], color=color, ls=ls, label=label)


# ---------------------------------------------------------------------------
# figures
# ---------------------------------------------------------------------------


def fig_rmse(records, spec=None, *, experiment: str | None = "E1", gamma: float | None = None):
    """RMSE of Ã and B̃ per N (the curves behind Table 2): OLS vs SVR, per σ_w."""
    cols, meta = as_columns(records), _meta(spec)
    g = _table_gamma(cols, gamma)
    systems = _systems(cols) or ["(none)"]
    fig, axes = _figure(2, len(systems), (5.2 * len(systems), 7), sharex=True)
    sig = _sigmas(cols)
    ratio = _n0_ratio(cols)
    for c, system in enumerate(systems):
        for r, mat in enumerate(("A", "B")):
            ax = axes[r, c]
            f = f"rmse_{mat}"
            any_line = False
            for i, s in enumerate(sig):
                for est, ls in (("ols", "-"), ("svr", "--")):
                    m = _mask(
                        cols,
                        system=system,
                        estimator=est,
                        sigma_w=s,
                        gamma=None if est == "ols" else g,
                    )
                    x, _, y, _ = _by_N(cols, m, cols[f], _mean)
                    if np.isfinite(y).any():
                        ax.plot(x, y, color=f"C{i}", ls=ls, lw=1.3)
                        any_line = True
            if not any_line:
                _no_data(ax, _reason(cols, _mask(cols, system=system), (f,), meta))
                continue
            ax.set_yscale("log")
            ax.minorticks_off()
            ax.set_ylabel(f"RMSE of {mat}̃ (mean over reps)")
            ax.set_title(f"{system}: {mat}", fontsize=10)
            if r == 1:
                _x_axis(ax, ratio)
            ax.grid(alpha=0.3)
    handles = [_line(f"C{i}", "-", f"σ_w={_fmt(s)}") for i, s in enumerate(sig)]
    handles += [_line("0.2", "-", "OLS"), _line("0.2", "--", f"SVR γ={_fmt(g)}")]
    _legend(fig, handles, ncol=len(handles))
    _title(fig, f"RMSE per sample length behind Table 2 (OLS vs SVR γ={_fmt(g)})", experiment, meta)
    return fig


def _interval_panels(
    fig, axes, cols, meta, series, series_label, systems, ratio, certified_marks=None
):
    """Shared body of fig2/fig3: rows A, B; columns systems; one color per series.

    series: list of (label, mask-builder(system) -> mask)."""
    q = {mat: _entry_quantities(cols, meta, mat) for mat in ("A", "B")}
    for c, system in enumerate(systems):
        for r, mat in enumerate(("A", "B")):
            ax = axes[r, c]
            err, lo, hi = q[mat]
            any_line = False
            for i, (_label, mk) in enumerate(series):
                m = mk(system)
                x, _, y_err, _ = _by_N(cols, m, err, _mean)
                _, _, y_hi, _ = _by_N(cols, m, hi, _mean)
                _, _, y_lo, _ = _by_N(cols, m, lo, _mean)
                _, _, y_eps, _ = _by_N(cols, m, cols[f"eps_{mat}"], _mean)
                col = f"C{i}"
                for y, ls in ((y_err, "-"), (y_hi, "--"), (y_lo, "--"), (y_eps, ":")):
                    if np.isfinite(y).any():
                        ax.plot(x, y, color=col, ls=ls, lw=1.3)
                        any_line = True
                if certified_marks is not None and mat == "A":
                    mark = certified_marks(system, i)
                    if mark is not None:
                        ax.axvline(mark, color=col, ls=(0, (1, 2)), lw=2.2, alpha=0.8)
            if not any_line:
                _no_data(
                    ax,
                    _reason(
                        cols,
                        _mask_any(series, system, cols.n),
                        (f"{mat}_hat", f"r_{mat}", f"eps_{mat}"),
                        meta,
                    ),
                )
                continue
            ax.axhline(0.0, color="0.5", lw=0.6)
            ax.set_yscale("symlog", linthresh=1e-2)
            ax.minorticks_off()
            ax.set_ylabel(f"{mat}: error / interval ends / ε_{mat}")
            ax.set_title(f"{system}: {mat}", fontsize=10)
            if r == 1:
                _x_axis(ax, ratio)
            ax.grid(alpha=0.3)


def _mask_any(series, system, n):
    m = np.zeros(n, bool)
    for _, mk in series:
        m |= mk(system)
    return m


def _style_handles(extra_vertical: bool = False):
    h = [
        _line("0.2", "-", "max_ij |ΔX_ij| (mean over reps)"),
        _line("0.2", "--", "Lemma 2 interval ends: max_ij γX̃_ij + r_X, min_ij γX̃_ij − r_X"),
        _line("0.2", ":", "ε_X (Corollary 1)"),
    ]
    if extra_vertical:
        from matplotlib.lines import Line2D

        h.append(
            Line2D(
                [],
                [],
                color="0.2",
                ls=(0, (1, 2)),
                lw=2.2,
                label="first N0 with stable_certified in ≥ half the reps (A row)",
            )
        )
    return h


def fig2(records, spec=None, *, experiment: str | None = "E1", gamma: float | None = None):
    """Fig. 2: SVR (γ = 0.05) estimation error and Lemma 2 interval ends vs N0,
    S and U, one color per σ_w; ε_A, ε_B of Corollary 1 dotted."""
    cols, meta = as_columns(records), _meta(spec)
    g = _table_gamma(cols, gamma)
    systems = _systems(cols) or ["(none)"]
    sig = _sigmas(cols)
    fig, axes = _figure(2, len(systems), (5.6 * len(systems), 8), sharex=True)
    series = (
        [
            (
                f"σ_w={_fmt(s)}",
                (
                    lambda system, s=s: _mask(
                        cols, system=system, estimator="svr", gamma=g, sigma_w=s
                    )
                ),
            )
            for s in sig
        ]
        if g is not None
        else []
    )
    _interval_panels(fig, axes, cols, meta, series, "σ_w", systems, _n0_ratio(cols))
    handles = [_line(f"C{i}", "-", lab) for i, (lab, _) in enumerate(series)] + _style_handles()
    _legend(fig, handles, ncol=3)
    _title(
        fig,
        f"Fig. 2: SVR (γ={_fmt(g)}) estimation error and Lemma 2 interval ends vs "
        f"sample length, for each σ_w",
        experiment,
        meta,
    )
    return fig


def fig3(records, spec=None, *, experiment: str | None = "E2", sigma_w: float | None = None):
    """Fig. 3: as Fig. 2 for the four gammas at one σ_w (default 1), with the
    first N0 at which stable_certified holds in ≥ half the reps ("never" else)."""
    cols, meta = as_columns(records), _meta(spec)
    sig = _sigmas(cols)
    if sigma_w is None:
        sigma_w = 1.0 if any(math.isclose(s, 1.0) for s in sig) else (sig[0] if sig else None)
    systems = _systems(cols) or ["(none)"]
    gs = _gammas(cols)
    fig, axes = _figure(2, len(systems), (5.6 * len(systems), 8.4), sharex=True)
    series = [
        (
            g,
            (
                lambda system, g=g: _mask(
                    cols, system=system, estimator="svr", gamma=g, sigma_w=sigma_w
                )
            ),
        )
        for g in gs
    ]
    first = first_stable_certified(cols) if sigma_w is not None else {}

    def mark(system, i):
        hit = first.get((system, sigma_w, "svr", gs[i]))
        return None if hit is None or hit["N0"] is None else hit["N0"]

    _interval_panels(
        fig, axes, cols, meta, series, "γ", systems, _n0_ratio(cols), certified_marks=mark
    )
    handles = []
    for i, g in enumerate(gs):
        parts = []
        for system in systems:
            hit = first.get((system, sigma_w, "svr", g))
            if hit is None:
                parts.append(f"{system}: no data")
            elif hit["N0"] is None:
                parts.append(f"{system}: never (N0 ≤ {hit['N0_max']})")
            else:
                parts.append(f"{system}: from N0={hit['N0']}")
        handles.append(_line(f"C{i}", "-", f"γ={_fmt(g)} — certified stable " + "; ".join(parts)))
    handles += _style_handles(extra_vertical=True)
    _legend(fig, handles, ncol=2)
    _title(
        fig,
        f"Fig. 3: SVR estimation error and Lemma 2 interval ends for each γ (σ_w={_fmt(sigma_w)})",
        experiment,
        meta,
    )
    return fig


def _pick_system(cols: Columns, prefer: str, field_: str) -> str | None:
    systems = _systems(cols)
    if prefer in systems:
        return prefer
    for s in systems:
        if cols.has(field_, _mask(cols, system=s)):
            return s
    return systems[0] if systems else None


def fig4(records, spec=None, *, experiment: str | None = "E3", system: str = STABLE):
    """Fig. 4: ΔJ = J_b − J vs N0 for each γ on S (mean, 5-95 % band), and the
    share of cells with ΔJ < 0."""
    cols, meta = as_columns(records), _meta(spec)
    system = _pick_system(cols, system, "delta_J")
    fig, axes = _figure(1, 2, (12, 5))
    ax, ax2 = axes[0]
    ms = _mask(cols, system=system) if system else np.zeros(cols.n, bool)
    gs = _gammas(cols, ms)
    ratio = _n0_ratio(cols, ms)
    handles = []
    if not cols.has("delta_J", ms):
        reason = _reason(cols, ms, ("delta_J", "J_bound", "J_exact"), meta)
        _no_data(ax, reason)
        _no_data(ax2, reason)
    else:
        dJ = cols["delta_J"]
        for i, g in enumerate(gs):
            m = ms & _mask(cols, estimator="svr", gamma=g)
            x, _, mean, _ = _by_N(cols, m, dJ, _mean)
            _, _, q05, _ = _by_N(cols, m, dJ, lambda v: float(np.quantile(v, 0.05)))
            _, _, q95, _ = _by_N(cols, m, dJ, lambda v: float(np.quantile(v, 0.95)))
            _, _, neg, _ = _by_N(cols, m, dJ, lambda v: float(np.mean(v < 0)))
            n_neg = int(np.sum((dJ[m] < 0) & np.isfinite(dJ[m])))
            n_all = int(np.isfinite(dJ[m]).sum())
            ax.plot(x, mean, color=f"C{i}", lw=1.4)
            ax.fill_between(x, q05, q95, color=f"C{i}", alpha=0.15, lw=0)
            ax2.plot(x, neg, color=f"C{i}", lw=1.4)
            handles.append(_line(f"C{i}", "-", f"γ={_fmt(g)} (ΔJ<0 in {n_neg} of {n_all} cells)"))
        ax.axhline(0, color="k", lw=0.8)
        ax.set_ylabel("ΔJ = J_b − J (mean over reps; band 5-95 %)")
        ax.set_yscale("symlog", linthresh=1e-2)
        ax.minorticks_off()
        ax2.set_ylabel("share of repetitions with ΔJ < 0")
        ax2.set_ylim(-0.02, 1.02)
        for a in (ax, ax2):
            _x_axis(a, ratio)
            a.grid(alpha=0.3)
        ax.set_title(f"{system}: bound minus exact cost", fontsize=10)
        ax2.set_title(f"{system}: where Theorem 3's bound fails", fontsize=10)
    _legend(fig, handles, ncol=2)
    _title(fig, f"Fig. 4: ΔJ = J_b − J vs sample length for each γ on {system}", experiment, meta)
    return fig


def cost_ratio_of_means(cols: Columns, system: str, gamma: float, gamma_ref: float):
    """r(N) = |mean J_γ − mean J_ref| / mean J_ref with J the exact cost (SPEC 9)."""
    J = cols["J_exact"]
    m = _mask(cols, system=system, estimator="svr", gamma=gamma)
    mr = _mask(cols, system=system, estimator="svr", gamma=gamma_ref)
    x, Ns, mean, _ = _by_N(cols, m, J, _mean)
    _, Nr, mean_r, _ = _by_N(cols, mr, J, _mean)
    ref = dict(zip(Nr.tolist(), mean_r.tolist()))
    r = np.array(
        [
            abs(v - ref[n]) / ref[n] if ref.get(n) else np.nan
            for n, v in zip(Ns.tolist(), mean.tolist())
        ]
    )
    return x, Ns, r


def fig5(records, spec=None, *, experiment: str | None = "E4"):
    """Fig. 5: cost ratio r = |mean J_γ − mean J_ref| / mean J_ref vs N0, S and U
    (solid); the mean of the per-repetition ``cost_ratio`` field dashed."""
    cols, meta = as_columns(records), _meta(spec)
    systems = _systems(cols) or ["(none)"]
    g_ref = meta.gamma_ref
    fig, axes = _figure(1, len(systems), (5.8 * len(systems), 5), sharey=True)
    gs = _gammas(cols)
    handles = [
        _line(f"C{i}", "-", f"γ={_fmt(g)}")
        for i, g in enumerate(gs)
        if not math.isclose(g, g_ref, rel_tol=_GAMMA_RTOL)
    ]
    for c, system in enumerate(systems):
        ax = axes[0, c]
        ms = _mask(cols, system=system)
        if not cols.has("J_exact", ms):
            _no_data(ax, _reason(cols, ms, ("J_exact",), meta))
            continue
        if not cols.has("J_exact", ms & _mask(cols, gamma=g_ref)):
            _no_data(ax, f"no J at the reference γ_ref={_fmt(g_ref)}")
            continue
        for i, g in enumerate(gs):
            if math.isclose(g, g_ref, rel_tol=_GAMMA_RTOL):
                continue
            x, _, r = cost_ratio_of_means(cols, system, g, g_ref)
            ax.plot(x, r, color=f"C{i}", lw=1.4)
            m = ms & _mask(cols, estimator="svr", gamma=g)
            if cols.has("cost_ratio", m):
                x2, _, y2, _ = _by_N(cols, m, cols["cost_ratio"], _mean)
                ax.plot(x2, y2, color=f"C{i}", lw=0.9, ls="--", alpha=0.7)
        ax.set_yscale("log")
        ax.minorticks_off()
        ax.set_ylabel(f"r = |J_γ − J_ref| / J_ref  (γ_ref = {_fmt(g_ref)})")
        ax.set_title(system, fontsize=10)
        _x_axis(ax, _n0_ratio(cols, ms))
        ax.grid(alpha=0.3, which="both")
    handles += [
        _line("0.2", "-", "ratio of the mean exact costs (SPEC 9)"),
        _line("0.2", "--", "mean of per-repetition cost_ratio"),
    ]
    _legend(fig, handles, ncol=len(handles))
    _title(
        fig,
        f"Fig. 5: observer cost ratio vs sample length (reference γ={_fmt(g_ref)})",
        experiment,
        meta,
    )
    return fig


def fig_coverage(records, spec=None, *, experiment: str | None = "E2"):
    """Empirical coverage of the Lemma 2 intervals vs N0 with the 1 − δ line:
    rows A, B; columns (system, σ_w); one line per estimator / γ."""
    cols, meta = as_columns(records), _meta(spec)
    systems = _systems(cols) or ["(none)"]
    sig = _sigmas(cols) or [None]
    rows_ = [(system, mat) for system in systems for mat in ("A", "B")]
    fig, axes = _figure(
        len(rows_),
        len(sig),
        (3.9 * len(sig) + 0.8, 2.6 * len(rows_) + 1.2),
        sharex=True,
        sharey=True,
    )
    series = [
        (est, g)
        for est, g in ([("ols", None)] if np.any(cols["estimator"] == "ols") else [])
        + [("svr", g) for g in _gammas(cols)]
    ]
    level = 1 - meta.delta
    lows = [level]
    for r, (system, mat) in enumerate(rows_):
        for c, s in enumerate(sig):
            ax = axes[r, c]
            f = f"coverage_{mat}"
            ms = _mask(cols, system=system, sigma_w=s) if s is not None else np.zeros(cols.n, bool)
            if not cols.has(f, ms):
                _no_data(ax, _reason(cols, ms, (f,), meta))
                continue
            for i, (est, g) in enumerate(series):
                m = ms & _mask(cols, estimator=est, gamma=g)
                x, _, y, _ = _by_N(cols, m, cols[f], _mean)
                ax.plot(x, y, color=f"C{i}", lw=1.3, marker="." if len(x) < 8 else None)
                if np.isfinite(y).any():
                    lows.append(float(np.nanmin(y)))
            ax.axhline(level, color="k", ls="--", lw=1)
            ax.set_title(f"{system}, σ_w={_fmt(s)}: {mat}", fontsize=9)
            if c == 0:
                ax.set_ylabel(f"coverage of {mat}_ij intervals", fontsize=9)
            if r == len(rows_) - 1:
                _x_axis(ax, _n0_ratio(cols, ms))
            ax.grid(alpha=0.3)
    axes[0, 0].set_ylim(min(lows) - 0.03, 1.01)
    handles = [_line(f"C{i}", "-", _gamma_label(e, g)) for i, (e, g) in enumerate(series)]
    handles.append(_line("k", "--", f"1 − δ = {_fmt(level)}"))
    _legend(fig, handles, ncol=len(handles))
    _title(
        fig,
        "Empirical coverage of the Lemma 2 entry intervals (mean share of entries "
        "inside, over reps)",
        experiment,
        meta,
    )
    return fig


def fig_certified(records, spec=None, *, experiment: str | None = "E4"):
    """Share of repetitions whose observer gain L is certified (g(L) < 1), and
    the share with ρ(A − LC) < 1 for the true A, vs N0 per γ."""
    cols, meta = as_columns(records), _meta(spec)
    systems = _systems(cols) or ["(none)"]
    fig, axes = _figure(1, len(systems), (5.6 * len(systems), 5), sharey=True)
    gs = _gammas(cols)
    for c, system in enumerate(systems):
        ax = axes[0, c]
        ms = _mask(cols, system=system)
        if not cols.has("certified", ms):
            _no_data(ax, _reason(cols, ms, ("certified", "g_L"), meta))
            continue
        rho = cols["rho_true"]
        stable = np.where(np.isfinite(rho), (rho < 1).astype(float), np.nan)
        for i, g in enumerate(gs):
            m = ms & _mask(cols, estimator="svr", gamma=g)
            x, _, y, _ = _by_N(cols, m, cols["certified"], _mean)
            ax.plot(x, y, color=f"C{i}", lw=1.4)
            if np.isfinite(rho[m]).any():
                x2, _, y2, _ = _by_N(cols, m, stable, _mean)
                ax.plot(x2, y2, color=f"C{i}", lw=0.9, ls="--", alpha=0.7)
        ax.set_ylim(-0.02, 1.02)
        ax.set_ylabel("share of repetitions")
        ax.set_title(system, fontsize=10)
        _x_axis(ax, _n0_ratio(cols, ms))
        ax.grid(alpha=0.3)
    handles = [_line(f"C{i}", "-", f"γ={_fmt(g)}") for i, g in enumerate(gs)]
    handles += [
        _line("0.2", "-", "certified: g(L) < 1 (Theorem 2 on the Lemma 2 box)"),
        _line("0.2", "--", "ρ(A − LC) < 1 for the true A"),
    ]
    _legend(fig, handles, ncol=3)
    _title(fig, "Share of certified observer gains vs sample length", experiment, meta)
    return fig


def fig_svr_ols_diff(records, spec=None, *, experiment: str | None = "E2"):
    """max_ij |Ã_svr − Ã_ols| on the same data (mean over reps) vs N0, per γ
    (color) and σ_w (line style): where SVR and OLS really differ."""
    cols, meta = as_columns(records), _meta(spec)
    systems = _systems(cols) or ["(none)"]
    fig, axes = _figure(1, len(systems), (5.8 * len(systems), 5.2), sharey=True)
    d = _svr_ols_diff(cols)
    gs = _gammas(cols)
    sig = _sigmas(cols)
    styles = ["-", "--", ":", "-."]
    for c, system in enumerate(systems):
        ax = axes[0, c]
        ms = _mask(cols, system=system)
        if not np.isfinite(d[ms]).any():
            why = (
                "needs OLS and SVR estimates (A_hat) of the same repetitions"
                if cols.has("rmse_A", ms)
                else _reason(cols, ms, ("A_hat",), meta)
            )
            _no_data(ax, why)
            continue
        for i, g in enumerate(gs):
            for j, s in enumerate(sig):
                m = ms & _mask(cols, estimator="svr", gamma=g, sigma_w=s)
                x, _, y, _ = _by_N(cols, m, d, _mean)
                if np.isfinite(y).any():
                    ax.plot(x, y, color=f"C{i}", ls=styles[j % 4], lw=1.3)
        ax.set_yscale("log")
        ax.minorticks_off()
        ax.set_ylabel("max_ij |Ã_SVR − Ã_OLS| (mean over reps)")
        ax.set_title(system, fontsize=10)
        _x_axis(ax, _n0_ratio(cols, ms))
        ax.grid(alpha=0.3, which="both")
    handles = [_line(f"C{i}", "-", f"γ={_fmt(g)}") for i, g in enumerate(gs)]
    handles += [_line("0.2", styles[j % 4], f"σ_w={_fmt(s)}") for j, s in enumerate(sig)]
    _legend(fig, handles, ncol=len(handles))
    _title(fig, "SVR minus OLS: largest entry difference of Ã on the same data", experiment, meta)
    return fig


# ---------------------------------------------------------------------------
# findings
# ---------------------------------------------------------------------------


def _pct(k: int, n: int) -> str:
    return f"{k} of {n} ({100.0 * k / n:.1f} %)" if n else f"{k} of 0"


def _stage_findings(cols: Columns, meta: _Meta) -> list[str]:
    out = []
    for stage in meta.stages:
        fs = STAGE_FIELDS.get(stage, ())
        if fs and not any(cols.has(f) for f in fs):
            notes = [v for v in cols["notes"] if v]
            extra = f' Notes on the records: "{notes[0][:120]}".' if notes else ""
            out.append(
                f"[no data] Stage '{stage}' is in the spec but its fields "
                f"({', '.join(fs)}) are null in all {cols.n} records.{extra}"
            )
    return out


def _f_svr_vs_ols(cols: Columns) -> list[str]:
    out = []
    if not (
        cols.has("rmse_A")
        and np.any(cols["estimator"] == "ols")
        and np.any(cols["estimator"] == "svr")
    ):
        return out
    claim = PUBLISHED_CLAIMS["svr_beats_ols_large_noise"]
    gs = _gammas(cols)
    wins = 0
    cells = 0
    max_rel = 0.0
    for system in _systems(cols):
        for s in _sigmas(cols, _mask(cols, system=system)):
            parts = []
            for mat in ("A", "B"):
                f = f"rmse_{mat}"
                base, _, _ = _avg_over_reps_then_N(
                    cols, _mask(cols, system=system, estimator="ols", sigma_w=s), f
                )
                if base is None:
                    continue
                better = []
                for g in gs:
                    v, _, _ = _avg_over_reps_then_N(
                        cols, _mask(cols, system=system, estimator="svr", gamma=g, sigma_w=s), f
                    )
                    if v is None:
                        continue
                    cells += 1
                    max_rel = max(max_rel, abs(v - base) / base if base else 0.0)
                    if v < base:
                        better.append(g)
                        wins += 1
                parts.append(
                    f"{mat}: {len(better)} of {len(gs)} γ"
                    + (f" ({', '.join(_fmt(g) for g in better)})" if better else "")
                )
            out.append(
                f"[info] SVR beats OLS in mean RMSE for {system}, σ_w={_fmt(s)}: "
                + "; ".join(parts)
                + "."
            )
    # the paper's claim, at the largest noise level
    top = max(_sigmas(cols))
    k = n = 0
    for system in _systems(cols):
        for mat in ("A", "B"):
            f = f"rmse_{mat}"
            base, _, _ = _avg_over_reps_then_N(
                cols, _mask(cols, system=system, estimator="ols", sigma_w=top), f
            )
            for g in gs:
                v, _, _ = _avg_over_reps_then_N(
                    cols, _mask(cols, system=system, estimator="svr", gamma=g, sigma_w=top), f
                )
                if base is not None and v is not None:
                    n += 1
                    k += v < base
    status = "holds" if n and k == n else ("does not hold" if k == 0 else "partly")
    out.insert(
        0,
        (
            f'[{status}] Paper ({claim["where"]}): "{claim["quote"]}". Here, at σ_w={_fmt(top)}, '
            f"SVR has the lower mean RMSE in {_pct(k, n)} (system, matrix, γ) cells; over all "
            f"{cells} cells SVR wins {wins}. The largest relative RMSE difference between SVR and "
            f"OLS anywhere is {100 * max_rel:.3g} %."
        ),
    )
    return out


def _f_coverage(cols: Columns, meta: _Meta) -> list[str]:
    out = []
    level = 1 - meta.delta
    claim = PUBLISHED_CLAIMS["lemma2_intervals"]
    for mat in ("A", "B"):
        f = f"coverage_{mat}"
        if not cols.has(f):
            continue
        groups = _groupby(cols, GROUP_FIELDS, np.isfinite(cols[f]))
        below = []
        for key, idx in groups.items():
            mcov = float(np.mean(cols[f][idx]))
            if mcov < level:
                below.append((mcov, key))
        rec_miss = int(np.sum(cols[f][np.isfinite(cols[f])] < 1))
        n_rec = int(np.isfinite(cols[f]).sum())
        status = "holds" if not below else "does not hold"
        text = (
            f"[{status}] Lemma 2 intervals for {mat} (paper, {claim['where']}: "
            f'"{claim["quote"]}"): mean empirical coverage is below 1 − δ = {_fmt(level)} '
            f"in {_pct(len(below), len(groups))} groups (system, σ_w, N, estimator, γ); "
            f"{_pct(rec_miss, n_rec)} records have at least one entry of {mat} outside "
            f"its interval."
        )
        if below:
            below.sort(key=lambda t: t[0])
            worst = ", ".join(
                f"{k[0]} σ_w={_fmt(k[1])} N={_fmt(k[2])} {_gamma_label(k[3], k[4])}: {_fmt(c, 3)}"
                for c, k in below[:3]
            )
            text += f" Lowest: {worst}."
        out.append(text)
    return out


def _f_theorem1(cols: Columns, meta: _Meta) -> list[str]:
    out = []
    for mat in ("A", "B"):
        f = f"thm1_holds_{mat}"
        v = cols[f]
        ok = np.isfinite(v)
        n = int(ok.sum())
        if not n:
            continue
        k = int(np.sum(v[ok] == 0))
        rate = k / n
        status = "holds" if k == 0 else ("partly" if rate <= meta.delta else "does not hold")
        per = []
        for (est, g), idx in _groupby(cols, ("estimator", "gamma"), ok).items():
            kk = int(np.sum(v[idx] == 0))
            per.append(f"{_gamma_label(est, g)}: {kk}/{idx.size}")
        out.append(
            f"[{status}] Theorem 1 for {mat} (every row): violated in {_pct(k, n)} "
            f"records (the theorem allows probability δ = {_fmt(meta.delta)}). "
            f"By estimator: {'; '.join(per)}."
        )
    return out


def _f_stable_certified(cols: Columns, meta: _Meta) -> list[str]:
    out = []
    if not cols.has("stable_certified"):
        return out
    claim = PUBLISHED_CLAIMS["stable_after_sample_length"]
    first = first_stable_certified(cols)
    by_sys: dict[str, list[str]] = {}
    never: dict[str, list[str]] = {}
    n_max: dict[str, int] = {}
    earliest = None
    for (system, s, est, g), hit in first.items():
        label = f"σ_w={_fmt(s)} {_gamma_label(est, g)}"
        by_sys.setdefault(system, [])
        n_max[system] = max(n_max.get(system, 0), hit["N_max"])
        if hit["N0"] is None:
            never.setdefault(system, []).append(label)
        else:
            by_sys[system].append(f"{label}: N={hit['N']} (N0={hit['N0']})")
            if system == claim["system"]:
                earliest = hit["N0"] if earliest is None else min(earliest, hit["N0"])
    for system, parts in by_sys.items():
        nv = never.get(system, [])
        total = len(parts) + len(nv)
        text = (
            f"[info] First N at which stable_certified (ρ upper bound < 1) holds in ≥ half "
            f"the repetitions, {system}: "
        )
        if parts:
            text += "; ".join(parts) + ". "
        if nv:
            which = "all" if not parts else f"{len(nv)} of {total}"
            text += (
                f"Never in the grid (N ≤ {n_max[system]}) for {which} (σ_w, estimator) "
                f"combinations" + (f": {', '.join(nv)}." if parts else ".")
            )
        out.append(text.strip())
    if claim["system"] in by_sys:
        pub = claim["sample_length"]
        n0_max = max(h["N0_max"] for k, h in first.items() if k[0] == claim["system"])
        if earliest is not None and earliest <= pub:
            status = "holds"
        elif earliest is None and n0_max < pub:
            status = "no data"  # the grid stops before the paper's sample length
        else:
            status = "does not hold"
        got = (
            f"never in the grid (N0 ≤ {n0_max})"
            if earliest is None
            else f"from N0={earliest} at the earliest"
        )
        out.insert(
            0,
            f'[{status}] Paper ({claim["where"]}, published): "{claim["quote"]}" '
            f"(sample length {pub}). Here, with the sound Perron-Frobenius certificate "
            f"of SPEC section 3, {claim['system']} is certified stable {got}.",
        )
    # soundness: a certificate of stability for a truly unstable A is a false positive
    sc = cols["stable_certified"]
    for system in _systems(cols):
        truth = meta.truth.get(system)
        if truth is None:
            continue
        rho = float(np.max(np.abs(np.linalg.eigvals(truth[0]))))
        if rho >= 1:
            m = _mask(cols, system=system) & np.isfinite(sc)
            k = int(np.sum(sc[m] == 1))
            status = "holds" if k == 0 else "does not hold"
            out.append(
                f"[{status}] Soundness on {system} (true ρ(A) = {_fmt(rho)}): "
                f"stable_certified is true in {_pct(k, int(m.sum()))} records."
            )
    return out


def _f_cost(cols: Columns, meta: _Meta) -> list[str]:
    out = []
    dJ = cols["delta_J"]
    if cols.has("delta_J"):
        claim = PUBLISHED_CLAIMS["delta_j_positive"]
        for system in _systems(cols):
            ms = _mask(cols, system=system) & np.isfinite(dJ)
            if not ms.any():
                continue
            n = int(ms.sum())
            k = int(np.sum(dJ[ms] < 0))
            per = []
            neg_groups = 0
            groups = _groupby(cols, ("gamma", "N"), ms)
            for g in _gammas(cols, ms):
                m = ms & _mask(cols, gamma=g)
                per.append(f"γ={_fmt(g)}: {int(np.sum(dJ[m] < 0))}/{int(m.sum())}")
            for idx in groups.values():
                neg_groups += float(np.mean(dJ[idx])) < 0
            status = "holds" if k == 0 else ("does not hold" if neg_groups else "partly")
            out.append(
                f'[{status}] Paper ({claim["where"]}): "{claim["quote"]}". On {system}, '
                f"ΔJ = J_b − J < 0 in {_pct(k, n)} cells ({'; '.join(per)}); the mean ΔJ "
                f"over repetitions is negative in {_pct(neg_groups, len(groups))} "
                f"(γ, N) groups."
            )
    J = cols["J_exact"]
    if cols.has("J_exact"):
        claim = PUBLISHED_CLAIMS["cost_variance_small_gamma"]
        for system in _systems(cols):
            ms = _mask(cols, system=system) & np.isfinite(J)
            gs = _gammas(cols, ms)
            if len(gs) < 2:
                continue
            stds = []
            for g in gs:
                m = ms & _mask(cols, gamma=g)
                _, _, sd, _ = _by_N(cols, m, J, lambda v: float(np.std(v)))
                stds.append(float(np.nanmean(sd)) if np.isfinite(sd).any() else np.nan)
            dec = all(a > b for a, b in zip(stds, stds[1:]))
            ratio = stds[0] / stds[-1] if stds[-1] else float("nan")
            # "much larger": decreasing in gamma and at least twice as large at the
            # smallest gamma as at the largest; "partly" if only larger
            if dec and ratio >= 2:
                status = "holds"
            elif ratio > 1:
                status = "partly"
            else:
                status = "does not hold"
            out.append(
                f'[{status}] Paper ({claim["where"]}): "{claim["quote"]}". On {system}, '
                f"the standard deviation of J over repetitions (mean over N) is "
                + ", ".join(f"γ={_fmt(g)}: {_fmt(v, 3)}" for g, v in zip(gs, stds))
                + f"; smallest-γ / largest-γ ratio {_fmt(ratio, 3)} (counted as holding "
                f"when decreasing in γ with a ratio of at least 2)."
            )
    mc, se = cols["J_mc"], cols["J_mc_se"]
    ok = np.isfinite(mc) & np.isfinite(se) & np.isfinite(J)
    if ok.any():
        bad = int(np.sum(np.abs(mc[ok] - J[ok]) > 4 * se[ok]))
        status = "holds" if bad == 0 else "does not hold"
        out.append(
            f"[{status}] Monte Carlo J agrees with the exact finite-horizon J within "
            f"4 standard errors in {_pct(int(ok.sum()) - bad, int(ok.sum()))} records "
            f"that have a Monte Carlo estimate."
        )
    if cols.has("certified"):
        cert = cols["certified"]
        for system in _systems(cols):
            ms = _mask(cols, system=system) & np.isfinite(cert)
            if not ms.any():
                continue
            per = []
            for g in _gammas(cols, ms):
                m = ms & _mask(cols, gamma=g)
                per.append(f"γ={_fmt(g)}: {_pct(int(np.sum(cert[m] == 1)), int(m.sum()))}")
            rho = cols["rho_true"]
            mm = ms & (cert == 1) & np.isfinite(rho)
            unsound = int(np.sum(rho[mm] >= 1))
            if not mm.any():
                status, tail = "info", "No certified gain, so their soundness is not tested here."
            else:
                status = "holds" if unsound == 0 else "does not hold"
                tail = (
                    f"Certified gains with ρ(A − LC) ≥ 1 for the true A: "
                    f"{_pct(unsound, int(mm.sum()))}."
                )
            out.append(
                f"[{status}] Certified gains (g(L) < 1) on {system}: "
                + "; ".join(per)
                + ". "
                + tail
            )
    return out


def _f_svr_ols_diff(cols: Columns) -> list[str]:
    d = _svr_ols_diff(cols)
    if not np.isfinite(d).any():
        return []
    parts = []
    for g in _gammas(cols):
        m = _mask(cols, estimator="svr", gamma=g) & np.isfinite(d)
        if m.any():
            parts.append(
                f"γ={_fmt(g)}: max {_fmt(float(d[m].max()), 3)}, "
                f"median {_fmt(float(np.median(d[m])), 3)}"
            )
    return [
        "[info] SVR and OLS estimates of A on the same data differ by at most (largest "
        "entry difference over all records): " + "; ".join(parts) + "."
    ]


def _f_notes(cols: Columns) -> list[str]:
    codes, values = cols.codes("notes")
    per_value = np.bincount(codes, minlength=len(values)).tolist()
    n_notes = sum(c for v, c in zip(values, per_value) if v)
    if not n_notes:
        return []
    counts: dict[str, int] = {}
    for v, c in zip(values, per_value):
        if not v:
            continue
        for part in str(v).split("; "):
            counts[part] = counts.get(part, 0) + c
    notes = range(n_notes)
    top = sorted(counts.items(), key=lambda kv: -kv[1])[:4]
    return [
        f"[info] {_pct(len(notes), cols.n)} records carry notes (null fields and why): "
        + "; ".join(f'"{k[:100]}" ×{v}' for k, v in top)
        + "."
    ]


def findings(records, spec=None) -> list[str]:
    """Statements generated from the data: where the paper's claims hold here and
    where not, with counts. Each starts with [holds], [does not hold], [partly],
    [no data] or [info]."""
    cols, meta = as_columns(records), _meta(spec)
    if cols.n == 0:
        return ["[no data] No records."]
    out: list[str] = []
    out += _stage_findings(cols, meta)
    out += _f_svr_vs_ols(cols)
    out += _f_coverage(cols, meta)
    out += _f_theorem1(cols, meta)
    out += _f_stable_certified(cols, meta)
    out += _f_cost(cols, meta)
    out += _f_svr_ols_diff(cols)
    out += _f_notes(cols)
    return out


# ---------------------------------------------------------------------------
# the whole report
# ---------------------------------------------------------------------------


@dataclass
class ReportFigure:
    name: str
    title: str
    caption: str
    experiment: str
    figure: object  # matplotlib.figure.Figure
    _png: bytes | None = None
    _svg: bytes | None = None

    def png(self) -> bytes:
        if self._png is None:
            self._png = figure_bytes(self.figure, "png")
            # the constrained layout is computed by that first draw; keep it fixed
            # so the SVG (and any later render) skips the second layout pass
            self.figure.set_layout_engine("none")
        return self._png

    def svg(self) -> bytes:
        if self._svg is None:
            self.png()
            self._svg = figure_bytes(self.figure, "svg")
        return self._svg

    def set_rendered(self, png: bytes, svg: bytes):
        """Bytes rendered elsewhere (e.g. :func:`render_figure` in another process)."""
        self._png, self._svg = png, svg


def render_figure(fig) -> tuple[bytes, bytes]:
    """(PNG, SVG) of a Figure, as ``ReportFigure.png()``/``svg()`` give them
    (picklable: figures can be rendered in worker processes)."""
    rf = ReportFigure("", "", "", "", fig)
    return rf.png(), rf.svg()


@dataclass
class Report:
    title: str
    experiments: dict[str, dict]  # name -> {title, spec, n_records, findings, notes}
    table2: list[dict]
    table2_source: str | None
    figures: list[ReportFigure]
    provenance: dict


# name, function, preferred experiments, fields it needs, title, caption
FIGURE_PLAN = (
    (
        "fig_rmse",
        fig_rmse,
        ("E1",),
        ("rmse_A",),
        "RMSE per sample length (Table 2 curves)",
        "Mean RMSE of Ã and B̃ over repetitions at each N, OLS (solid) and SVR (dashed).",
    ),
    (
        "fig2",
        fig2,
        ("E1", "E2"),
        ("A_hat", "r_A"),
        "Fig. 2: estimation error and Lemma 2 interval ends, γ = 0.05",
        "Solid: max_ij |ΔX_ij| with ΔX = X − X̃; dashed: the envelope "
        "of the Lemma 2 intervals γX̃_ij ± r_X; dotted: ε_X of Corollary 1. Means over repetitions.",
    ),
    (
        "fig3",
        fig3,
        ("E2",),
        ("A_hat", "r_A"),
        "Fig. 3: the same for the four γ",
        "As Fig. 2, one color per γ, at σ_w = 1; the dotted vertical line marks the first N0 at "
        "which stable_certified holds in at least half of the repetitions.",
    ),
    (
        "fig4",
        fig4,
        ("E3", "E4"),
        ("delta_J",),
        "Fig. 4: ΔJ = J_b − J on S",
        "Left: mean ΔJ over repetitions with the 5-95 % band; right: share of repetitions where "
        "Theorem 3's bound is below the exact cost (ΔJ < 0).",
    ),
    (
        "fig5",
        fig5,
        ("E4", "E3"),
        ("J_exact",),
        "Fig. 5: cost ratio",
        "r = |mean J_γ − mean J_ref| / mean J_ref with J the exact finite-horizon cost (solid) "
        "and the mean of the per-repetition cost_ratio (dashed).",
    ),
    (
        "fig_coverage",
        fig_coverage,
        ("E2", "E1"),
        ("coverage_A",),
        "Beyond the paper: empirical coverage of the Lemma 2 intervals",
        "Mean share of the entries of A (B) inside their Lemma 2 interval, with the 1 − δ line.",
    ),
    (
        "fig_certified",
        fig_certified,
        ("E4", "E3"),
        ("certified",),
        "Beyond the paper: share of certified observer gains",
        "Share of repetitions with g(L) < 1 (solid) and with ρ(A − LC) < 1 for the true A "
        "(dashed).",
    ),
    (
        "fig_svr_ols_diff",
        fig_svr_ols_diff,
        ("E2", "E1"),
        ("A_hat",),
        "Beyond the paper: SVR minus OLS on the same data",
        "Mean over repetitions of max_ij |Ã_SVR − Ã_OLS|, per γ and σ_w: where SVR and OLS "
        "really differ.",
    ),
)


def _records_of(exp: dict) -> Columns:
    return as_columns(exp["records"])


def _choose_source(experiments: dict[str, dict], cols: dict[str, Columns], prefer, needs):
    for name in prefer:
        if name in experiments:
            return name
    for name in experiments:
        if all(cols[name].has(f) for f in needs):
            return name
    return next(iter(experiments), None)


def build_report(
    experiments: dict[str, dict],
    provenance: dict | None = None,
    title: str | None = None,
    *,
    render: Callable[[object], Any] | None = None,
) -> Report:
    """``experiments``: name -> {"spec": dict, "records": list|Columns, optional
    "title", "notes" (list[str], e.g. stages that could not run)}.

    ``render``: optional ``fig -> future`` (e.g. ``pool.submit(render_figure, fig)``);
    each figure is handed to it as soon as it is built, so that rendering runs
    elsewhere while the rest is computed; the futures' ``(png, svg)`` are
    collected at the end."""
    builder = ReportBuilder(list(experiments), provenance, title, render=render)
    for name, e in experiments.items():
        builder.add(name, e)
    return builder.finish()


class ReportBuilder:
    """:func:`build_report` in steps, for experiments whose records arrive one
    group at a time: ``add(name, experiment)`` computes that experiment's
    findings and the figures drawn from it (their source is decided from the
    experiment names given up front, as :func:`build_report` decides it);
    ``finish()`` returns the :class:`Report`, the same as :func:`build_report`
    on all experiments."""

    def __init__(
        self,
        names,
        provenance: dict | None = None,
        title: str | None = None,
        *,
        render: Callable[[object], Any] | None = None,
    ):
        self.names = list(names)
        self.provenance = provenance
        self.title = title
        self.render = render
        self.experiments: dict[str, dict] = {}
        self.cols: dict[str, Columns] = {}
        self.exps: dict[str, dict] = {}
        self.figs: dict[int, tuple[ReportFigure, Any]] = {}

    def _source(self, prefer, needs, final: bool):
        for name in prefer:
            if name in self.names:
                return name
        if not final:
            return None  # decided on the data, once every experiment is there
        ordered = {n: self.experiments[n] for n in self.names if n in self.experiments}
        return _choose_source(ordered, self.cols, prefer, needs)

    def _figures(self, final: bool):
        for i, (name, fn, prefer, needs, ftitle, caption) in enumerate(FIGURE_PLAN):
            if i in self.figs:
                continue
            src = self._source(prefer, needs, final)
            if src is None or src not in self.experiments:
                continue
            fig = fn(
                self.cols[src],
                self.experiments[src].get("spec"),
                experiment=_exp_label(src, self.provenance),
            )
            fut = self.render(fig) if self.render is not None else None
            self.figs[i] = (ReportFigure(name, ftitle, caption, src, fig), fut)

    def add(self, name: str, e: dict):
        self.experiments[name] = e
        self.cols[name] = _records_of(e)
        self._figures(final=False)
        self.exps[name] = {
            "title": e.get("title") or EXPERIMENTS.get(name, {}).get("title", name),
            "paper": EXPERIMENTS.get(name, {}).get("paper"),
            "spec": e.get("spec"),
            "n_records": len(self.cols[name]),
            "notes": list(e.get("notes") or []),
            "findings": [f"[no data] {n}" for n in (e.get("notes") or [])]
            + findings(self.cols[name], e.get("spec")),
        }

    def finish(self) -> Report:
        self._figures(final=True)
        experiments = {n: self.experiments[n] for n in self.names if n in self.experiments}
        t_src = _choose_source(experiments, self.cols, ("E1",), ("rmse_A",))
        rows = table2(self.cols[t_src]) if t_src else []
        figs = []
        for i in sorted(self.figs):
            fg, fut = self.figs[i]
            if fut is not None:
                fg.set_rendered(*fut.result())
            figs.append(fg)
        return Report(
            title=self.title or f"Reproduction of the paper's Section 6 ({PRESET_NAME})",
            experiments={n: self.exps[n] for n in experiments},
            table2=rows,
            table2_source=t_src,
            figures=figs,
            provenance=dict(self.provenance or {}),
        )


def _exp_label(name: str, provenance: dict | None) -> str:
    preset = (provenance or {}).get("preset")
    return f"{preset} / {name}" if preset else name


def spec_json(spec) -> str:
    """A spec as JSON with one top-level field per line (valid JSON)."""
    if not isinstance(spec, dict):
        return json.dumps(spec)
    items = [f" {json.dumps(k)}: {json.dumps(v)}" for k, v in spec.items()]
    return "{\n" + ",\n".join(items) + "\n}"


def _md_escape(s: str) -> str:
    return s.replace("|", "\\|")


def render_markdown(report: Report, figure_files: dict[str, str] | None = None) -> str:
    """The report as Markdown; figures referenced by file name (``<name>.png``,
    with a link to ``<name>.svg``) unless ``figure_files`` maps names to paths."""
    L = [f"# {report.title}", ""]
    L.append(
        "Every number below comes from the records of this run (and, for the true "
        "system matrices, from its specs), except the columns marked *published*, which "
        "are the paper's own Table 2 values."
    )
    L.append("")
    L.append("| Experiment | What | Records |")
    L.append("|---|---|---|")
    for name, e in report.experiments.items():
        L.append(f"| {name} | {_md_escape(e['title'])} | {e['n_records']} |")
    L += ["", "## Findings: where the paper's claims hold here and where they do not", ""]
    for name, e in report.experiments.items():
        L.append(f"### {name}: {e['title']}")
        L.append("")
        for f in e["findings"]:
            L.append(f"- {f}")
        L.append("")
    L += ["## Table 2: RMSE, ours beside the paper's published values", ""]
    if report.table2:
        L.append(f"Source: experiment {report.table2_source}.")
        L.append("")
        L.append(table2_markdown(report.table2))
    else:
        L.append("No data for Table 2.")
        L.append("")
    L += ["## Figures", ""]
    for fg in report.figures:
        png = (figure_files or {}).get(fg.name, f"{fg.name}.png")
        svg = png[:-4] + ".svg" if png.endswith(".png") else None
        L.append(f"### {fg.title}")
        L.append("")
        L.append(f"![{fg.title}]({png})")
        L.append("")
        L.append(
            f"{fg.caption} Data: experiment {fg.experiment}." + (f" [SVG]({svg})" if svg else "")
        )
        L.append("")
    L += ["## Specs", ""]
    for name, e in report.experiments.items():
        L.append(f"### {name}" + (f" (paper: {e['paper']})" if e.get("paper") else ""))
        L.append("")
        L.append("```json")
        L.append(spec_json(e["spec"]))
        L.append("```")
        L.append("")
    L += ["## Provenance", "", "| Key | Value |", "|---|---|"]
    for k, v in report.provenance.items():
        val = v if isinstance(v, str) else json.dumps(v)
        L.append(f"| {k} | {_md_escape(str(val))} |")
    L.append("")
    return "\n".join(L)


_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,sans-serif;max-width:1200px;margin:2em auto;
padding:0 1em;color:#222;line-height:1.45}
table{border-collapse:collapse;margin:1em 0;font-size:0.9em}
td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}
td:first-child,th:first-child{text-align:left}
th{background:#f3f3f3} img{max-width:100%;border:1px solid #eee}
pre{background:#f7f7f7;padding:0.8em;overflow-x:auto;font-size:0.85em}
li{margin:0.3em 0} .pub{background:#fff7e0}
.holds{color:#17692a;font-weight:600}.nothold{color:#a01616;font-weight:600}
.partly{color:#a06a00;font-weight:600}.nodata{color:#666;font-weight:600}
"""

_STATUS_CLASS = {
    "[holds]": "holds",
    "[does not hold]": "nothold",
    "[partly]": "partly",
    "[no data]": "nodata",
    "[info]": "",
}


def _html_finding(f: str) -> str:
    for tag, cls in _STATUS_CLASS.items():
        if f.startswith(tag):
            rest = html.escape(f[len(tag) :])
            return f'<li><span class="{cls}">{html.escape(tag)}</span>{rest}</li>'
    return f"<li>{html.escape(f)}</li>"


def render_html(report: Report, figure_src: dict[str, str] | None = None) -> str:
    """The report as one HTML page; figures embedded as base64 PNG unless
    ``figure_src`` maps figure names to URLs."""
    e = html.escape
    H = [
        "<!DOCTYPE html>",
        "<html><head><meta charset='utf-8'>",
        f"<title>{e(report.title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{e(report.title)}</h1>",
        "<p>Every number below comes from the records of this run (and, for the true system "
        "matrices, from its specs), except the cells marked <span class='pub'>published</span>, "
        "which are the paper's own Table 2 values.</p>",
        "<table><tr><th>Experiment</th><th>What</th><th>Records</th></tr>",
    ]
    for name, x in report.experiments.items():
        H.append(f"<tr><td>{e(name)}</td><td>{e(x['title'])}</td><td>{x['n_records']}</td></tr>")
    H.append("</table>")
    H.append("<h2>Findings: where the paper's claims hold here and where they do not</h2>")
    for name, x in report.experiments.items():
        H.append(f"<h3>{e(name)}: {e(x['title'])}</h3><ul>")
        H += [_html_finding(f) for f in x["findings"]]
        H.append("</ul>")
    H.append("<h2>Table 2: RMSE, ours beside the paper's published values</h2>")
    if report.table2:
        H.append(f"<p>Source: experiment {e(str(report.table2_source))}.</p>")
        H.append(
            "<table><tr><th>System</th><th>σ_w</th><th>Matrix</th><th>OLS (ours)</th>"
            "<th>SVR (ours)</th><th class='pub'>OLS (paper, published)</th>"
            "<th class='pub'>\"Ours\" SVR (paper, published)</th><th>OLS ours/paper</th>"
            "<th>SVR ours/paper</th><th>SVR − OLS (ours)</th></tr>"
        )
        for r in report.table2:
            H.append(
                f"<tr><td>{e(r['system'])}</td><td>{_fmt(r['sigma_w'])}</td><td>{r['matrix']}</td>"
                f"<td>{_fmt(r['ols'])}</td><td>{_fmt(r['svr'])}</td>"
                f"<td class='pub'>{_fmt(r['paper_ols'])}</td>"
                f"<td class='pub'>{_fmt(r['paper_ours'])}</td>"
                f"<td>{_fmt(r['ratio_ols'], 3)}</td><td>{_fmt(r['ratio_svr'], 3)}</td>"
                f"<td>{_fmt(r['svr_minus_ols'], 3)}</td></tr>"
            )
        H.append("</table>")
        note = table2_markdown(report.table2).strip().splitlines()[-1]
        H.append(f"<p>{e(note)}</p>")
    else:
        H.append("<p>No data for Table 2.</p>")
    H.append("<h2>Figures</h2>")
    for fg in report.figures:
        src = (figure_src or {}).get(fg.name)
        if src is None:
            src = "data:image/png;base64," + base64.b64encode(fg.png()).decode("ascii")
        H.append(f"<h3>{e(fg.title)}</h3><img alt='{e(fg.title)}' src='{e(src)}'>")
        H.append(f"<p>{e(fg.caption)} Data: experiment {e(fg.experiment)}.</p>")
    H.append("<h2>Specs</h2>")
    for name, x in report.experiments.items():
        H.append(f"<h3>{e(name)}</h3><pre>{e(spec_json(x['spec']))}</pre>")
    H.append("<h2>Provenance</h2><table><tr><th>Key</th><th>Value</th></tr>")
    for k, v in report.provenance.items():
        val = v if isinstance(v, str) else json.dumps(v)
        H.append(f"<tr><td>{e(str(k))}</td><td style='text-align:left'>{e(str(val))}</td></tr>")
    H.append("</table></body></html>")
    return "\n".join(H)


def job_report_html(spec: dict, records, provenance: dict | None = None, name: str = "job") -> str:
    """One job's spec and records -> a self-contained HTML report (for the REST route)."""
    rep = build_report(
        {name: {"spec": spec, "records": records, "title": f"Job {name}"}},
        provenance,
        title=f"svrobs report: {name}",
    )
    return render_html(rep)
