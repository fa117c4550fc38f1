"""`svrobs run-local` refuses what it cannot run, before running.

Each case is a spec it refuses, run as a user runs it (a subprocess):
one line on stderr naming the field, exit status 2, no traceback, and no
records file left behind.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
BASE = {"systems": ["paper-stable"], "sigma_w": [1.0], "N": [10], "reps": 1}


def run_local(tmp_path, spec: dict, *extra: str) -> subprocess.CompletedProcess:
    (tmp_path / "spec.json").write_text(json.dumps(spec))
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run(
        [sys.executable, "-m", "svrobs_cli", "run-local", str(tmp_path / "spec.json")]
        + ["--out", str(tmp_path / "out"), "--quiet", *extra],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )


CASES = [
    # the work of the whole job, refused by the cost model (was 4.6 GB after 40 s)
    ({"N": {"start": 1, "stop": 100_000}, "estimators": ["ols"]}, "CPU seconds", "error: "),
    # 10^11 records: refused by the cell cap from the axis lengths, before the cost model
    (
        {"N": {"start": 1, "stop": 100_000}, "reps": 1_000_000},
        "SVROBS_MAX_JOB_CELLS",
        "error: invalid spec: spec",
    ),
    # a hard cap (was "Unable to allocate 29.8 GiB")
    ({"N": [100_000_000]}, "N[0]: must be <= 1000000", "error: invalid spec: N[0]"),
    # was "SVD did not converge"
    (
        {"systems": [{"name": "big", "A": [[1e308]], "B": [[1.0]]}]},
        "larger than 1e+100",
        "error: invalid spec: systems[0].A",
    ),
    # was a mid-run failure naming `sigma_v`, with an empty records.jsonl
    (
        {
            "systems": [
                {
                    "name": "c",
                    "A": [[0.5, 0.0], [0.0, 0.5]],
                    "B": [[1.0], [0.0]],
                    "C": [[1.0, 0.0], [1.0, 1e-13]],
                    "sigma_v": 0.0,
                }
            ]
        },
        "cond(C)",
        "error: invalid spec: systems[0].sigma_v",
    ),
    ({"sigma_w": ["0.5"]}, "must be a number", "error: invalid spec: sigma_w[0]"),
    ({"reps": 3.0}, "must be an integer", "error: invalid spec: reps"),
]


@pytest.mark.parametrize("extra, text, prefix", CASES)
def test_refused_before_running_with_the_field_named(tmp_path, extra, text, prefix):
    proc = run_local(tmp_path, {**BASE, **extra})
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2, proc.stderr
    assert len(lines) == 1 and lines[0].startswith(prefix) and text in lines[0], lines
    assert "Traceback" not in proc.stderr + proc.stdout
    assert not (tmp_path / "out" / "records.jsonl").exists()


def test_memory_limit_names_the_field_and_gives_estimate_and_limit(tmp_path):
    spec = {**BASE, "N": [900_000], "estimators": ["ols"], "stages": ["estimate"]}
    proc = run_local(tmp_path, spec, "--max-memory-mb", "256")
    assert proc.returncode == 2
    line = proc.stderr.strip()
    assert line.startswith("error: invalid spec: N: one work unit") and "limit of 256 MB" in line
    assert not (tmp_path / "out").exists()


def test_a_spec_under_the_limits_runs(tmp_path):
    proc = run_local(tmp_path, BASE, "--max-cpu-seconds", "60", "--max-memory-mb", "1024")
    assert proc.returncode == 0, proc.stderr
    assert len((tmp_path / "out" / "records.jsonl").read_text().splitlines()) == 2
