"""`svrobs run-local SPEC.json --out DIR`: the core in process, records to files.

Writes ``DIR/records.jsonl`` (one section 10 record per line, null never
NaN) and ``DIR/summary.json`` (mean/std/count per group), with a progress
bar on stderr.
"""

from __future__ import annotations

import json
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

from svrobs_core import parse_spec, plan_units, summarize
from svrobs_core.runner import run_unit_result


def load_spec_file(path: Path) -> dict:
    """Read a JSON (or YAML, if PyYAML is installed) spec file."""
    text = Path(path).read_text()
    if Path(path).suffix in (".yaml", ".yml"):
        import yaml  # optional

        return yaml.safe_load(text)
    return json.loads(text)


def run_local(spec_obj: dict, out: Path, *, quiet: bool = False) -> dict:
    """Run a spec in process; returns ``{"records": n, "out": str}``."""
    spec = parse_spec(spec_obj)
    units = plan_units(spec)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    records: list[dict] = []
    console = Console(stderr=True)
    with Progress(
        "[progress.description]{task.description}",
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
        disable=quiet,
        transient=False,
    ) as bar:
        task = bar.add_task("work units", total=len(units))
        with open(out / "records.jsonl", "w") as fh:
            for unit in units:
                result = run_unit_result(spec, unit)
                lines = result.json_lines()  # = json.dumps(record) per record, built per field
                if lines:
                    fh.write("\n".join(lines) + "\n")
                records += result.records()
                bar.advance(task)
    summary = {"spec": spec.to_dict(), "groups": summarize(records)}
    (out / "summary.json").write_text(json.dumps(summary, indent=1, allow_nan=False))
    return {"records": len(records), "out": str(out)}
