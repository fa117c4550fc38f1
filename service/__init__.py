"""svrobs service: the REST API, DB models and broker configuration shared with the worker.

An API process computes too (a dataset job's validation on request, the reports'
summaries and figures): BLAS's threads and kernel are pinned as in a worker, before
numpy is imported (:mod:`svrobs_core.threads`).
"""

from svrobs_core.threads import single_thread_env

single_thread_env()
