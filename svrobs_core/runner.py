"""Run work units -> records (docs/spec.md#record-fields).

``run_unit_result(spec, unit)`` is the one pure function a worker calls (one
unit of :func:`svrobs_core.planning.plan_units` -> a :class:`UnitResult`);
``run_unit`` gives the same unit's record dicts; ``run_spec`` runs every
unit in process (or in ``n_jobs`` processes). Records do not depend on how
the grid is split nor on where the units run
(docs/science.md#14-randomness-and-reproducibility).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from concurrent.futures import Executor
from dataclasses import replace
from typing import Any

from .parallel import open_pool, run_ordered
from .pipeline import run_dataset_variants, shares_data
from .planning import estimator_axis, plan_units
from .spec import ExperimentSpec
from .threads import blas_single_thread
from .unit_result import Dataset, UnitResult


def run_unit_result(spec: ExperimentSpec, unit: dict[str, Any]) -> UnitResult:
    """Run one work unit of ``plan_units`` -> its records as a :class:`UnitResult`.

    A unit may carry ``"mc_reps"``: it overrides the spec's for this unit
    (used to compute the Monte Carlo J once for several specs that differ
    only there; see :meth:`UnitResult.with_mc_reps`)."""
    return run_unit_results([spec], unit)[0]


def run_unit_results(
    specs: list[ExperimentSpec], unit: dict[str, Any], *, timings: dict[Any, float] | None = None
) -> list[UnitResult]:
    """One work unit of ``specs[0]``'s plan for specs that share its data and
    estimates (:func:`svrobs_core.pipeline.shares_data`, e.g. the same grid with
    other bounds methods): every dataset is simulated and estimated once, each
    spec's stages run on it. -> one :class:`UnitResult` per spec, holding the
    unit's N values that are in that spec (its records are the ones the spec
    gives on its own). ``timings``: CPU seconds are added to it per spec index
    (the shared simulation and estimates count for ``specs[0]``), those of the
    Monte Carlo J under ``("mc", index)``."""
    specs = [
        replace(s, mc_reps=unit["mc_reps"])
        if "mc_reps" in unit and unit["mc_reps"] != s.mc_reps
        else s
        for s in specs
    ]
    for s in specs[1:]:
        if not shares_data(specs[0], s):
            raise ValueError("run_unit_results: the specs do not share their data")
    spec = specs[0]
    si, wi = unit["system"], unit["sigma_w"]
    reps = list(range(*unit["reps"]))
    axis = estimator_axis(spec)
    datasets: list[list[Dataset]] = [[] for _ in specs]
    prev_gains: list[Any] = [None] * len(specs)
    with blas_single_thread():
        for N in sorted(unit["N"]):
            which = [i for i, s in enumerate(specs) if N in s.N]
            if not which:
                continue
            t: dict[Any, float] = {}
            results = run_dataset_variants(
                [specs[i] for i in which],
                si=si,
                wi=wi,
                N=N,
                reps=reps,
                axis=axis,
                prev_gains=[prev_gains[i] for i in which],
                timings=None if timings is None else t,
            )
            if timings is not None:
                for key, sec in t.items():
                    i = which[key[1]] if isinstance(key, tuple) else which[key]
                    k = ("mc", i) if isinstance(key, tuple) else i
                    timings[k] = timings.get(k, 0.0) + sec
            for i, (fields, notes, N0, gain) in zip(which, results):
                if specs[i].reuse_gain:
                    prev_gains[i] = gain
                datasets[i].append(Dataset(N=int(N), N0=int(N0), fields=fields, note_entries=notes))
    return [
        UnitResult(
            system=s.systems[si].name,
            system_idx=si,
            sigma_w=s.sigma_w[wi],
            sigma_w_idx=wi,
            reps=reps,
            axis=axis,
            datasets=ds,
            mc_reps=s.mc_reps,
            n_reps=s.reps,
        )
        for s, ds in zip(specs, datasets)
    ]


def run_unit(spec: ExperimentSpec, unit: dict[str, Any]) -> list[dict[str, Any]]:
    """Run one work unit of ``plan_units`` -> its records."""
    return run_unit_result(spec, unit).records()


def _records_of(result: UnitResult) -> list[dict[str, Any]]:
    return result.records()


def _work(spec: ExperimentSpec, unit: dict[str, Any], post: Callable[[UnitResult], Any]) -> Any:
    return post(run_unit_result(spec, unit))


def run_spec(
    spec: ExperimentSpec,
    *,
    progress: Callable[[int, int], None] | None = None,
    units: list[dict[str, Any]] | None = None,
    n_jobs: int = 1,
    post: Callable[[UnitResult], Any] | None = None,
    pool: Executor | None = None,
) -> Iterator[Any]:
    """Run every unit, yielding each unit's records in unit order.

    ``n_jobs > 1`` runs units in that many worker processes (scikit-learn's
    convention); the records are the same to the bit either way. ``pool``:
    an executor from :func:`svrobs_core.parallel.open_pool` to reuse across
    calls. ``post``: a picklable function applied to each unit's
    :class:`UnitResult` (in the worker process when ``n_jobs > 1``); its value
    is yielded instead of the list of record dicts (e.g. ``UnitResult.json_lines``).
    """
    units = plan_units(spec) if units is None else units
    post = _records_of if post is None else post
    if (n_jobs > 1 or pool is not None) and len(units) > 1:
        calls = [(spec, u, post) for u in units]
        if pool is not None:
            yield from run_ordered(pool, _work, calls, progress)
        else:
            with open_pool(n_jobs) as own:
                assert own is not None  # n_jobs > 1
                yield from run_ordered(own, _work, calls, progress)
        return
    for i, unit in enumerate(units):
        yield post(run_unit_result(spec, unit))
        if progress is not None:
            progress(i + 1, len(units))
