"""The embedded stack (uvicorn + celery worker on SQLite and the filesystem broker,
real processes) with its queue folder poisoned: a 0-byte ``*.msg`` file, a garbage
one, and envelopes Celery cannot run (a body that is not JSON, a task nobody
registered) are dropped in front of a real job. The job succeeds with the records
the core computes in process, the worker process that was running before is still
the one running, and the files that are not messages are in ``broker/bad``."""

from __future__ import annotations

import base64
import json
import os

import pytest

from tests.integration.stack import Stack, cell_key, in_process_records, same, submit

pytestmark = [pytest.mark.integration, pytest.mark.timeout(240)]

SPEC = {
    "systems": ["paper-stable"],
    "sigma_w": [0.5],
    "N": [10, 20],
    "gamma": [0.05],
    "estimators": ["ols", "svr"],
    "reps": 2,
    "stages": ["estimate", "bounds"],
    "seed": 5,
}


def _envelope(body: bytes, headers: dict) -> bytes:
    return json.dumps(
        {
            "body": base64.b64encode(body).decode(),
            "content-type": "application/json",
            "content-encoding": "utf-8",
            "headers": headers,
            "properties": {
                "body_encoding": "base64",
                "delivery_tag": "poison",
                "delivery_info": {"exchange": "svrobs", "routing_key": "svrobs"},
                "priority": 0,
            },
        }
    ).encode()


@pytest.fixture
def stack(tmp_path, request):
    """The embedded stack's API and one worker (the worker's process is checked below)."""
    st = Stack("embedded", tmp_path)
    request.addfinalizer(st.teardown)
    st.setup()
    st.start_api_and_worker()
    return st


def test_poisoned_queue_folder_does_not_stop_the_worker(stack):
    queue = stack.root / "broker" / "queue"
    worker = stack.children["worker1"]
    files = {
        "00000000000000000000_empty.svrobs.msg": b"",
        "00000000000000000001_garbage.svrobs.msg": os.urandom(200).replace(b"{", b"x"),
        "00000000000000000002_not-json-body.svrobs.msg": _envelope(
            b"\x00 not json", {"task": "svrobs.run_unit", "id": "p1"}
        ),
        "00000000000000000003_unknown-task.svrobs.msg": _envelope(
            b"[[], {}, {}]", {"task": "no.such.task", "id": "p2"}
        ),
    }
    for name, data in files.items():
        (queue / name).write_bytes(data)

    with stack.client() as c:
        job = submit(c, SPEC)
        done = stack.wait_job(c, job["id"], timeout=180)
        assert done["status"] == "succeeded", done
        r = c.get(f"/jobs/{job['id']}/results", params={"format": "jsonl"})
    assert r.status_code == 200, r.text
    got = [json.loads(line) for line in r.text.splitlines() if line.strip()]

    assert worker.poll() is None, stack.log_tail("worker1")  # the same process, still up
    assert stack.children["worker1"] is worker
    bad = sorted(p.name for p in (stack.root / "broker" / "bad").iterdir())
    assert bad == sorted(list(files)[:2])  # the two files that are not kombu messages
    assert not [p for p in queue.iterdir() if p.name.endswith(".msg")]  # all taken
    log = (stack.logs / "worker1.log").read_text()
    assert log.count("is not a message") == 2, stack.log_tail("worker1")

    expected = in_process_records(SPEC)
    assert len(got) == len(expected)
    diffs = [d for rec in got for d in same(rec, expected[cell_key(rec)], repr(cell_key(rec)))]
    assert not diffs, diffs[:5]
