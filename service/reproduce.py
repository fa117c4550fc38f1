"""`svrobs reproduce --out DIR`: the paper's Section 6 (preset ``paper-section-6``) in process.

Runs E1..E4 of ``svrobs_core.paper.paper_specs(scale)`` with ``run_spec`` and
writes::

    DIR/<experiment>/records.jsonl   one section 10 record per line (null, never NaN)
    DIR/<experiment>/spec.json       the spec that ran
    DIR/table2.md, DIR/table2.csv    Table 2, ours beside the published values
    DIR/<figure>.png, .svg           Figs. 2-5 and the figures beyond the paper
    DIR/report.md, DIR/report.html   the whole report (HTML self-contained)
    DIR/provenance.json

Sub-grids are not recomputed: when an experiment's spec equals another's
restricted to some systems / gammas / estimators at the same seed-key
indices (E1 inside E2, E3 inside E4), its records are the other run's
records for those cells (SPEC section 1: a cell's numbers depend only on the
seed and its key). Pass ``derive=False`` to run every spec on its own.

If a pipeline stage is not available in this build (it raises
``NotImplementedError`` or its module is missing), the experiment is rerun
without that stage, the report says so, and the figures needing it show
"no data".
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

from svrobs_core import __version__, parse_spec, plan_units, run_spec
from svrobs_core import report as rpt
from svrobs_core.paper import EXPERIMENTS, PRESET_NAME, paper_specs

# Above this many cells an experiment keeps no A_hat/B_hat in memory for the
# report (only E1/E2-sized grids draw the figures that need them).
MATRIX_CELLS_LIMIT = 200_000
# One reusable encoder: about a third faster than json.dumps(..., allow_nan=False) per record.
_ENCODER = json.JSONEncoder(allow_nan=False)


def _derivable(child: dict, parent: dict) -> bool:
    """True when every record of ``child`` is a record of ``parent`` (same keys)."""
    c, p = parse_spec(child), parse_spec(parent)
    cd, pd = c.to_dict(), p.to_dict()
    for k in cd:
        if k in ("systems", "gamma", "estimators"):
            continue
        if cd[k] != pd[k]:
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
        cands = [p for p in specs if p != child and size[p] >= size[child]
                 and _derivable(specs[child], specs[p])]
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


def _run_group(parent: str, children: list[str], specs: dict[str, dict], out: Path,
               bar: Progress | None) -> dict[str, dict]:
    """Run ``parent`` once (streaming records to files), fill the children too."""
    names = [parent] + children
    spec_objs = {n: json.loads(json.dumps(specs[n])) for n in names}
    unavailable: dict[str, str] = {}
    while True:
        try:
            return _stream(parent, children, spec_objs, out, bar, unavailable)
        except (NotImplementedError, ImportError) as exc:
            stages = spec_objs[parent].get("stages", ["estimate", "bounds"])
            if len(stages) <= 1:
                raise  # not even the estimate stage runs: nothing to report
            dropped = stages[-1]
            unavailable[dropped] = f"{type(exc).__name__}: {exc}".strip()
            for n in names:
                spec_objs[n]["stages"] = [s for s in spec_objs[n]["stages"] if s != dropped]
            if bar is not None:
                bar.console.print(f"[yellow]{parent}: stage '{dropped}' is not available in "
                                  f"this build ({unavailable[dropped]}); rerunning without it")


def _stream(parent, children, spec_objs, out: Path, bar, unavailable) -> dict[str, dict]:
    spec = parse_spec(spec_objs[parent])
    units = plan_units(spec)
    keep_matrices = spec.n_cells <= MATRIX_CELLS_LIMIT
    select = {c: _Selector(spec_objs[c]) for c in children}
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

        for batch in run_spec(spec, progress=progress, units=units):
            lines = [_ENCODER.encode(r) + "\n" for r in batch]
            files[parent].writelines(lines)
            counts[parent] += len(batch)
            cols = rpt.Columns.from_records(batch, matrices=keep_matrices)
            parts[parent].append(cols)
            for c in children:
                mask = [select[c](r) for r in batch]
                files[c].writelines(line for line, keep in zip(lines, mask) if keep)
                counts[c] += sum(mask)
                parts[c].append(cols.subset(mask))
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
        (out / n / "spec.json").write_text(json.dumps(
            {"spec": spec_objs[n], "normalised": run_spec_dict,
             "derived_from": parent if n != parent else None,
             "stages_unavailable": unavailable}, indent=1))
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


def _git_commit() -> str | None:
    try:
        root = Path(__file__).resolve().parent.parent
        res = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True,
                             text=True, timeout=5, env={**os.environ, "GIT_OPTIONAL_LOCKS": "0"})
        return res.stdout.strip() or None if res.returncode == 0 else None
    except (OSError, subprocess.SubprocessError):
        return None


def _versions() -> dict:
    import matplotlib
    import numpy
    import scipy

    return {"python": platform.python_version(), "numpy": numpy.__version__,
            "scipy": scipy.__version__, "matplotlib": matplotlib.__version__}


def reproduce(out_dir, scale: str = "full", quiet: bool = False, *, derive: bool = True) -> dict:
    """Run the preset ``paper-section-6`` in process and write tables, figures, report.

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
    with Progress("[progress.description]{task.description}", BarColumn(),
                  MofNCompleteColumn(), TimeElapsedColumn(), console=console,
                  disable=quiet, transient=False) as bar:
        for parent, children in plan:
            results.update(_run_group(parent, children, specs, out, None if quiet else bar))
    t_run = time.perf_counter() - t_start

    provenance = {
        "preset": PRESET_NAME,
        "scale": scale,
        "command": f"svrobs reproduce --out {out_dir}" + ("" if scale == "full"
                                                          else f" --scale {scale}"),
        "svrobs_version": __version__,
        "git_commit": _git_commit(),
        **_versions(),
        "platform": platform.platform(),
        "cpus": os.cpu_count(),
        "started_utc": started.isoformat(timespec="seconds"),
        "records": {n: results[n]["n_records"] for n in specs},
        "derived_from": {n: results[n]["derived_from"] for n in specs
                         if results[n]["derived_from"]},
        "run_seconds": {n: round(results[n]["seconds"], 3) for n in specs
                        if not results[n]["derived_from"]},
        "stages_unavailable": {n: results[n]["stages_unavailable"] for n in specs
                               if results[n]["stages_unavailable"]},
    }
    t_rep = time.perf_counter()
    report = rpt.build_report(
        {n: {"spec": results[n]["spec"], "records": results[n]["records"],
             "title": EXPERIMENTS[n]["title"], "notes": results[n]["notes"]} for n in specs},
        provenance,
    )
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
        write(f"{fg.name}.png", fg.png())
        write(f"{fg.name}.svg", fg.svg())
    provenance["report_seconds"] = round(time.perf_counter() - t_rep, 3)
    provenance["run_total_seconds"] = round(t_run, 3)
    report.provenance = provenance
    write("report.md", rpt.render_markdown(report))
    write("report.html", rpt.render_html(report))
    write("provenance.json", json.dumps(provenance, indent=1))
    if not quiet:
        console.print(f"[green]wrote {len(files)} files to {out}[/] "
                      f"(runs {t_run:.1f} s, report {provenance['report_seconds']:.1f} s)")
    return {"out": str(out), "records": provenance["records"], "files": files,
            "seconds": round(time.perf_counter() - t_start, 3)}


if __name__ == "__main__":  # python -m service.reproduce DIR [full|reduced]
    reproduce(sys.argv[1] if len(sys.argv) > 1 else "reproduce-out",
              sys.argv[2] if len(sys.argv) > 2 else "full")
