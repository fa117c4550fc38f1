"""One BLAS/OpenMP thread per process and one OpenBLAS kernel on every x86-64 host:
the rule and the two ways to apply it (docs/science.md#14-randomness-and-reproducibility).

The pipeline makes many small matrix products; BLAS threads only add
synchronisation to them (2-3x slower on a busy 2-core machine), and with
several worker processes they would oversubscribe the cores. A single
thread also gives the same bits as the in-process run.

OpenBLAS picks its kernels by CPU when it loads, and its AVX-512 kernels round
differently from its AVX2 ones: every cell of a job computed on an AVX-512 host
differed in the last bits from the same cell computed on an AVX2 host. On an
x86-64 CPU with AVX2 and FMA the Haswell (AVX2) kernels are pinned, so records
are the same bits on every such host.

* :data:`THREAD_ENV`: the environment variables that fix the pool sizes of
  the BLAS/OpenMP libraries and OpenBLAS's kernel (:func:`blas_kernel_env`);
  :func:`single_thread_env` sets them (before numpy is imported, e.g. in a
  worker process, the command line or a child's environment).
* :data:`blas_single_thread`: limits BLAS at run time (threadpoolctl, when
  installed): ``with blas_single_thread(): ...`` or ``.limit_process()``.
"""

from __future__ import annotations

import os
import platform
from collections.abc import MutableMapping
from contextlib import AbstractContextManager, nullcontext
from typing import Any

BLAS_KERNEL = "Haswell"  # OpenBLAS's AVX2 + FMA kernels
KERNEL_FLAGS = frozenset({"avx2", "fma"})  # what they need of the CPU


def blas_kernel_env(cpuinfo: str | None = None, machine: str | None = None) -> dict[str, str]:
    """``{"OPENBLAS_CORETYPE": BLAS_KERNEL}`` on an x86-64 Linux CPU whose flags (the
    first ``flags`` line of ``/proc/cpuinfo``, or ``cpuinfo``) include AVX2 and FMA;
    else nothing (OpenBLAS would stop on an instruction such a CPU lacks)."""
    if (machine or platform.machine()).lower() not in ("x86_64", "amd64"):
        return {}
    if cpuinfo is None:
        try:
            with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
                cpuinfo = f.read(1 << 16)
        except OSError:
            return {}
    for line in cpuinfo.splitlines():
        name, _, value = line.partition(":")
        if name.strip() == "flags":
            return {"OPENBLAS_CORETYPE": BLAS_KERNEL} if KERNEL_FLAGS <= set(value.split()) else {}
    return {}


THREAD_ENV = {
    "OPENBLAS_NUM_THREADS": "1",
    "OMP_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "NUMEXPR_NUM_THREADS": "1",
    "VECLIB_MAXIMUM_THREADS": "1",
    **blas_kernel_env(),
}


def single_thread_env(environ: MutableMapping[str, str] | None = None) -> MutableMapping[str, str]:
    """Set every :data:`THREAD_ENV` variable not already set (default: ``os.environ``)."""
    environ = os.environ if environ is None else environ
    for name, value in THREAD_ENV.items():
        environ.setdefault(name, value)
    return environ


class _BlasSingleThread:
    """Context: BLAS limited to one thread (when threadpoolctl is installed)."""

    def __init__(self) -> None:
        self._controller: Any = None
        self._tried = False

    def _get(self) -> Any:
        if not self._tried:
            self._tried = True
            try:
                from threadpoolctl import ThreadpoolController

                self._controller = ThreadpoolController()
            except Exception:  # noqa: BLE001 - optional dependency, any failure: no limit
                self._controller = None
        return self._controller

    def __call__(self) -> AbstractContextManager[Any]:
        c = self._get()
        if c is None:
            return nullcontext()
        ctx: AbstractContextManager[Any] = c.limit(limits=1, user_api="blas")
        return ctx

    def limit_process(self) -> None:
        c = self._get()
        if c is not None:
            c.limit(limits=1, user_api="blas")


blas_single_thread = _BlasSingleThread()
