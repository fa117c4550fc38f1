"""`make run` on a fresh clone: the runtime only (the test extras come with `make test`),
with a progress line per step, then `svrobs serve` with the HOST and PORT given.

Read from `make -n` (what make would run, nothing run) with a virtual environment
that does not exist yet, as on a fresh clone."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def dry_run(tmp_path: Path, *args: str) -> list[str]:
    venv = tmp_path / "venv"
    # not the flags of a `make test` this runs under
    env = {k: v for k, v in os.environ.items() if k not in ("MAKEFLAGS", "MFLAGS", "MAKELEVEL")}
    run = subprocess.run(
        ["make", "-n", "--no-print-directory", f"VENV={venv}", *args],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        check=True,
        timeout=30,
    )
    return run.stdout.splitlines()


def test_make_run_installs_the_runtime_only_and_says_so(tmp_path):
    lines = dry_run(tmp_path, "run")
    installs = [ln for ln in lines if "pip install" in ln]
    assert len(installs) == 1, lines
    assert installs[0].rstrip().endswith(" -e .") and "[test]" not in installs[0]
    assert "--progress-bar on" in installs[0]
    steps = [ln for ln in lines if ln.startswith("echo ") and "svrobs: [" in ln]
    assert [s.split("[")[1][:3] for s in steps] == ["1/2", "2/2"], lines
    assert lines[-1].split() == [f"{tmp_path / 'venv'}/bin/svrobs", "serve"]


def test_make_run_passes_host_and_port_to_serve(tmp_path):
    last = dry_run(tmp_path, "run", "PORT=8010", "HOST=0.0.0.0")[-1]
    assert last.split()[1:] == ["serve", "--host", "0.0.0.0", "--port", "8010"]


def test_make_test_adds_the_test_extras(tmp_path):
    lines = dry_run(tmp_path, "test")
    assert any("pip install" in ln and "'.[test]'" in ln for ln in lines), lines
