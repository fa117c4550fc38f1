"""svrobs worker: the Celery app, the thin ``svrobs.run_unit`` task and the tick.

BLAS/OpenMP pools are pinned to one thread before numpy is imported anywhere in
a worker process: one unit per process is the unit of parallelism, and a
single-threaded BLAS gives the same bits as the in-process run.
"""

import os

for _var in (
    "OPENBLAS_NUM_THREADS",
    "OMP_NUM_THREADS",
    "MKL_NUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
):
    os.environ.setdefault(_var, "1")
