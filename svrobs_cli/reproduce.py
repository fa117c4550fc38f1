"""`svrobs reproduce --out DIR`: the paper's Section 6 (preset ``paper-section-6``) in process.

Runs the experiments of ``svrobs_core.paper.paper_specs(scale)`` (E1-E4 and
the audits A1, A2; ``only`` picks some) and writes::

    DIR/<experiment>/records.jsonl   one record per line (null, never NaN)
    DIR/<experiment>/spec.json       the spec that ran
    DIR/table2.md, DIR/table2.csv    Table 2, ours beside the published values
    DIR/<figure>.png, .svg, .pdf     Figs. 2-5 and the figures beyond the paper
    DIR/<figure>.csv                 each figure's plotted data
    DIR/report.md, DIR/report.html   the whole report (HTML self-contained)
    DIR/provenance.json

One pass over the data (docs/performance.md#one-pass): the experiments are
run in groups around the largest grid, and nothing is simulated twice.

* An experiment whose spec equals another's restricted to some systems /
  gammas / estimators at the same seed-key indices (E1 inside E2, E3 inside
  E4, up to ``mc_reps``) takes its records from that run (a cell's numbers
  depend only on the seed and its key).
* An experiment that differs from another only in the bounds method (and on
  a subset of its N values: A1 and A2 of E2) runs in the same pass: the same
  data, factorisation and estimates, its own bounds and later stages
  (:func:`svrobs_core.runner.run_unit_results`).

Pass ``derive=False`` to run every spec on its own. Every stage of every
experiment runs, or the reproduction stops with a :class:`ReproduceError`
naming the experiment, the stage and why.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import os
import shutil
import time
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from rich.console import Console

from svrobs_cli.progress import progress_bar
from svrobs_cli.reproduce_plan import (
    Group,
    ReproduceError,
    mc_limit,
    plan,
    run_order,
    select_experiments,
)
from svrobs_cli.reproduce_report import FinishedRun, report_input, write_report
from svrobs_core import parse_spec, plan_units
from svrobs_core import report as rpt
from svrobs_core.paper import PRESET_NAME, paper_specs
from svrobs_core.parallel import open_pool
from svrobs_core.pipeline import failed_stage
from svrobs_core.runner import run_unit_results
from svrobs_core.threads import blas_single_thread
from svrobs_lab.figure_pool import DrawnFigure

# Above this many cells an experiment keeps no A_hat/B_hat in memory for the
# report (only E1/E2-sized grids draw the figures that need them).
MATRIX_CELLS_LIMIT = 200_000


class _Selector:
    """The cells of a child experiment among its parent's (report columns)."""

    def __init__(self, spec_obj: dict):
        s = parse_spec(spec_obj)
        self.systems = {x.name for x in s.systems}
        self.estimators = set(s.estimators)
        self.gammas = list(s.gamma)

    def mask(self, cols: rpt.Columns) -> np.ndarray:
        m = np.isin(cols["system"], list(self.systems)) & np.isin(
            cols["estimator"], list(self.estimators)
        )
        g = cols["gamma"]
        ok = np.isnan(g)
        for x in self.gammas:
            ok |= np.abs(g - x) <= 1e-12 * max(1.0, abs(x))
        return m & ok


@dataclass(frozen=True)
class _Output:
    """What a worker writes for one experiment of a group, from one unit."""

    name: str
    source: int  # index of the spec (parent, variants...) whose UnitResult it reads
    mc_reps: int | None
    systems: tuple[str, ...]
    matrices: bool
    select: dict | None  # the child's spec when it is a selection of the source's cells


def _part(out: Path, name: str, ui: int) -> Path:
    return out / name / ".parts" / f"{ui:06d}.jsonl"


def _work(specs, unit, outputs, out: Path, ui: int):
    """Worker side: one unit of a group; writes each experiment's JSON lines of
    the unit to its part file (:func:`_part`) -> ({name: (record count, report
    columns)}, {name: CPU seconds}): the parent's share of the pass and each
    experiment's own stages and encoding."""
    timings: dict = {}
    results = run_unit_results(list(specs), unit, timings=timings)
    cpu = {o.name: 0.0 for o in outputs}
    for o in outputs[: len(specs)]:
        cpu[o.name] += timings.get(o.source, 0.0)
        # the Monte Carlo J counts for the experiment that asks for the most of it
        need = [x for x in outputs if x.source == o.source and _has(results, x)]
        top = max(need or [o], key=lambda x: (_mc_of(x, specs), x is o))
        cpu[top.name] += timings.get(("mc", o.source), 0.0)
    encoded, cache = {}, {}
    for o in outputs:
        t = time.process_time()
        res = results[o.source]
        if res.system in o.systems and res.datasets:
            key = (o.source, o.mc_reps)
            if key not in cache:
                r = res.with_mc_reps(o.mc_reps)
                cache[key] = (r.json_lines(), r.columns(matrices=o.matrices))
            lines, data = cache[key]
            if o.select is not None:
                mask = _Selector(o.select).mask(rpt.Columns(data, len(lines)))
                if not mask.all():
                    keep = np.flatnonzero(mask)
                    lines = [lines[i] for i in keep.tolist()]
                    data = {f: v[keep] for f, v in data.items()}
            _part(out, o.name, ui).write_text("\n".join(lines) + "\n" if lines else "")
            encoded[o.name] = (len(lines), data)
        cpu[o.name] += time.process_time() - t
    return encoded, cpu


def _has(results, o: _Output) -> bool:
    return results[o.source].system in o.systems


def _mc_of(o: _Output, specs) -> float:
    s = specs[o.source]
    return s.reps if o.mc_reps is None else o.mc_reps


# ---------------------------------------------------------------------------
# running
# ---------------------------------------------------------------------------
@dataclass
class _GroupRun:
    group: Group
    specs: tuple  # parsed: parent, then variants
    units: list[dict]
    outputs: list[_Output]
    parts: dict = field(default_factory=dict)
    counts: dict = field(default_factory=dict)
    files: dict = field(default_factory=dict)  # name -> its records.jsonl, open
    done: set = field(default_factory=set)  # the units finished
    written: int = 0  # the units appended to the records.jsonl files, in unit order
    cpu: dict = field(default_factory=dict)
    t0: float = 0.0
    seconds: float = 0.0

    @property
    def finished(self) -> bool:
        return len(self.done) == len(self.units)


def _prepare(group: Group, specs: dict[str, dict]) -> _GroupRun:
    parsed = {n: parse_spec(specs[n]) for n in group.names}
    parent = parsed[group.parent]
    run_specs = tuple(parsed[n] for n in [group.parent, *group.variants])
    keep = parent.n_cells <= MATRIX_CELLS_LIMIT
    outputs = [
        _Output(n, i, parsed[n].mc_reps, tuple(x.name for x in parsed[n].systems), keep, None)
        for i, n in enumerate([group.parent, *group.variants])
    ]
    for c in group.children:
        outputs.append(
            _Output(
                c, 0, parsed[c].mc_reps, tuple(x.name for x in parsed[c].systems), keep, specs[c]
            )
        )
    units = plan_units(parent)
    for u in units:  # the Monte Carlo J as far as any spec using the unit needs it
        name = parent.systems[u["system"]].name
        need = [parsed[o.name] for o in outputs if name in o.systems]
        top = max(need, key=mc_limit)
        if top.mc_reps != parent.mc_reps:
            u["mc_reps"] = top.mc_reps
    return _GroupRun(group=group, specs=run_specs, units=units, outputs=outputs)


def _error(run: _GroupRun, exc: BaseException) -> ReproduceError:
    """The experiment, the stage (or that it was none: writing, the pool) and why."""
    why = f"{type(exc).__name__}: {exc}".strip()
    tagged = failed_stage(exc)
    if tagged is None:
        return ReproduceError(f"{run.group.parent}: failed outside its stages: {why}")
    stage, index = tagged
    names = [run.group.parent, *run.group.variants]
    name = names[index] if index < len(names) else run.group.parent
    return ReproduceError(f"{name}: stage '{stage}' failed: {why}")


def _run_all(runs: list[_GroupRun], out: Path, bar, pool, on_group, window: int = 4) -> None:
    """Every unit of every group, ``window`` at a time in the pool (groups in
    order, each in unit order), written as they finish: each
    experiment's unit texts go to part files, appended to its records.jsonl in
    unit order (:func:`_append_ready`); ``on_group(run)`` when a group is complete."""
    tasks = {}
    for gi, run in enumerate(runs):
        label = run.group.parent
        if run.group.variants or run.group.children:
            label += f" (+{', '.join(run.group.variants + run.group.children)})"
        if bar is not None:
            tasks[gi] = bar.add_task(label, total=len(run.units))
        for n in run.group.names:
            (out / n / ".parts").mkdir(parents=True, exist_ok=True)
            run.parts[n], run.counts[n], run.cpu[n] = {}, 0, 0.0
            run.files[n] = open(out / n / "records.jsonl", "wb", buffering=0)
        run.t0 = time.perf_counter()
    calls = [(gi, ui) for gi, run in enumerate(runs) for ui in range(len(run.units))]

    def args(gi, ui):
        run = runs[gi]
        return run.specs, run.units[ui], tuple(run.outputs), out, ui

    def take(gi, ui, produce):
        run = runs[gi]
        try:
            encoded, cpu = produce()
        except Exception as exc:
            raise _error(run, exc) from exc
        for n, (k, data) in encoded.items():
            run.counts[n] += k
            run.parts[n][ui] = rpt.Columns(data, k)
        for n, c in cpu.items():
            run.cpu[n] += c
        run.done.add(ui)
        _append_ready(run, out)
        if bar is not None:
            bar.update(tasks[gi], completed=len(run.done))
        if run.finished:
            _close(run)
            run.seconds = time.perf_counter() - run.t0
            on_group(run)

    try:
        if pool is None:
            for gi, ui in calls:
                with blas_single_thread():
                    take(gi, ui, lambda gi=gi, ui=ui: _work(*args(gi, ui)))
            return
        # in unit order, so that the part files are appended and removed as they come
        queue = calls[::-1]
        futures: dict = {}
        try:
            while queue or futures:
                # a few units ahead of the workers, so the report's figure renders
                # (submitted to the same pool as groups finish) do not wait for all
                while queue and len(futures) < window:
                    c = queue.pop()
                    futures[pool.submit(_work, *args(*c))] = c
                done, _ = wait(futures, return_when=FIRST_COMPLETED)
                for f in done:
                    gi, ui = futures.pop(f)
                    take(gi, ui, f.result)
        finally:
            for f in futures:
                f.cancel()
    finally:
        for run in runs:
            for n, f in run.files.items():
                f.close()
                if not run.finished:  # stopped: no records.jsonl of a group that did not finish
                    (out / n / "records.jsonl").unlink(missing_ok=True)
            for n in run.group.names:
                # a unit still running in a worker after a failure may add a part
                shutil.rmtree(out / n / ".parts", ignore_errors=True)


def _append_ready(run: _GroupRun, out: Path) -> None:
    """Append the part files of the finished units that no unfinished one precedes
    to their experiments' records.jsonl, in unit order (copied within the kernel
    where it can), and remove them: the parts on disk are the few units finished
    ahead of an earlier one, and the memory of a removed part's pages serves the
    next ones (docs/performance.md#one-pass)."""
    while run.written in run.done:
        ui = run.written
        for n in run.group.names:
            if ui in run.parts[n]:
                part = _part(out, n, ui)
                with open(part, "rb", buffering=0) as src:
                    _copy_file(src, run.files[n], os.fstat(src.fileno()).st_size)
                part.unlink()
        run.written += 1


def _close(run: _GroupRun) -> None:
    """A finished group: its records.jsonl files closed, each experiment's report
    columns in unit order."""
    for n in run.group.names:
        run.files[n].close()
        parts = run.parts[n]
        run.parts[n] = [parts[ui] for ui in sorted(parts)]


def _copy_file(src, dst, length: int) -> None:
    done = 0
    if hasattr(os, "copy_file_range"):
        try:
            while done < length:
                k = os.copy_file_range(src.fileno(), dst.fileno(), length - done)
                if k == 0:
                    break
                done += k
        except OSError:  # e.g. another file system: copy through memory
            pass
    while done < length:
        chunk = src.read(min(1 << 24, length - done))
        dst.write(chunk)
        done += len(chunk)


def _results(run: _GroupRun, specs: dict[str, dict], out: Path) -> dict[str, dict]:
    g = run.group
    results = {}
    for n in g.names:
        derived = g.parent if n in g.children else None
        shared = g.parent if n in g.variants else None
        (out / n / "spec.json").write_text(
            json.dumps(
                {
                    "spec": specs[n],
                    "normalised": parse_spec(specs[n]).to_dict(),
                    "derived_from": derived,
                    "shares_data_of": shared,
                },
                indent=1,
            )
        )
        results[n] = {
            "spec": specs[n],
            "records": rpt.Columns.concat(run.parts[n]),
            "n_records": run.counts[n],
            "derived_from": derived,
            "shares_data_of": shared,
            "seconds": run.seconds if n == g.parent else 0.0,
            "cpu_seconds": run.cpu[n],
        }
    return results


def _renderer(pool):
    """Figures built and drawn in the worker processes (a future per figure)."""

    def render(job):  # a figure whose worker failed is built and drawn here
        future = pool.submit(rpt.draw_files, job)
        return DrawnFigure(job, future, None, draw=rpt.draw_files, timed=False)

    return render


def reproduce(
    out_dir,
    scale: str = "full",
    quiet: bool = False,
    *,
    derive: bool = True,
    n_jobs: int | None = None,
    only=None,
    rng: str | None = None,
    draws: str | None = None,
) -> dict:
    """Run the preset ``paper-section-6`` in process and write tables, figures, report.

    ``only``: experiment names (list or "E1,E2") to run, default all;
    ``rng``: the generator of every experiment (default the preset's);
    ``draws``: how every experiment draws its datasets (default the preset's,
    ``"wishart"``; docs/science.md#15-wishart-draws);
    ``n_jobs``: worker processes for the pipeline (default: the machine's CPU
    count); the records are the same to the bit for any value.
    Returns ``{"out", "records": {exp: n}, "files": [...], "seconds"}``.
    """
    out = Path(out_dir)
    specs = select_experiments(paper_specs(scale), only)
    over = {k: v for k, v in (("rng", rng), ("draws", draws)) if v is not None}
    specs = {n: {**s, **over} for n, s in specs.items()}
    out.mkdir(parents=True, exist_ok=True)
    groups = plan(specs, derive)
    console = Console(stderr=True)
    started = _dt.datetime.now(_dt.UTC)
    t_start = time.perf_counter()
    results: dict[str, dict] = {}
    n_jobs = max(1, os.cpu_count() or 1) if n_jobs is None else max(1, int(n_jobs))
    with contextlib.ExitStack() as stack:
        # the worker processes start before the progress bar's thread does
        pool = stack.enter_context(open_pool(n_jobs))
        # The report is made as the groups finish: the findings and figures of a
        # group are computed in a background thread while the next group runs,
        # and the figures are built and drawn in the worker processes.
        builder = rpt.ReportBuilder(
            list(specs),
            {"preset": PRESET_NAME},
            render=None if pool is None else _renderer(pool),
        )
        background = stack.enter_context(ThreadPoolExecutor(max_workers=1))
        report_parts = []

        report_cpu: dict[str, float] = {}

        def add(name, e):  # in the background thread: its CPU seconds per experiment
            t = time.thread_time()
            builder.add(name, e)
            report_cpu[name] = time.thread_time() - t

        def on_group(run):
            group = _results(run, specs, out)
            results.update(group)
            for n in group:
                report_parts.append(background.submit(add, n, report_input(n, group[n])))

        runs = [_prepare(g, specs) for g in run_order(groups, specs)]
        with progress_bar(console, quiet=quiet) as bar:
            _run_all(runs, out, None if quiet else bar, pool, on_group, window=2 * n_jobs)
        t_run = time.perf_counter() - t_start
        for f in report_parts:
            f.result()
        run = FinishedRun(
            out=out,
            command=f"svrobs reproduce --out {out_dir}"
            + ("" if scale == "full" else f" --scale {scale}"),
            scale=scale,
            specs=specs,
            groups=groups,
            results=results,
            started=started,
            t_start=t_start,
            t_run=t_run,
            n_jobs=n_jobs,
            report_cpu=report_cpu,
        )
        return write_report(run, builder, console, quiet)
