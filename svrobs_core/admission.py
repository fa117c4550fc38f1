"""Admission of a job: refuse work over a limit before anything is planned or run
(docs/deploy.md#admission).

:func:`admit` checks, cheapest first: the cells and the stored bytes (products of
the grid's axis lengths, :func:`check_size`), the CPU floor, then the closed-form
cost of the whole grid (:func:`grid_cost`: the cost model of
:mod:`svrobs_core.workload` summed over the axes with numpy, no loop over units),
and only then plans the units under the memory and per-unit CPU caps. The closed
form equals the sum of :func:`~svrobs_core.workload.estimate_unit` over
:func:`~svrobs_core.planning.plan_units`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from . import planning
from .array_types import FloatArray
from .cost_rates import CELL_COST
from .measured.runner import plan_measured_units
from .measured.workload import measured_fixed_bytes
from .records import NUMERIC_FIELDS
from .spec import ExperimentSpec
from .system_kinds import (
    SystemKinds,
    SystemTable,
    _dims,
    system_dims,
    system_kinds,
    system_table,
)
from .workload import (
    DataShape,
    JobCost,
    UnitCost,
    WorkloadError,
    _dataset,
    _fit,
    _unit_cost,
    estimate_job,
    estimate_unit,
    plan_under_memory,
    unit_base_bytes,
    unit_fixed_seconds,
)

ROW_BYTES = 8 * len(NUMERIC_FIELDS) + 120  # a stored row's scalars, keys and overhead
CULPRIT_AXIS = 2048  # N values the reductions of a longer N axis are costed on


@dataclass(frozen=True)
class GridCost:
    """The closed-form cost of ``plan_units(spec)``: total CPU seconds, the unit
    count, the largest unit's peak bytes and CPU seconds."""

    cpu_seconds: float
    n_units: int
    peak_unit_bytes: int
    max_unit_seconds: float
    per_system: tuple[float, ...] = ()  # CPU seconds of each system's units


def cell_entries(spec: ExperimentSpec, si: int) -> int:
    """Matrix entries stored per cell of system ``si``: A_hat and B_hat; radii_A and
    radii_B with ``bounds``; L and K with ``gain``."""
    n, m, p, _ = _dims(spec, si)
    out = n * n + n * m
    if spec.has("bounds"):
        out += n * n + n * m
    if spec.has("gain"):
        out += 2 * n * p
    return out


def stored_bytes(spec: ExperimentSpec, *, data: DataShape | None = None) -> float:
    """Bytes the job's records take in the store: per cell a row of scalars and
    8 bytes per matrix entry (:func:`cell_entries`), from the axis lengths only."""
    per_pair = spec.n_cells // max(1, len(spec.grid_systems) * len(spec.grid_sigma_w))
    if spec.measured is not None:
        n = data.n if data is not None else 1
        m = data.m if data is not None else 1
        entries = (2 if spec.has("bounds") else 1) * (n * n + n * m)
        return float(spec.n_cells) * (ROW_BYTES + 8 * entries)
    n, m, p = system_dims(spec).T  # cell_entries of every system at once
    entries = n * n + n * m
    if spec.has("bounds"):
        entries = entries + n * n + n * m
    if spec.has("gain"):
        entries = entries + 2 * n * p
    per_system = int(np.sum(ROW_BYTES + 8 * entries))
    return float(per_pair) * len(spec.sigma_w) * float(per_system)


def check_size(
    spec: ExperimentSpec,
    *,
    max_cells: int | None = None,
    max_stored_bytes: float | None = None,
    data: DataShape | None = None,
) -> None:
    """:class:`WorkloadError` (``kind`` "cells" or "stored") when the job has more
    cells than ``max_cells`` or its records would take more than ``max_stored_bytes``;
    costs O(grid axes). None: no limit."""
    cells = spec.n_cells
    field = "reps" if spec.reps > len(spec.N) else "N"
    if max_cells is not None and cells > max_cells:
        raise WorkloadError(
            field,
            f"the job has {cells:,} cells; the limit is {max_cells:,}",
            kind="cells",
            estimate=cells,
            limit=max_cells,
        )
    if max_stored_bytes is not None:
        size = stored_bytes(spec, data=data)
        if size > max_stored_bytes:
            raise WorkloadError(
                field,
                f"the job's records would take an estimated {size / 2**20:,.0f} MB in the"
                f" store, over the limit of {max_stored_bytes / 2**20:,.0f} MB",
                kind="stored",
                estimate=size,
                limit=max_stored_bytes,
            )


def _rep_classes(spec: ExperimentSpec, chunk: int) -> list[tuple[int, int, int]]:
    """(R, Monte Carlo rows, count) of the repetition chunks of ``chunk`` reps."""
    limit = spec.reps if spec.mc_reps is None else spec.mc_reps
    r0 = np.arange(0, spec.reps, chunk, dtype=np.int64)
    r1 = np.minimum(spec.reps, r0 + chunk)
    mc = np.maximum(0, np.minimum(r1, limit) - r0)
    pairs, counts = np.unique(np.stack([r1 - r0, mc], axis=1), axis=0, return_counts=True)
    return [(int(R), int(m), int(c)) for (R, m), c in zip(pairs, counts, strict=True)]


def grid_cost(
    spec: ExperimentSpec,
    *,
    max_cells: int = planning.MAX_CELLS_PER_UNIT,
    target_cells: int = planning.TARGET_CELLS_PER_UNIT,
    n_axis: FloatArray | None = None,
    table: SystemTable | None = None,
) -> GridCost:
    """The cost of ``plan_units(spec, max_cells=, target_cells=)`` in closed form: the
    N axis as one numpy array per kind of system (:func:`~svrobs_core.system_kinds.system_kinds`:
    systems of one kind cost the same) and repetition chunk size, each unit's sum over
    its N group by a reshape (a simulated job). ``n_axis``: :func:`n_axis` of the
    spec, ``table``: :func:`~svrobs_core.system_kinds.system_table` of its systems, if
    already made."""
    if spec.measured is not None:
        raise ValueError("a dataset job's cost: workload.estimate_job with its shape")
    E, L, W = spec.cells_per_rep, len(spec.N), len(spec.sigma_w)
    Ns = n_axis_of(spec) if n_axis is None else n_axis
    g = L if spec.reuse_gain else max(1, target_cells // (E * spec.reps))
    starts = np.arange(0, L, g)
    lengths = np.minimum(g, L - starts)
    # the N groups of each length (at most two: the groups' and the last one's) and
    # their repetition chunks, the same for every system
    blocks = []
    for Lg in np.unique(lengths).tolist():
        sel = starts[lengths == Lg]
        idx = (sel[:, None] + np.arange(Lg)[None, :]).ravel()  # N of these groups
        chunk = max(1, min(spec.reps, max_cells // (E * Lg)))
        within = np.tile(np.arange(Lg), len(sel))  # earlier N's records kept
        blocks.append((Lg, len(sel), Ns[idx], within, _rep_classes(spec, chunk)))
    kinds = system_kinds(spec, table)
    n_units, peak, longest, per_kind = 0, 0.0, 0.0, []
    for (n, m, p, orth, ill_data), systems in zip(kinds.kinds, kinds.counts.tolist()):
        total = 0.0
        ill = "svr" in spec.estimators and ill_data
        fixed = unit_fixed_seconds(spec, n=n, p=p)
        base = unit_base_bytes(spec, n=n, p=p, orth=orth)
        for Lg, groups, N_axis, within, rep_classes in blocks:
            for R, mc, count in rep_classes:
                c, transient, kept = _dataset(
                    spec, n=n, m=m, p=p, orth=orth, N=N_axis, R=R, mc_rows=mc, ill=ill,
                    ill_data=ill_data,
                )  # fmt: skip
                c = np.broadcast_to(c, N_axis.shape)
                per_unit = c.reshape(groups, Lg).sum(axis=1) + fixed
                total += W * count * float(per_unit.sum())
                n_units += systems * W * count * groups
                longest = max(longest, float(per_unit.max()))
                peak = max(peak, base + float(np.max(within * kept + transient)))
        per_kind.append(total)
    per_system = np.array(per_kind, dtype=np.float64)[kinds.of].tolist()
    return GridCost(
        cpu_seconds=float(sum(per_system)),  # summed in the systems' order
        n_units=n_units,
        peak_unit_bytes=int(peak),
        max_unit_seconds=longest,
        per_system=tuple(per_system),
    )


def n_axis_of(spec: ExperimentSpec) -> FloatArray:
    """The N axis in the plan's order (sorted, unless ``reuse_gain``), as floats."""
    Ns = np.fromiter(spec.N, dtype=np.float64, count=len(spec.N))
    return Ns if spec.reuse_gain else np.sort(Ns)


def smallest_unit_bytes(
    spec: ExperimentSpec, *, data: DataShape | None = None, table: SystemTable | None = None
) -> int:
    """Peak bytes of the smallest unit the plan can make: one repetition of the
    largest N (all N together under ``reuse_gain``), for the largest system
    (``table``: :func:`~svrobs_core.system_kinds.system_table` of its systems, if made)."""
    return max(u.peak_bytes for u in _smallest(spec, data, table))


def smallest_unit_seconds(
    spec: ExperimentSpec, *, data: DataShape | None = None, table: SystemTable | None = None
) -> float:
    """CPU seconds of the longest smallest unit: one repetition of the largest N."""
    return max(u.cpu_seconds for u in _smallest(spec, data, table))


def _smallest(
    spec: ExperimentSpec, data: DataShape | None, table: SystemTable | None
) -> list[UnitCost]:
    """The smallest unit's cost for each kind of system (a dataset job: its one)."""
    Ns = list(spec.N) if spec.reuse_gain else [max(spec.N)]
    unit = {"system": 0, "sigma_w": 0, "N": Ns, "reps": [0, 1]}
    if spec.measured is not None:
        return [estimate_unit(spec, unit, data=data)]
    return [_unit_cost(spec, unit, kind) for kind in system_kinds(spec, table).kinds]


def _reductions(spec: ExperimentSpec, kind: str) -> dict[str, ExperimentSpec]:
    """The spec with one size field at its smallest, per field (for naming the culprit)."""
    if spec.measured is not None:  # a dataset job: no simulation fields
        out = {
            "N": replace(spec, N=(min(spec.N),)),
            "gamma": replace(spec, gamma=spec.gamma[:1]),
            "sls.T_fir": replace(spec, sls_T_fir=2),
            "estimators": replace(spec, estimators=spec.estimators[:1]),
        }
        if kind == "cpu":
            out["reps"] = replace(spec, reps=1)
        return out
    out = {
        "N": replace(spec, N=(1,)),
        "T0": replace(spec, T0=2),
        "gamma": replace(spec, gamma=spec.gamma[:1]),
        "mc_runs": replace(spec, mc_runs=2),
        "horizon": replace(spec, horizon=1),
        "sls.T_fir": replace(spec, sls_T_fir=2),
        "estimators": replace(spec, estimators=spec.estimators[:1]),
    }
    if spec.bounds_method == "bootstrap":
        out["boot_reps"] = replace(spec, boot_reps=2)
    if kind == "cpu":
        out["reps"] = replace(spec, reps=1, mc_reps=None if spec.mc_reps is None else 1)
        out["sigma_w"] = replace(spec, sigma_w=spec.sigma_w[:1])
        out["systems"] = replace(spec, systems=spec.systems[:1])
    return out


def _plan(
    spec: ExperimentSpec,
    max_unit_bytes: int | None,
    max_unit_seconds: float | None,
    data: DataShape | None,
    kinds: SystemKinds | None = None,
) -> list[dict[str, Any]]:
    """The units under the memory and per-unit CPU caps: :func:`plan_under_memory`, or
    for a dataset job :func:`~svrobs_core.measured.plan_measured_units` with what the
    memory cap leaves beside the bytes every unit holds, a unit still over a cap by
    this estimate split as :func:`plan_under_memory` splits one."""
    if spec.measured is None:
        return plan_under_memory(
            spec, max_unit_bytes=max_unit_bytes, max_unit_seconds=max_unit_seconds, kinds=kinds
        )
    if max_unit_bytes is None:
        units = plan_measured_units(spec)
    else:
        if data is None:
            raise ValueError("a dataset job's plan needs its dataset's shape (data=DataShape)")
        budget = max(1, max_unit_bytes - measured_fixed_bytes(spec, data))
        units = plan_measured_units(
            spec, lengths=list(data.lengths), n=data.n, m=data.m, max_unit_bytes=budget
        )
    if max_unit_bytes is None and max_unit_seconds is None:
        return units
    return [v for u in units for v in _fit(spec, u, max_unit_bytes, max_unit_seconds, data)]


def _cpu_sizes(
    spec: ExperimentSpec,
    data: DataShape | None,
    grid: GridCost | None,
    Ns: FloatArray | None,
    table: SystemTable | None,
) -> dict[str, float]:
    """The job's CPU seconds with each size field at its smallest. A simulated job's
    in closed form: one :func:`grid_cost` per reduction that changes the spec, the
    sigma_w and systems reductions read off the whole grid's (units cost the same
    for every sigma_w; each system's are summed apart). ``table``: the systems'
    :func:`~svrobs_core.system_kinds.system_table`, which no reduction costed here changes."""
    if spec.measured is not None:
        return {
            f: estimate_job(s, _plan(s, None, None, data), data=data).cpu_seconds
            for f, s in _reductions(spec, "cpu").items()
        }
    Ns = n_axis_of(spec) if Ns is None else Ns
    table = system_table(spec) if table is None else table
    grid = grid_cost(spec, n_axis=Ns, table=table) if grid is None else grid
    if len(spec.N) > CULPRIT_AXIS:  # only a name: the reductions costed on a strided N axis
        step = -(-len(spec.N) // CULPRIT_AXIS)
        Ns, spec = Ns[::step], replace(spec, N=tuple(int(v) for v in Ns[::step]))
        grid = grid_cost(spec, n_axis=Ns, table=table)
    reductions = _reductions(spec, "cpu")
    sizes = {
        "sigma_w": grid.cpu_seconds / len(spec.sigma_w),
        "systems": grid.per_system[0],
    }
    inert = {  # fields the cost does not read for this spec
        "mc_runs": not spec.has("cost"),
        "horizon": not spec.has("cost"),
        "sls.T_fir": not spec.has("sls"),
        "gamma": set(spec.estimators) == {"ols"},
    }
    for f, s in reductions.items():
        if f in sizes:
            continue
        if inert.get(f, False) or s == spec:  # e.g. one gamma already: nothing to reduce
            sizes[f] = grid.cpu_seconds
        else:
            axis = Ns if s.N is spec.N else None
            sizes[f] = grid_cost(s, n_axis=axis, table=table).cpu_seconds
    return sizes


def _culprit(
    spec: ExperimentSpec,
    kind: str,
    data: DataShape | None = None,
    grid: GridCost | None = None,
    n_axis: FloatArray | None = None,
    table: SystemTable | None = None,
) -> str:
    """The size field whose reduction lowers the estimate of ``kind`` most (``grid``,
    ``n_axis`` and ``table``: the spec's, if already made)."""
    if kind == "cpu":
        sizes = _cpu_sizes(spec, data, grid, n_axis, table)
    else:
        need = smallest_unit_seconds if kind == "unit_cpu" else smallest_unit_bytes
        reduced = _reductions(spec, "memory").items()  # none changes the systems
        sizes = {f: need(s, data=data, table=table) for f, s in reduced}
    return min(sizes, key=lambda f: sizes[f])


def _over_cpu(
    spec: ExperimentSpec,
    seconds: float,
    limit: float,
    data: DataShape | None,
    grid: GridCost | None = None,
    Ns: FloatArray | None = None,
    table: SystemTable | None = None,
) -> WorkloadError:
    return WorkloadError(
        _culprit(spec, "cpu", data, grid, Ns, table),
        f"the job needs an estimated {seconds:.0f} CPU seconds, over the limit of {limit:.0f} s",
        kind="cpu",
        estimate=seconds,
        limit=limit,
    )


def admit(
    spec: ExperimentSpec,
    *,
    max_cells: int | None = None,
    max_stored_bytes: float | None = None,
    max_cpu_seconds: float | None = None,
    max_unit_bytes: int | None = None,
    max_unit_seconds: float | None = None,
    data: DataShape | None = None,
) -> tuple[list[dict[str, Any]], JobCost]:
    """The work units of ``spec`` planned under the memory and per-unit CPU caps, and
    their cost, or :class:`WorkloadError` if the job is over ``max_cells`` or
    ``max_stored_bytes``, its smallest unit over ``max_unit_bytes`` or
    ``max_unit_seconds``, or the job over ``max_cpu_seconds`` (None: no limit). The
    message gives the estimate and the limit; ``field`` the spec field that weighs
    most. A dataset job needs its dataset's shape ``data``."""
    if spec.measured is not None and data is None:
        raise ValueError("a dataset job's admission needs its dataset's shape (data=DataShape)")
    check_size(spec, max_cells=max_cells, max_stored_bytes=max_stored_bytes, data=data)
    floor = spec.n_cells * CELL_COST["estimate"][0]  # every cell builds its record at least
    if max_cpu_seconds is not None and floor > max_cpu_seconds:
        raise WorkloadError(
            "reps" if spec.reps > len(spec.N) else "N",
            f"the job ({spec.n_cells} records) needs an estimated {floor:.0f} CPU seconds or"
            f" more, over the limit of {max_cpu_seconds:.0f} s",
            kind="cpu",
            estimate=floor,
            limit=max_cpu_seconds,
        )
    # what the cost model reads of each system, for every system at once
    table = system_table(spec) if spec.measured is None else None
    smallest: list[UnitCost] = []  # smallest_unit_bytes and _seconds read the same units
    for kind, cap in (("memory", max_unit_bytes), ("unit_cpu", max_unit_seconds)):
        if cap is None:
            continue
        smallest = smallest or _smallest(spec, data, table)
        value = max(u.peak_bytes if kind == "memory" else u.cpu_seconds for u in smallest)
        if value > cap:
            what = f"{value / 2**20:.0f} MB" if kind == "memory" else f"{value:.0f} CPU seconds"
            limit = f"{cap / 2**20:.0f} MB" if kind == "memory" else f"{cap:.0f} s"
            raise WorkloadError(
                _culprit(spec, kind, data, table=table),
                f"one work unit (a single repetition) needs an estimated {what},"
                f" over the limit of {limit}",
                kind=kind,
                estimate=value,
                limit=cap,
            )
    if spec.measured is None:
        Ns = n_axis_of(spec)
        grid = grid_cost(spec, n_axis=Ns, table=table)
        if max_cpu_seconds is not None and grid.cpu_seconds > max_cpu_seconds:
            raise _over_cpu(spec, grid.cpu_seconds, max_cpu_seconds, data, grid, Ns, table)
        fits = (max_unit_bytes is None or grid.peak_unit_bytes <= max_unit_bytes) and (
            max_unit_seconds is None or grid.max_unit_seconds <= max_unit_seconds
        )
        if fits:  # no unit is split: the plan's cost is the closed form's
            job = JobCost(grid.cpu_seconds, grid.peak_unit_bytes, grid.n_units)
            return planning.plan_units(spec), job
    kinds = None if table is None else system_kinds(spec, table)
    units = _plan(spec, max_unit_bytes, max_unit_seconds, data, kinds)
    job = estimate_job(spec, units, data=data, kinds=kinds)
    if max_cpu_seconds is not None and job.cpu_seconds > max_cpu_seconds:
        raise _over_cpu(spec, job.cpu_seconds, max_cpu_seconds, data, table=table)
    return units, job


__all__ = [
    "GridCost",
    "admit",
    "cell_entries",
    "check_size",
    "grid_cost",
    "n_axis_of",
    "smallest_unit_bytes",
    "smallest_unit_seconds",
    "stored_bytes",
]
