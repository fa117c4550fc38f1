"""Memory of a large dataset upload: how much the API process grows while it takes a
CSV of ``--mb`` MB (default 200) through ``POST /api/v1/datasets``.

    .venv/bin/python bench/dataset_upload.py               # 200 MB, port 8131
    .venv/bin/python bench/dataset_upload.py --mb 50 --port 8132

It writes a long-form CSV (rollouts of ``--steps`` steps, 4 states and 2 inputs,
numbers with 17 significant digits) in a temporary folder, starts ``uvicorn
service.app:app`` (one process, loopback, embedded SQLite) with
SVROBS_MAX_DATASET_MB above the file, uploads a small CSV once (so that lazy imports
are done), reads the process's resident memory (VmRSS), uploads the large file
(streamed by httpx) and reads VmHWM, the process's peak: the growth is their
difference (target < 300 MB for 200 MB). The arrays' own size (8 bytes a number)
is printed beside it: the parse holds the arrays, the text of one block of rows and
one 1 MiB chunk at a time.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import httpx  # noqa: E402
import numpy as np  # noqa: E402

from bench.api_server import start_server, stop_server, wait_ready  # noqa: E402
from bench.reads import rss_mb  # noqa: E402

N_STATES, N_INPUTS = 4, 2


def write_csv(path: Path, mb: float, steps: int, seed: int = 0) -> tuple[int, int]:
    """A long-form CSV of about ``mb`` MB -> (rollouts, numbers)."""
    rng = np.random.default_rng(seed)
    target = int(mb * 2**20)
    header = ",".join(["rollout", "k"] + [f"x{i + 1}" for i in range(N_STATES)])
    header += "," + ",".join(f"u{i + 1}" for i in range(N_INPUTS))
    rollouts = numbers = 0
    with path.open("w") as f:
        f.write(header + "\n")
        while f.tell() < target:
            x = rng.standard_normal((steps + 1, N_STATES))
            u = rng.standard_normal((steps + 1, N_INPUTS))
            k = np.arange(steps + 1)
            lines = [
                f"{rollouts},{kk},"
                + ",".join(repr(float(v)) for v in xr)
                + ","
                + (",".join(repr(float(v)) for v in ur) if kk < steps else ",")
                for kk, xr, ur in zip(k, x, u)
            ]
            f.write("\n".join(lines) + "\n")
            rollouts += 1
            numbers += (steps + 1) * N_STATES + steps * N_INPUTS
    return rollouts, numbers


def make_key(db_url: str) -> str:
    from service.db import accounts
    from service.db.migrate import upgrade
    from service.db.session import dispose_all, session_scope

    upgrade(db_url)
    with session_scope(db_url) as s:
        team = accounts.create_team(s, "bench-datasets")
        user = accounts.create_user(s, team.id, "bench@datasets.org")
        _, key = accounts.create_key(s, user.id, name="bench")
    dispose_all()
    return key


def upload(base: str, key: str, path: Path) -> tuple[int, float, dict]:
    t0 = time.perf_counter()
    with path.open("rb") as fh:
        r = httpx.post(
            f"{base}/api/v1/datasets",
            files={"file": (path.name, fh, "text/csv")},
            data={"name": path.stem},
            headers={"Authorization": f"Bearer {key}"},
            timeout=3600,
        )
    return r.status_code, time.perf_counter() - t0, r.json()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--mb", type=float, default=200.0)
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--port", type=int, default=8131)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="svrobs-dsbench-") as tmp_name:
        tmp = Path(tmp_name)
        big, small = tmp / "big.csv", tmp / "small.csv"
        t0 = time.perf_counter()
        rollouts, numbers = write_csv(big, args.mb, args.steps)
        write_csv(small, 0.01, 20)
        size = big.stat().st_size
        print(
            f"CSV: {size / 2**20:.1f} MB, {rollouts} rollouts of {args.steps} steps, "
            f"{numbers:,} numbers ({numbers * 8 / 2**20:.1f} MB as float64), "
            f"written in {time.perf_counter() - t0:.1f} s"
        )
        db_url = f"sqlite:///{tmp / 'svrobs.db'}"
        key = make_key(db_url)
        os.environ["SVROBS_MAX_DATASET_MB"] = str(int(size / 2**20) + 16)
        proc = start_server(tmp, db_url, args.port)
        base = f"http://127.0.0.1:{args.port}"
        try:
            wait_ready(base, proc)
            status, _, body = upload(base, key, small)
            assert status == 201, body
            before, _ = rss_mb(proc.pid)
            status, seconds, body = upload(base, key, big)
            after, peak = rss_mb(proc.pid)
        finally:
            stop_server(proc)
        if status != 201:
            raise SystemExit(f"upload failed: HTTP {status}: {body}")
        print(
            f"upload: {seconds:.1f} s, dataset {body['id']}: {body['rollouts']} rollouts, "
            f"n={body['n']}, m={body['m']}"
        )
        print(
            f"API process: VmRSS {before:.0f} MB before, VmHWM {peak:.0f} MB (peak), "
            f"VmRSS {after:.0f} MB after; growth {peak - before:.0f} MB "
            f"({(peak - before) / (size / 2**20):.2f} x the file; target < 300 MB)"
        )


if __name__ == "__main__":
    main()
