"""The files a finished ``svrobs reproduce`` writes: provenance, Table 2, the figures,
report.md and report.html (docs/performance.md#one-pass for the run itself)."""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.config import get_settings
from service.db.provenance import git_commit
from svrobs_cli.reproduce_plan import normals_drawn
from svrobs_core import __version__, parse_spec
from svrobs_core import report as rpt
from svrobs_core.paper import EXPERIMENTS, MC_DECISION, PRESET_NAME
from svrobs_lab.report_html import render_html


def _versions() -> dict:
    import matplotlib
    import scipy

    return {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "matplotlib": matplotlib.__version__,
    }


def report_input(name: str, result: dict) -> dict:
    return {
        "spec": result["spec"],
        "records": result["records"],
        "title": EXPERIMENTS[name]["title"],
        "notes": [],
    }


@dataclass
class FinishedRun:
    """What the report's provenance says about a finished run."""

    out: Path
    command: str
    scale: str
    specs: dict
    groups: list
    results: dict
    started: _dt.datetime
    t_start: float
    t_run: float
    n_jobs: int
    report_cpu: dict


def write_report(run: FinishedRun, builder, console, quiet) -> dict:
    """Provenance, tables, figures, report (``builder`` holds every experiment)."""
    out, specs, results, groups = run.out, run.specs, run.results, run.groups
    t_start, t_run, report_cpu = run.t_start, run.t_run, run.report_cpu
    provenance = {
        "preset": PRESET_NAME,
        "scale": run.scale,
        "experiments": list(specs),
        "command": run.command,
        "svrobs_version": __version__,
        "git_commit": git_commit(get_settings().GIT_COMMIT),
        **_versions(),
        "platform": platform.platform(),
        "cpus": os.cpu_count(),
        "started_utc": run.started.isoformat(timespec="seconds"),
        "records": {n: results[n]["n_records"] for n in specs},
        "derived_from": {
            n: results[n]["derived_from"] for n in specs if results[n]["derived_from"]
        },
        "shares_data_of": {
            n: results[n]["shares_data_of"] for n in specs if results[n]["shares_data_of"]
        },
        "run_seconds": {g.parent: round(results[g.parent]["seconds"], 3) for g in groups},
        "worker_cpu_seconds": {n: round(results[n]["cpu_seconds"], 3) for n in specs},
        "normals": normals_drawn(specs, groups),
        "rng": {n: parse_spec(specs[n]).rng for n in specs},
        "draws": {n: parse_spec(specs[n]).draws for n in specs},
        "n_jobs": run.n_jobs,
        "monte_carlo": {
            n: {
                "mc_reps": parse_spec(results[n]["spec"]).mc_reps,
                "mc_runs": parse_spec(results[n]["spec"]).mc_runs,
            }
            for n in specs
            if "cost" in results[n]["spec"].get("stages", [])
        },
        "monte_carlo_decision": MC_DECISION,
    }
    t_rep, c_rep = time.perf_counter(), time.thread_time()
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
    # CPU of this process's report work: per experiment as it arrived, then the rest
    provenance["report_cpu_seconds"] = {
        **{n: round(report_cpu[n], 3) for n in specs},
        "finish": round(time.thread_time() - c_rep, 3),
    }
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
