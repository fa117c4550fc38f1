"""`svrobs reproduce --out DIR`: the paper's Section 6 (preset ``paper-section-6``) in process.

Runs E1..E4 of ``svrobs_core.paper.paper_specs(scale)`` with ``run_spec`` and
writes::

    DIR/<experiment>/records.jsonl   one record per line (null, never NaN)
    DIR/<experiment>/spec.json       the spec that ran
    DIR/table2.md, DIR/table2.csv    Table 2, ours beside the published values
    DIR/<figure>.png, .svg, .pdf     Figs. 2-5 and the figures beyond the paper
    DIR/<figure>.csv                 each figure's plotted data
    DIR/report.md, DIR/report.html   the whole report (HTML self-contained)
    DIR/provenance.json

Sub-grids are not recomputed: when an experiment's spec equals another's
restricted to some systems / gammas / estimators at the same seed-key
indices (E1 inside E2, E3 inside E4), its records are the other run's
records for those cells (docs/science.md#1-system-and-data: a cell's numbers depend only on the
seed and its key). Pass ``derive=False`` to run every spec on its own.

If a pipeline stage is not available in this build (it raises
``NotImplementedError`` or its module is missing), the experiment is rerun
without that stage, the report says so, and the figures needing it show
"no data".
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import functools
import json
import os
import platform
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.progress import Progress

from service.db.provenance import git_commit
from service.progress import progress_bar
from svrobs_core import __version__, parse_spec, plan_units, run_spec
from svrobs_core import report as rpt
from svrobs_core.paper import EXPERIMENTS, MC_DECISION, PRESET_NAME, paper_specs
from svrobs_core.parallel import open_pool
from svrobs_core.unit_result import UnitResult

from .html import render_html

# Above this many cells an experiment keeps no A_hat/B_hat in memory for the
# report (only E1/E2-sized grids draw the figures that need them).
MATRIX_CELLS_LIMIT = 200_000
# One reusable encoder: about a third faster than json.dumps(..., allow_nan=False) per record.
_ENCODER = json.JSONEncoder(allow_nan=False)


def _derivable(child: dict, parent: dict) -> bool:
    """True when every record of ``child`` is a record of ``parent`` (same keys),
    up to ``mc_reps``: the parent's run then computes the Monte Carlo J as far
    as the child needs it and writes each spec's own records
    (``UnitResult.with_mc_reps``)."""
    c, p = parse_spec(child), parse_spec(parent)
    cd, pd = c.to_dict(), p.to_dict()
    for k in cd.keys() | pd.keys():  # both ways: e.g. bounds_method is in only one of them
        if k in ("systems", "gamma", "estimators", "mc_reps"):
            continue
        if cd.get(k) != pd.get(k):
            return False
    # the seed key holds the system index: it must be the same in both
    for i, s in enumerate(cd["systems"]):
        if i >= len(pd["systems"]) or pd["systems"][i] != s:
            return False
    if not set(c.estimators) <= set(p.estimators):
        return False
    if "cost" in c.stages:  # the cost ratio couples the gammas of a repetition
        return c.gamma == p.gamma
    return set(c.gamma) <= set(p.gamma)


def _plan(specs: dict[str, dict], derive: bool) -> list[tuple[str, list[str]]]:
    """[(experiment to run, [experiments taken from its records])], largest grids first."""
    if not derive:
        return [(name, []) for name in specs]
    size = {n: parse_spec(s).n_cells for n, s in specs.items()}
    parent_of: dict[str, str] = {}
    for child in specs:
        cands = [
            p
            for p in specs
            if p != child and size[p] >= size[child] and _derivable(specs[child], specs[p])
        ]
        cands = [p for p in cands if p not in parent_of]
        if cands:
            parent_of[child] = max(cands, key=lambda p: size[p])
    # a parent must itself be run
    for child, p in list(parent_of.items()):
        if p in parent_of:
            del parent_of[child]
    plan = []
    for name in specs:
        if name in parent_of:
            continue
        plan.append((name, [c for c in specs if parent_of.get(c) == name]))
    return plan


class _Selector:
    def __init__(self, spec_obj: dict):
        s = parse_spec(spec_obj)
        self.systems = {x.name for x in s.systems}
        self.estimators = set(s.estimators)
        self.gammas = list(s.gamma)

    def __call__(self, r: dict) -> bool:
        if r["system"] not in self.systems or r["estimator"] not in self.estimators:
            return False
        g = r["gamma"]
        return g is None or any(abs(g - x) <= 1e-12 * max(1.0, abs(x)) for x in self.gammas)

    def mask(self, cols: rpt.Columns) -> np.ndarray:
        """The same selection on report columns (vectorised)."""
        m = np.isin(cols["system"], list(self.systems)) & np.isin(
            cols["estimator"], list(self.estimators)
        )
        g = cols["gamma"]
        ok = np.isnan(g)
        for x in self.gammas:
            ok |= np.abs(g - x) <= 1e-12 * max(1.0, abs(x))
        return m & ok


def _encode(result: UnitResult, variants: tuple):
    """Worker side: a unit's records as JSON lines and report columns, for each
    ``(name, mc_reps, systems, matrices)`` variant whose systems hold the unit."""
    out = {}
    for name, mc_reps, systems, matrices in variants:
        if result.system in systems:
            r = result.with_mc_reps(mc_reps)
            lines = r.json_lines()
            # one string per unit: much cheaper to send between processes than a list
            out[name] = (
                "".join(line + "\n" for line in lines),
                len(lines),
                r.columns(matrices=matrices),
            )
    return out


def _mc_limit(spec) -> float:
    return spec.reps if spec.mc_reps is None else spec.mc_reps


def _run_group(
    parent: str,
    children: list[str],
    specs: dict[str, dict],
    out: Path,
    bar: Progress | None,
    pool=None,
    n_jobs: int = 1,
) -> dict[str, dict]:
    """Run ``parent`` once (streaming records to files), fill the children too."""
    names = [parent] + children
    spec_objs = {n: json.loads(json.dumps(specs[n])) for n in names}
    unavailable: dict[str, str] = {}
    while True:
        try:
            return _stream(parent, children, spec_objs, out, bar, unavailable, pool, n_jobs)
        except (NotImplementedError, ImportError) as exc:
            stages = spec_objs[parent].get("stages", ["estimate", "bounds"])
            if len(stages) <= 1:
                raise  # not even the estimate stage runs: nothing to report
            dropped = stages[-1]
            unavailable[dropped] = f"{type(exc).__name__}: {exc}".strip()
            for n in names:
                spec_objs[n]["stages"] = [s for s in spec_objs[n]["stages"] if s != dropped]
            if bar is not None:
                bar.console.print(
                    f"[yellow]{parent}: stage '{dropped}' is not available in "
                    f"this build ({unavailable[dropped]}); rerunning without it"
                )


def _stream(
    parent, children, spec_objs, out: Path, bar, unavailable, pool=None, n_jobs: int = 1
) -> dict[str, dict]:
    spec = parse_spec(spec_objs[parent])
    specs = {n: parse_spec(spec_objs[n]) for n in [parent] + children}
    keep_matrices = spec.n_cells <= MATRIX_CELLS_LIMIT
    select = {c: _Selector(spec_objs[c]) for c in children}
    # records are written from the parent's records, or from a variant of them
    # with another Monte Carlo limit (a child that differs only there)
    source = {c: parent if specs[c].mc_reps == spec.mc_reps else c for c in children}
    variants = [(parent, spec.mc_reps, tuple(x.name for x in spec.systems), keep_matrices)]
    variants += [
        (c, specs[c].mc_reps, tuple(x.name for x in specs[c].systems), keep_matrices)
        for c in children
        if source[c] == c
    ]
    units = plan_units(spec)
    for u in units:  # compute the Monte Carlo J as far as any spec using the unit needs
        name = spec.systems[u["system"]].name
        need = [specs[v[0]] for v in variants if name in v[2]]
        top = max(need, key=_mc_limit)
        if top.mc_reps != spec.mc_reps:
            u["mc_reps"] = top.mc_reps
    files, parts, counts = {}, {n: [] for n in [parent] + children}, {}
    task = None
    label = parent + (f" (+{', '.join(children)})" if children else "")
    if bar is not None:
        task = bar.add_task(label, total=len(units))
    t0 = time.perf_counter()
    try:
        for n in [parent] + children:
            d = out / n
            d.mkdir(parents=True, exist_ok=True)
            files[n] = open(d / "records.jsonl", "w")
            counts[n] = 0

        def progress(done, total):
            if bar is not None:
                bar.update(task, completed=done, total=total)

        def emit(n, text, n_lines, cols, mask=None):
            if mask is not None and not mask.all():
                lines = text.split("\n")
                text = "".join(lines[i] + "\n" for i in np.flatnonzero(mask).tolist())
                cols = cols.subset(mask)
                n_lines = len(cols)
            files[n].write(text)
            counts[n] += n_lines
            parts[n].append(cols)

        post = functools.partial(_encode, variants=tuple(variants))
        for item in run_spec(
            spec, progress=progress, units=units, n_jobs=n_jobs, post=post, pool=pool
        ):
            if isinstance(item, list):  # plain records (a run_spec without post)
                if any(source[c] != parent for c in children):
                    raise RuntimeError("records of another mc_reps need UnitResult batches")
                cols = rpt.Columns.from_records(item, matrices=keep_matrices)
                item = {parent: ("".join(_ENCODER.encode(r) + "\n" for r in item), len(item), cols)}
            else:
                item = {n: (text, k, rpt.Columns(data, k)) for n, (text, k, data) in item.items()}
            emit(parent, *item[parent])
            for c in children:
                if source[c] in item:
                    text, k, cols = item[source[c]]
                    emit(c, text, k, cols, select[c].mask(cols))
    except BaseException:
        if bar is not None and task is not None:
            bar.remove_task(task)  # a retry without the failing stage gets a fresh bar
        raise
    finally:
        for fh in files.values():
            fh.close()
    seconds = time.perf_counter() - t0
    results = {}
    for n in [parent] + children:
        run_spec_dict = parse_spec(spec_objs[n]).to_dict()
        notes = [f"stage '{s}' did not run: {why}" for s, why in unavailable.items()]
        (out / n / "spec.json").write_text(
            json.dumps(
                {
                    "spec": spec_objs[n],
                    "normalised": run_spec_dict,
                    "derived_from": parent if n != parent else None,
                    "stages_unavailable": unavailable,
                },
                indent=1,
            )
        )
        results[n] = {
            "spec": spec_objs[n],
            "records": rpt.Columns.concat(parts[n]),
            "n_records": counts[n],
            "notes": notes,
            "derived_from": parent if n != parent else None,
            "seconds": seconds if n == parent else 0.0,
            "stages_unavailable": dict(unavailable),
        }
    return results


def _versions() -> dict:
    import matplotlib
    import numpy
    import scipy

    return {
        "python": platform.python_version(),
        "numpy": numpy.__version__,
        "scipy": scipy.__version__,
        "matplotlib": matplotlib.__version__,
    }


def reproduce(
    out_dir,
    scale: str = "full",
    quiet: bool = False,
    *,
    derive: bool = True,
    n_jobs: int | None = None,
) -> dict:
    """Run the preset ``paper-section-6`` in process and write tables, figures, report.

    ``n_jobs``: worker processes for the pipeline (default: the machine's CPU
    count); the records are the same to the bit for any value.
    Returns ``{"out", "records": {exp: n}, "files": [...], "seconds"}``.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    specs = paper_specs(scale)
    plan = _plan(specs, derive)
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
        # and the figures are rendered in the worker processes.
        builder = rpt.ReportBuilder(
            list(specs),
            {"preset": PRESET_NAME},
            render=None if pool is None else functools.partial(pool.submit, rpt.render_figure),
        )
        background = stack.enter_context(ThreadPoolExecutor(max_workers=1))
        report_parts = []
        with progress_bar(console, quiet=quiet) as bar:
            for parent, children in plan:
                group = _run_group(
                    parent, children, specs, out, None if quiet else bar, pool=pool, n_jobs=n_jobs
                )
                results.update(group)
                for n in group:
                    report_parts.append(
                        background.submit(builder.add, n, _report_input(n, results[n]))
                    )
        t_run = time.perf_counter() - t_start
        for f in report_parts:
            f.result()
        return _write_report(
            out,
            out_dir,
            scale,
            specs,
            results,
            started,
            t_start,
            t_run,
            n_jobs,
            builder,
            console,
            quiet,
        )


def _report_input(name: str, result: dict) -> dict:
    return {
        "spec": result["spec"],
        "records": result["records"],
        "title": EXPERIMENTS[name]["title"],
        "notes": result["notes"],
    }


def _write_report(
    out, out_dir, scale, specs, results, started, t_start, t_run, n_jobs, builder, console, quiet
) -> dict:
    """Provenance, tables, figures, report (``builder`` holds every experiment)."""
    provenance = {
        "preset": PRESET_NAME,
        "scale": scale,
        "command": f"svrobs reproduce --out {out_dir}"
        + ("" if scale == "full" else f" --scale {scale}"),
        "svrobs_version": __version__,
        "git_commit": git_commit(),
        **_versions(),
        "platform": platform.platform(),
        "cpus": os.cpu_count(),
        "started_utc": started.isoformat(timespec="seconds"),
        "records": {n: results[n]["n_records"] for n in specs},
        "derived_from": {
            n: results[n]["derived_from"] for n in specs if results[n]["derived_from"]
        },
        "run_seconds": {
            n: round(results[n]["seconds"], 3) for n in specs if not results[n]["derived_from"]
        },
        "n_jobs": n_jobs,
        "monte_carlo": {
            n: {
                "mc_reps": parse_spec(results[n]["spec"]).mc_reps,
                "mc_runs": parse_spec(results[n]["spec"]).mc_runs,
            }
            for n in specs
            if "cost" in results[n]["spec"].get("stages", [])
        },
        "monte_carlo_decision": MC_DECISION,
        "stages_unavailable": {
            n: results[n]["stages_unavailable"] for n in specs if results[n]["stages_unavailable"]
        },
    }
    t_rep = time.perf_counter()
    report = builder.finish()
    files = []

    def write(name: str, data):
        p = out / name
        if isinstance(data, bytes):
            p.write_bytes(data)
        else:
            p.write_text(data)
        files.append(str(p))

    write("table2.md", rpt.table2_markdown(report.table2))
    write("table2.csv", rpt.table2_csv(report.table2))
    for fg in report.figures:
        if fg.empty:  # nothing to plot: the report carries the note instead
            continue
        write(f"{fg.name}.png", fg.png())
        write(f"{fg.name}.svg", fg.svg())
        write(f"{fg.name}.pdf", fg.pdf())
        write(f"{fg.name}.csv", fg.csv())
    # the part of the report made after the last run (the rest overlaps the runs)
    provenance["report_seconds"] = round(time.perf_counter() - t_rep, 3)
    provenance["run_total_seconds"] = round(t_run, 3)
    report.provenance = provenance
    write("report.md", rpt.render_markdown(report))
    write("report.html", render_html(report))
    write("provenance.json", json.dumps(provenance, indent=1))
    if not quiet:
        console.print(
            f"[green]wrote {len(files)} files to {out}[/] "
            f"(runs {t_run:.1f} s, report {provenance['report_seconds']:.1f} s)"
        )
    return {
        "out": str(out),
        "records": provenance["records"],
        "files": files,
        "seconds": round(time.perf_counter() - t_start, 3),
    }


if __name__ == "__main__":  # python -m service.reports.reproduce DIR [full|reduced]
    reproduce(
        sys.argv[1] if len(sys.argv) > 1 else "reproduce-out",
        sys.argv[2] if len(sys.argv) > 2 else "full",
    )
