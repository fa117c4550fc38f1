"""Real-process stacks for the integration tests.

``stack`` is module-scoped and parametrized over

* ``embedded``: a temporary SQLite file and Celery's filesystem broker in
  tmp_path (always runs);
* ``pg``: ``SVROBS_TEST_DATABASE_URL`` + ``SVROBS_TEST_BROKER_URL`` (CI sets
  them; skipped only when unset). Each stack migrates a fresh PostgreSQL
  schema of its own (``search_path`` in the URL; dropped at teardown) and
  flushes the Redis database number of the broker URL before and after.

A stack migrates (``svrobs_cli.serve.prepare_dirs`` and ``migrate``, what
``svrobs serve`` runs first, in the test process with the stack's settings),
creates a team and key, and starts uvicorn on a free
port plus one celery worker - the exact commands ``svrobs_cli.serve`` uses, from
``svrobs_cli.serve.child_commands``. Tests can stop/start workers, start beat or a
second API with another environment. Teardown terminates every child, then
kills its process group: no orphans. Logs are under the stack's folder and
their tails are printed when a wait times out.
"""

from __future__ import annotations

import pytest

from .stack import API, PG_URL, READY_TIMEOUT, REDIS_URL, ROOT, Stack, free_port  # noqa: F401


def _stack_params():
    marks_pg = (
        []
        if (PG_URL and REDIS_URL)
        else [pytest.mark.skip(reason="SVROBS_TEST_DATABASE_URL / SVROBS_TEST_BROKER_URL not set")]
    )
    return [pytest.param("embedded", id="embedded"), pytest.param("pg", id="pg", marks=marks_pg)]


@pytest.fixture(scope="module", params=_stack_params())
def stack(request, tmp_path_factory):
    """A migrated stack with a team key, the API and one worker running."""
    st = Stack(request.param, tmp_path_factory.mktemp(f"stack-{request.param}"))
    try:
        st.setup()
        st.start_api_and_worker()
        yield st
    finally:
        st.teardown()
