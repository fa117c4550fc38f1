"""One BLAS/OpenMP thread per process: the rule and the two ways to apply it.

The pipeline makes many small matrix products; BLAS threads only add
synchronisation to them (2-3x slower on a busy 2-core machine), and with
several worker processes they would oversubscribe the cores. A single
thread also gives the same bits as the in-process run.

* :data:`THREAD_ENV`: the environment variables that fix the pool sizes of
  the BLAS/OpenMP libraries; :func:`single_thread_env` sets them (before
  numpy is imported, e.g. in a worker process or a child's environment).
* :data:`blas_single_thread`: limits BLAS at run time (threadpoolctl, when
  installed): ``with blas_single_thread(): ...`` or ``.limit_process()``.
"""

from __future__ import annotations

import os
from collections.abc import MutableMapping
from contextlib import AbstractContextManager, nullcontext
from typing import Any

THREAD_ENV = {
    "OPENBLAS_NUM_THREADS": "1",
    "OMP_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "NUMEXPR_NUM_THREADS": "1",
    "VECLIB_MAXIMUM_THREADS": "1",
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
