"""The sizes and kinds of a spec's systems, for the cost model
(:mod:`svrobs_core.workload`) and admission (:mod:`svrobs_core.admission`).

Per system: n, m, p, the spectral radius of A, whether C is orthogonal and whether
its data are likely ill-conditioned for SVR (docs/deploy.md#admission); systems of
one :data:`Kind` cost the same, so the models cost each kind once, with every
system's table computed in a few stacked numpy calls.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .array_types import BoolArray, FloatArray, IntArray
from .estimators import SVR_COND_LIMIT
from .gains import is_orthogonal, orthogonal_each
from .spec import ExperimentSpec


def _dims(spec: ExperimentSpec, si: int) -> tuple[int, int, int, bool]:
    s = spec.systems[si]
    return s.n, s.m, s.p, bool(is_orthogonal(s.C))


def _ill_from_rho(rho: FloatArray, T0: int) -> BoolArray:
    """Whether SVR's data are likely worse conditioned than estimators.SVR_COND_LIMIT,
    per spectral radius ``rho`` of A: the states of an unstable system grow like
    rho^T0, so cond(Z Z^T) like rho^(2 T0) (a heuristic for the cost, not for the
    numbers)."""
    ill: BoolArray = rho > 1
    ill[ill] = 2 * (T0 - 1) * np.log10(rho[ill]) > np.log10(SVR_COND_LIMIT)
    return ill


def _ill_conditioned(spec: ExperimentSpec, si: int) -> bool:
    """:func:`_ill_from_rho` of system ``si`` of ``spec``."""
    rho = np.max(np.abs(np.linalg.eigvals(spec.systems[si].A)), keepdims=True)
    return bool(_ill_from_rho(rho, spec.T0)[0])


# What the cost model reads of a system: (n, m, p, C orthogonal, ill-conditioned data)
Kind = tuple[int, int, int, bool, bool]


@dataclass(frozen=True)
class SystemTable:
    """Per system of a spec: n, m, p, the spectral radius of A and whether C is
    orthogonal (:func:`~svrobs_core.gains.is_orthogonal`); what :func:`_dims` and
    :func:`_ill_conditioned` read, for every system at once."""

    n: IntArray
    m: IntArray
    p: IntArray
    rho: FloatArray
    orth: BoolArray


@dataclass(frozen=True)
class SystemKinds:
    """The distinct :data:`Kind` of a spec's systems (for its T0), and each system's
    index into them: systems of one kind cost the same."""

    kinds: tuple[Kind, ...]
    of: IntArray
    counts: IntArray

    def kind(self, si: int) -> Kind:
        return self.kinds[int(self.of[si])]


def system_dims(spec: ExperimentSpec) -> IntArray:
    """(n, m, p) of each system of ``spec``: an integer array (systems, 3)."""
    dims = [(s.A.shape[0], s.B.shape[1], s.C.shape[0]) for s in spec.systems]
    return np.array(dims, dtype=np.int64).reshape(len(dims), 3)


def system_table(spec: ExperimentSpec) -> SystemTable:
    """The :class:`SystemTable` of ``spec``'s systems: one eigenvalue call on the
    stacked A of each n, one C^T C of the stacked square C of each n."""
    dims = system_dims(spec)
    rho = np.zeros(len(dims))
    orth = np.zeros(len(dims), dtype=bool)
    for n in np.unique(dims[:, 0]).tolist():
        idx = np.flatnonzero(dims[:, 0] == n)
        A = np.stack([spec.systems[i].A for i in idx.tolist()])
        rho[idx] = np.max(np.abs(np.linalg.eigvals(A)), axis=-1)
        square = idx[dims[idx, 2] == n]
        if len(square):
            orth[square] = orthogonal_each(np.stack([spec.systems[i].C for i in square.tolist()]))
    return SystemTable(n=dims[:, 0], m=dims[:, 1], p=dims[:, 2], rho=rho, orth=orth)


def system_kinds(spec: ExperimentSpec, table: SystemTable | None = None) -> SystemKinds:
    """The :class:`SystemKinds` of ``spec`` (``table``: :func:`system_table` of its
    systems, if already made): :func:`_ill_from_rho` of every system at once."""
    t = system_table(spec) if table is None else table
    if len(t.n) != len(spec.systems):
        raise ValueError("the table is of other systems than the spec's")
    ill = _ill_from_rho(t.rho, spec.T0)
    base = int(max(t.n.max(initial=0), t.m.max(initial=0), t.p.max(initial=0))) + 1
    code = ((t.n * base + t.m) * base + t.p) * 4 + t.orth * 2 + ill  # one integer a kind
    codes, of, counts = np.unique(code, return_inverse=True, return_counts=True)
    kinds = []
    for c in codes.tolist():  # the distinct kinds, decoded
        nmp, flags = divmod(c, 4)
        nm, p = divmod(nmp, base)
        n, m = divmod(nm, base)
        kinds.append((n, m, p, flags >= 2, flags % 2 == 1))
    return SystemKinds(kinds=tuple(kinds), of=of.reshape(-1), counts=counts)
