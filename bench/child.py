"""Run a bench's measuring code in a fresh Python with one BLAS/OpenMP thread."""

from __future__ import annotations

import json
import os
import subprocess
import sys


def run_child(code: str, arg: object) -> dict:
    """Run ``code`` with ``json.dumps(arg)`` as ``sys.argv[1]`` (repository root on
    PYTHONPATH, one thread) and return the JSON of its last line of output."""
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    root = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    out = subprocess.run(
        [sys.executable, "-c", code, json.dumps(arg)],
        capture_output=True,
        text=True,
        check=True,
        env=env,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])
