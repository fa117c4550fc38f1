"""The embedded stack (uvicorn + celery worker on SQLite and the filesystem broker,
real processes) with its queue folder poisoned: a 0-byte ``*.msg`` file, a garbage
one, and envelopes Celery cannot run (a body that is not JSON, a task nobody
registered) are dropped in front of a real job. The job succeeds with the records
the core computes in process, the worker process that was running before is still
the one running, and the files that are not messages are in ``broker/bad``.

Then, on both stacks (the PostgreSQL + Redis one when its URLs are set), kombu
messages whose task message Celery cannot run and ``run_unit`` arguments that are
not unit ids are published in front of a job: each is one ERROR line, none stops or
restarts the worker, none is retried (docs/security.md#task-messages)."""

from __future__ import annotations

import base64
import json
import os
import subprocess
import sys
import time

import pytest

from service.redis_broker import BAD_LIST as REDIS_BAD_LIST
from tests.integration.stack import (
    PG_URL,
    REDIS_URL,
    ROOT,
    Stack,
    cell_key,
    in_process_records,
    same,
    submit,
)

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


# ----------------------------------------------------------------------------- task messages
# Well-formed envelopes whose task message Celery cannot run: each one is published
# through kombu (so the same test covers both brokers), then a real job follows it.
_OK = {"task": "svrobs.run_unit", "lang": "py", "retries": 0}
MALFORMED = {
    "no-id": ({"task": "svrobs.run_unit"}, [[1], {}, {}]),
    "empty-id": ({**_OK, "id": ""}, [[1], {}, {}]),
    "body-is-int": ({**_OK, "id": "m-int"}, 5),
    "body-short": ({**_OK, "id": "m-short"}, [[1]]),
    "body-dict": ({**_OK, "id": "m-dict"}, {"args": [1]}),
    "args-not-list": ({**_OK, "id": "m-args"}, ["x", {}, {}]),
    "timelimit-text": ({**_OK, "id": "m-tl", "timelimit": "abc"}, [[1], {}, {}]),
    "timelimit-words": ({**_OK, "id": "m-tl2", "timelimit": ["a", "b"]}, [[1], {}, {}]),
    "eta-text": ({**_OK, "id": "m-eta", "eta": "not-a-date"}, [[1], {}, {}]),
    "retries-text": ({**_OK, "id": "m-retries", "retries": "x"}, [[1], {}, {}]),
    "tick-no-id": ({"task": "svrobs.tick"}, [[], {}, {}]),
    "unknown-task-no-id": ({"task": "no.such.task"}, [[], {}, {}]),
    "task-is-list": ({"task": ["svrobs.run_unit"], "id": "m-task"}, [[1], {}, {}]),
    # iterated by the worker's revoke check in its main process
    "stamped-int": ({**_OK, "id": "m-stamped", "stamped_headers": 5}, [[1], {}, {}]),
    "stamped-lists": ({**_OK, "id": "m-stamped2", "stamped_headers": [["x"]]}, [[1], {}, {}]),
    "stamps-list": (
        {**_OK, "id": "m-stamps", "stamped_headers": ["x"], "stamps": [1]},
        [[1], {}, {}],
    ),
}
# run_unit's own argument: not a unit id (one line each, never retried)
BAD_UNIT_IDS = [["abc"], [None], [2**70], [True]]
# Raw items on the Redis list that are not kombu messages at all (redis-cli LPUSH):
# each one is one ERROR line and is kept on the list REDIS_BAD_LIST.
RAW_ITEMS = [b"not json", b"\xff\xfe\x00", b"5", b'{"headers": {}}', b'{"properties": 1}']

PUBLISH = """
import json, sys
from service.broker import make_celery
from service.config import get_settings
cases, bad_ids = json.loads(sys.stdin.read())
app = make_celery(get_settings())
with app.producer_or_acquire() as p:
    for headers, body in cases:
        p.publish(body, exchange="svrobs", routing_key="svrobs", serializer="json",
                  headers=headers, declare=[app.amqp.queues["svrobs"]])
    for args in bad_ids:
        app.send_task("svrobs.run_unit", args=args, producer=p)
"""

SMALL = {**SPEC, "N": [10], "estimators": ["ols"], "stages": ["estimate"]}


def _stack_kinds():
    skip = pytest.mark.skipif(
        not (PG_URL and REDIS_URL), reason="SVROBS_TEST_DATABASE_URL / _BROKER_URL not set"
    )
    return [pytest.param("embedded"), pytest.param("pg", marks=skip)]


def _publish(st: Stack, cases, bad_ids) -> None:
    subprocess.run(
        [sys.executable, "-c", PUBLISH],
        input=json.dumps([cases, bad_ids]).encode(),
        cwd=str(ROOT),
        env=st.env,
        check=True,
        capture_output=True,
        timeout=120,
    )


@pytest.mark.parametrize("kind", _stack_kinds())
def test_malformed_task_messages_are_dropped(kind, tmp_path, request):
    """Each malformed message is one ERROR line and is acknowledged (on the embedded
    broker kept in ``broker/bad``); the worker process that took them runs the job
    published after them, and a bad unit id is not retried."""
    st = Stack(kind, tmp_path)
    request.addfinalizer(st.teardown)
    st.setup()
    st.start_api_and_worker()
    worker = st.children["worker1"]

    if kind == "pg":
        import redis

        r = redis.Redis.from_url(st.redis_url)
        r.lpush("svrobs", *RAW_ITEMS)
    _publish(st, list(MALFORMED.values()), BAD_UNIT_IDS)
    with st.client() as c:
        job = submit(c, SMALL)
        for _ in range(240):
            assert worker.poll() is None, st.log_tail("worker1")
            if c.get(f"/jobs/{job['id']}").json()["status"] != "queued":
                break
            time.sleep(0.25)
        done = st.wait_job(c, job["id"], timeout=90)
    assert done["status"] == "succeeded", done
    st.wait_log("worker1", "not a unit id", count=len(BAD_UNIT_IDS), timeout=30)

    assert worker.poll() is None and st.children["worker1"] is worker, st.log_tail("worker1")
    log = (st.logs / "worker1.log").read_text()
    lines = log.splitlines()
    dropped = [ln for ln in lines if " ERROR " in ln and "task message" in ln and "dropped" in ln]
    assert len(dropped) == len(MALFORMED), "\n".join(dropped) + st.log_tail("worker1")
    for ident in ("m-int", "m-short", "m-tl", "m-eta", "m-retries", "m-stamped", "m-stamps"):
        assert any(f"'{ident}'" in ln for ln in dropped), (ident, dropped)
    bad_ids = [ln for ln in lines if "not a unit id" in ln]
    assert len(bad_ids) == len(BAD_UNIT_IDS), bad_ids
    for word in ("Unrecoverable", "Restoring", "Connection to broker lost", "retry"):
        assert word not in log, st.log_tail("worker1")
    if kind == "embedded":
        bad = list((st.root / "broker" / "bad").iterdir())
        assert len(bad) == len(MALFORMED), sorted(p.name for p in bad)
        kept = [json.loads(p.read_bytes()) for p in bad]
        assert sorted(str(m["headers"].get("task")) for m in kept) == sorted(
            str(h.get("task")) for h, _ in MALFORMED.values()
        )
        queue = st.root / "broker" / "queue"
        assert not [p for p in queue.iterdir() if p.name.endswith(".msg")]
    else:
        raw = [ln for ln in lines if " ERROR " in ln and "is not a message" in ln]
        assert len(raw) == len(RAW_ITEMS), "\n".join(raw) + st.log_tail("worker1")
        kept = r.lrange(REDIS_BAD_LIST, 0, -1)
        r.close()
        assert sorted(kept) == sorted(RAW_ITEMS)
