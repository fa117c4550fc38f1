"""Process-pool execution of independent calls, results in submission order."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Executor
from contextlib import contextmanager
from typing import Any

from .threads import blas_single_thread


def _worker_init() -> None:
    blas_single_thread.limit_process()


def _noop() -> None:
    return None


@contextmanager
def open_pool(n_jobs: int) -> Iterator[Executor | None]:
    """A process pool of ``n_jobs`` workers for :func:`svrobs_core.run_spec` (None
    for n_jobs <= 1).

    Workers are forked where the platform allows (no re-import) and started
    at once; each limits BLAS to one thread (the products are small and the
    cores are taken by the workers)."""
    if n_jobs <= 1:
        yield None
        return
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    ctx = mp.get_context("fork") if "fork" in mp.get_all_start_methods() else None
    with ProcessPoolExecutor(max_workers=n_jobs, mp_context=ctx, initializer=_worker_init) as pool:
        for f in [pool.submit(_noop) for _ in range(n_jobs)]:
            f.result()
        yield pool


def run_ordered(
    pool: Executor,
    fn: Callable[..., Any],
    calls: Sequence[tuple[Any, ...]],
    progress: Callable[[int, int], None] | None = None,
) -> Iterator[Any]:
    """Yield ``fn(*args)`` for every ``args`` of ``calls``, in order, computed in ``pool``.

    Everything is submitted at once; ``progress(done, total)`` after each
    result; the calls not yet started are cancelled if the caller stops."""
    futures = {i: pool.submit(fn, *args) for i, args in enumerate(calls)}
    try:
        for i in range(len(calls)):
            yield futures.pop(i).result()
            if progress is not None:
                progress(i + 1, len(calls))
    finally:
        for f in futures.values():
            f.cancel()
