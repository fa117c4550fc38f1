"""The embedded broker's candidates, side by side: messages/s and a poisoned queue.

    .venv/bin/python bench/broker.py            # 2,000 messages per transport
    .venv/bin/python bench/broker.py --n 500

Three kombu transports in a fresh temporary folder each:

- ``filesystem``: kombu's own filesystem transport (``filesystem://``);
- ``service.file_broker``: the one the embedded stack runs (atomic write and
  claim, undecodable messages moved aside);
- ``sqlalchemy``: kombu's SQLAlchemy transport on an SQLite file
  (``sqla+sqlite:///...``), as it would run on the service's own database file:
  with the service's pragmas (WAL, synchronous=NORMAL, its busy timeout).

For each: the time to publish ``--n`` messages from one producer, then to consume
them all from a second process (one consumer, acknowledging each, as a
prefetch-1 worker does), and the poison check: a 0-byte message and a garbage
one placed first in the queue (files for the filesystem transports, rows for
SQLAlchemy), then one real message; it says whether the consumer got the real
one or raised (and what). For SQLAlchemy it also counts the rows left in the
table once every message was acknowledged. The figures go to docs/performance.md#embedded-broker.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from kombu import Connection, Exchange, Queue  # noqa: E402

from service.file_broker import TRANSPORT  # noqa: E402

QUEUE = "bench"
BODY = {"task": "svrobs.run_unit", "args": [12345], "kwargs": {}}


def _service_pragmas() -> None:
    """Every SQLite connection of this process gets the service's pragmas (WAL,
    synchronous=NORMAL, service.db.session), as on the service's own file."""
    from sqlalchemy import event
    from sqlalchemy.engine import Engine

    from service.db.session import SQLITE_BUSY_TIMEOUT_MS

    @event.listens_for(Engine, "connect")
    def _on_connect(dbapi_conn, _record):
        cur = dbapi_conn.cursor()
        cur.execute(f"PRAGMA busy_timeout = {SQLITE_BUSY_TIMEOUT_MS}")
        if cur.execute("PRAGMA journal_mode").fetchone()[0].lower() != "wal":
            cur.execute("PRAGMA journal_mode = WAL")
        cur.execute("PRAGMA synchronous = NORMAL")
        cur.close()


def _connection(kind: str, folder: Path) -> Connection:
    if kind == "sqlalchemy":
        _service_pragmas()
        return Connection(
            f"sqla+sqlite:///{folder / 'svrobs.db'}",
            transport_options={"connect_args": {"timeout": 30}},
        )
    opts = {
        "data_folder_in": str(folder / "queue"),
        "data_folder_out": str(folder / "queue"),
        "processed_folder": str(folder / "processed"),
        "control_folder": str(folder / "control"),
        "store_processed": False,
        "polling_interval": 0.1,
    }
    for key in ("queue", "processed", "control", "bad"):
        (folder / key).mkdir(parents=True, exist_ok=True)
    transport = TRANSPORT if kind == "service.file_broker" else None
    return Connection("filesystem://", transport=transport, transport_options=opts)


def _queue() -> Queue:
    return Queue(QUEUE, Exchange(QUEUE, type="direct"), routing_key=QUEUE)


def publish(kind: str, folder: Path, n: int) -> float:
    with _connection(kind, folder) as conn:
        producer = conn.Producer(serializer="json")
        producer.publish(BODY, exchange=_queue().exchange, routing_key=QUEUE, declare=[_queue()])
        t0 = time.perf_counter()
        for _ in range(n):
            producer.publish(BODY, exchange=_queue().exchange, routing_key=QUEUE)
        return time.perf_counter() - t0


def consume(kind: str, folder: Path, n: int, timeout: float = 120.0) -> dict:
    """Consume ``n`` messages; the error that stopped the consumer, if any."""
    got: list = []

    def on_message(body, message):
        got.append(body)
        message.ack()

    t0 = time.perf_counter()
    try:
        with _connection(kind, folder) as conn:
            with conn.Consumer(_queue(), callbacks=[on_message], prefetch_count=1):
                while len(got) < n and time.perf_counter() - t0 < timeout:
                    try:
                        conn.drain_events(timeout=1)
                    except TimeoutError:
                        pass
    except Exception as exc:  # noqa: BLE001 - what would stop a worker
        return {"received": len(got), "error": f"{type(exc).__name__}: {str(exc)[:120]}"}
    return {"received": len(got), "seconds": time.perf_counter() - t0, "error": None}


def poison(kind: str, folder: Path) -> None:
    """Put a 0-byte and a garbage message in front of the queue."""
    if kind == "sqlalchemy":
        import sqlalchemy as sa

        engine = sa.create_engine(f"sqlite:///{folder / 'svrobs.db'}")
        with engine.begin() as c:
            qid = c.execute(sa.text("SELECT id FROM kombu_queue WHERE name = :q"), {"q": QUEUE})
            qid = qid.scalar_one()
            for payload in ("", "garbage{"):
                c.execute(
                    sa.text(
                        "INSERT INTO kombu_message (visible, timestamp, payload, version, queue_id)"
                        " VALUES (1, NULL, :p, 1, :q)"
                    ),
                    {"p": payload, "q": qid},
                )
        engine.dispose()
        return
    (folder / "queue" / f"0000000000000_empty.{QUEUE}.msg").write_bytes(b"")
    (folder / "queue" / f"0000000000001_garbage.{QUEUE}.msg").write_bytes(b"\x00garbage{")


def _kept_rows(folder: Path) -> int:
    """Rows kombu's SQLAlchemy transport keeps after every message was acknowledged
    (it marks a delivered message invisible and never deletes it)."""
    import sqlite3

    with sqlite3.connect(folder / "svrobs.db") as c:
        return c.execute("SELECT count(*) FROM kombu_message").fetchone()[0]


def _child(args) -> None:
    folder = Path(args.folder)
    if args.child == "consume":
        print(json.dumps(consume(args.kind, folder, args.n)))
    elif args.child == "publish":
        print(json.dumps({"seconds": publish(args.kind, folder, args.n)}))
    elif args.child == "poison":
        poison(args.kind, folder)
        print(json.dumps({}))


def _in_child(step: str, kind: str, folder: Path, n: int) -> dict:
    """One step in a fresh process (kombu keeps declarations per process)."""
    out = subprocess.run(
        [sys.executable, __file__, "--child", step, "--kind", kind, "--folder", str(folder)]
        + ["--n", str(n)],
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    if out.returncode:
        return {"received": 0, "error": out.stderr.strip().splitlines()[-1][:160]}
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=2000)
    p.add_argument("--kinds", default="filesystem,service.file_broker,sqlalchemy")
    p.add_argument("--child", help=argparse.SUPPRESS)
    p.add_argument("--kind", help=argparse.SUPPRESS)
    p.add_argument("--folder", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        return _child(args)
    rows = []
    kinds = args.kinds.split(",")
    for kind in kinds:
        with tempfile.TemporaryDirectory(prefix="svrobs-broker-") as tmp:
            folder = Path(tmp)
            pub = _in_child("publish", kind, folder, args.n)["seconds"]
            con = _in_child("consume", kind, folder, args.n + 1)  # + the declare-time one
            kept = _kept_rows(folder) if kind == "sqlalchemy" else 0
            _in_child("poison", kind, folder, 0)
            _in_child("publish", kind, folder, 0)  # the real message, behind the poison
            poisoned = _in_child("consume", kind, folder, 1)
            row = {
                "transport": kind,
                "publish_per_s": args.n / pub,
                "consume_per_s": (args.n + 1) / con["seconds"] if con.get("seconds") else None,
                "consume_error": con["error"],
                "rows_left_after_consuming": kept,
                "poison": "real message received"
                if poisoned["received"] == 1 and not poisoned["error"]
                else f"consumer stopped: {poisoned['error']}",
            }
            rows.append(row)
            consumed = f"{row['consume_per_s']:7.0f}" if row["consume_per_s"] else "  error"
            print(
                f"{kind:22s} publish {row['publish_per_s']:7.0f} msg/s  consume {consumed} msg/s"
                f"  poison: {row['poison']}"
                + (f"  ({kept} rows left after consuming)" if kept else ""),
                flush=True,
            )
    print(json.dumps({"n": args.n, "cpus": os.cpu_count(), "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
