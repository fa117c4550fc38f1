"""svrobs worker: the Celery app, the thin ``svrobs.run_unit`` task and the tick.

BLAS/OpenMP pools are pinned to one thread before numpy is imported anywhere in
a worker process: one unit per process is the unit of parallelism, and a
single-threaded BLAS gives the same bits as the in-process run.
"""

from svrobs_core.threads import single_thread_env

single_thread_env()
