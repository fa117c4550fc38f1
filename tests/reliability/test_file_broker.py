"""The embedded broker (service.file_broker) as the service configures it
(service.broker.make_celery), in real processes: every message published while
consumers race for them arrives exactly once; files that are not messages are
moved to ``bad/`` and the consumer goes on to the next message; an unreadable
exchange table is rewritten when a queue is bound."""

from __future__ import annotations

import base64
import json
import os
import subprocess
import sys
from pathlib import Path

from service.broker import make_celery
from service.config import Settings

ROOT = Path(__file__).resolve().parents[2]

# a child process: publish ids first:last, or consume until the queue is empty once a
# file "stop" exists (at most arg seconds), through the configured transport
SCRIPT = r"""
import json, os, sys, time
from kombu import Exchange, Queue
from service.broker import make_celery
from service.config import Settings

mode, folder, arg = sys.argv[1], sys.argv[2], sys.argv[3]
app = make_celery(Settings(BROKER_URL="filesystem://", BROKER_DIR=folder, BROKER_POLL_SECONDS=0.01))
queue = Queue("t", Exchange("t", type="direct"), routing_key="t")
with app.connection_for_write() as conn:
    if mode == "publish":
        queue(conn.default_channel).declare()
        producer = conn.Producer(serializer="json")
        first, last = map(int, arg.split(":"))
        for i in range(first, last):
            producer.publish({"id": i}, exchange=queue.exchange, routing_key="t", declare=[queue])
    else:
        got = []
        def on_message(body, message):
            got.append(body["id"])
            message.ack()
        # until the queue is empty once the test says publishing is over (a file "stop")
        deadline = time.monotonic() + float(arg)
        with conn.Consumer(queue, callbacks=[on_message], prefetch_count=1):
            while time.monotonic() < deadline:
                try:
                    conn.drain_events(timeout=0.5)
                except TimeoutError:
                    if os.path.exists(os.path.join(folder, "stop")):
                        break
        print(json.dumps(got))
"""


def _run(*args: str, wait: bool = True):
    proc = subprocess.Popen(
        [sys.executable, "-c", SCRIPT, *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    return proc.communicate(timeout=120) + (proc.returncode,) if wait else proc


def _folders(tmp_path: Path) -> dict[str, Path]:
    opts = make_celery(
        Settings(BROKER_URL="filesystem://", BROKER_DIR=str(tmp_path))
    ).conf.broker_transport_options
    return {k: Path(v) for k, v in opts.items() if k.endswith("folder") or k.startswith("data_")}


def test_racing_publishers_and_consumers_get_every_message_once(tmp_path):
    _folders(tmp_path)  # make_celery creates the folders
    consumers = [_run("consume", str(tmp_path), "25", wait=False) for _ in range(2)]
    publishers = [
        _run("publish", str(tmp_path), f"{k * 300}:{(k + 1) * 300}", wait=False) for k in range(2)
    ]
    for p in publishers:
        _out, err = p.communicate(timeout=120)
        assert p.returncode == 0, err[-2000:]
    (tmp_path / "stop").touch()
    got = []
    for c in consumers:
        out, err = c.communicate(timeout=120)
        assert c.returncode == 0, err[-2000:]  # no consumer stopped on a half-written file
        got += json.loads(out)
    assert sorted(got) == list(range(600))  # each exactly once
    folders = _folders(tmp_path)
    assert not list(folders["bad_folder"].iterdir())
    leftovers = [p.name for p in folders["data_folder_in"].iterdir()]
    assert leftovers == [], leftovers  # no temporary file left behind


def _envelope(body: bytes, **props) -> dict:
    return {
        "body": base64.b64encode(body).decode(),
        "content-type": "application/json",
        "content-encoding": "utf-8",
        "headers": {},
        "properties": {"body_encoding": "base64", "delivery_info": {}, **props},
    }


def test_files_that_are_not_messages_are_set_aside(tmp_path):
    folders = _folders(tmp_path)
    queue = folders["data_folder_in"]
    _out, err, rc = _run("publish", str(tmp_path), "0:0")  # declares the queue only
    assert rc == 0, err
    poison = {
        "empty": b"",
        "garbage": os.urandom(64).replace(b"{", b"x"),
        "truncated": b'{"body": "eyJp',
        "not-an-object": b"[1, 2]",
        "no-properties": b"{}",
        "no-delivery-tag": json.dumps(_envelope(b'{"id": -1}')).encode(),
        "unknown-encoding": json.dumps(
            _envelope(b'{"id": -2}', delivery_tag="x", body_encoding="rot13")
        ).encode(),
    }
    for i, (name, data) in enumerate(poison.items()):
        (queue / f"{i:013d}_{name}.t.msg").write_bytes(data)
    (queue / "0000000000000_other-queue.u.msg").write_bytes(b"")  # not this queue's
    _out, err, rc = _run("publish", str(tmp_path), "7:8")  # the real one, behind them all
    assert rc == 0, err

    (tmp_path / "stop").touch()
    out, err, rc = _run("consume", str(tmp_path), "30")
    assert rc == 0, err[-3000:]
    assert json.loads(out) == [7]
    bad = sorted(p.name.split("_", 1)[1].split(".")[0] for p in folders["bad_folder"].iterdir())
    assert bad == sorted(poison)
    for name in poison:
        assert f"_{name}.t.msg" in err and "is not a message" in err, err[-3000:]
    assert [p.name for p in queue.iterdir()] == ["0000000000000_other-queue.u.msg"]


def test_an_unreadable_exchange_table_is_rewritten_on_bind(tmp_path):
    folders = _folders(tmp_path)
    (folders["control_folder"] / "t.exchange").write_bytes(b"")  # a torn write
    out, err, rc = _run("publish", str(tmp_path), "0:3")
    assert rc == 0, err[-3000:]
    assert "unreadable" in err
    table = json.loads((folders["control_folder"] / "t.exchange").read_text())
    assert table == [["t", "", "t"]]
    (tmp_path / "stop").touch()
    out, err, rc = _run("consume", str(tmp_path), "30")
    assert rc == 0, err[-3000:]
    assert sorted(json.loads(out)) == [0, 1, 2]
