"""OpenBLAS's kernel is pinned on x86-64 hosts with AVX2 and FMA
(docs/science.md#14-randomness-and-reproducibility): records are the same bits on
an AVX-512 host as on an AVX2 one."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from svrobs_core.threads import BLAS_KERNEL, THREAD_ENV, blas_kernel_env

ROOT = Path(__file__).resolve().parents[2]
FLAGS = "processor\t: 0\nflags\t\t: fpu sse2 avx {extra}\nbogomips\t: 1\n"

# the records of a small spec, in a fresh interpreter that pins BLAS as a worker does
RECORDS = """
import json, sys
from svrobs_core.threads import single_thread_env
single_thread_env()
from svrobs_core import parse_spec, run_spec
spec = {"systems": ["paper-stable", "paper-unstable"], "sigma_w": [1.0], "N": [10],
        "gamma": [0.05], "estimators": ["ols", "svr"], "reps": 2,
        "stages": ["estimate", "bounds", "gain", "cost"], "seed": 1}
recs = [r for b in run_spec(parse_spec(spec)) for r in b]
print(json.dumps([[r["A_hat"], r["L"], r["J_exact"]] for r in recs]))
"""


@pytest.mark.parametrize(
    "cpuinfo, machine, pinned",
    [
        (FLAGS.format(extra="fma avx2"), "x86_64", True),
        (FLAGS.format(extra="fma avx2 avx512f avx512dq"), "x86_64", True),
        (FLAGS.format(extra="avx2"), "x86_64", False),  # no FMA
        (FLAGS.format(extra="fma"), "x86_64", False),  # no AVX2
        ("processor\t: 0\n", "x86_64", False),  # no flags line
        (FLAGS.format(extra="fma avx2"), "aarch64", False),
    ],
)
def test_the_kernel_is_pinned_only_where_the_cpu_runs_it(cpuinfo, machine, pinned):
    want = {"OPENBLAS_CORETYPE": BLAS_KERNEL} if pinned else {}
    assert blas_kernel_env(cpuinfo, machine) == want


def _cpu_flags() -> set[str]:
    try:
        text = Path("/proc/cpuinfo").read_text(errors="replace")
    except OSError:
        return set()
    return next(
        (set(ln.split(":", 1)[1].split()) for ln in text.splitlines() if ln.startswith("flags")),
        set(),
    )


def _records(**env: str) -> list:
    base = {k: v for k, v in os.environ.items() if not k.startswith("OPENBLAS_")}
    out = subprocess.run(
        [sys.executable, "-c", RECORDS],
        cwd=str(ROOT),
        env={**base, **env},
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    return json.loads(out.stdout)


@pytest.mark.skipif(
    "OPENBLAS_CORETYPE" not in THREAD_ENV, reason="no AVX2 + FMA on this x86-64 CPU"
)
def test_records_do_not_depend_on_the_hosts_native_kernel():
    """A process left to OpenBLAS's own choice (no OPENBLAS_CORETYPE) computes the
    bits of the pinned kernel. On an AVX-512 host, the AVX-512 kernel's records
    differ: without the pin, the host would decide the bits."""
    native = _records()
    pinned = _records(OPENBLAS_CORETYPE=BLAS_KERNEL)
    assert native == pinned
    if "avx512f" in _cpu_flags():
        assert _records(OPENBLAS_CORETYPE="SkylakeX") != pinned


# records the environment at numpy's first import, then runs an entry point
AT_NUMPY = """
import os, sys
from importlib.abc import MetaPathFinder
seen = {}
class Watch(MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "numpy" and not seen:
            seen.update(os.environ)
        return None
sys.meta_path.insert(0, Watch())
sys.argv = ["svrobs", "--help"]
try:
    exec(sys.stdin.read())
except SystemExit:
    pass
import numpy  # noqa: F401 - loaded by now in any case
from svrobs_core.threads import THREAD_ENV
print(all(seen.get(k) == v for k, v in THREAD_ENV.items()))
"""


@pytest.mark.parametrize(
    "entry",
    [
        "import service.app",  # uvicorn service.app:app
        "import worker.celery_app",  # celery -A worker.celery_app
        "from svrobs_cli.__main__ import main; main()",  # the svrobs console script
    ],
)
def test_each_entry_pins_blas_before_numpy_loads(entry):
    """The API, the worker and ``svrobs`` have the environment of :data:`THREAD_ENV`
    set when numpy first loads (OpenBLAS reads it then, once)."""
    env = {k: v for k, v in os.environ.items() if k not in THREAD_ENV}
    out = subprocess.run(
        [sys.executable, "-c", AT_NUMPY],
        input=entry,
        cwd=str(ROOT),
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.stdout.strip().splitlines()[-1:] == ["True"], out.stdout[-500:] + out.stderr[-2000:]
