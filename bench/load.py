"""Load: 20 concurrent clients against a real API process for 60 s.

    .venv/bin/python bench/load.py                 # 20 clients, 60 s
    .venv/bin/python bench/load.py --seconds 10 --clients 5

It starts ``uvicorn service.app:app`` on a free loopback port (SQLite and
the filesystem broker in a temporary folder, no worker: submitted jobs stay
queued), stores one finished job of 10,000 result rows (synthetic records with
every record field, written through ``units.complete_unit`` as a worker would),
then runs the clients (httpx.AsyncClient, one connection each) in a closed loop
for ``--seconds``, mixing

* submit   POST /jobs                      (a small spec; 10 %)
* status   GET  /jobs/{id}                 (the big job or a submitted one; 45 %)
* results  GET  /jobs/{id}/results?limit=100 with a grid filter (45 %)

and prints p50 / p99 latency per kind and overall, requests per second and the
error rate (anything but 202 for a submit and 200 otherwise, or a transport
error). Targets: p99 under 100 ms for reads, no errors.

The per-key rate limit and the per-team queued-jobs cap are raised for the run
(SVROBS_RATE_LIMIT_PER_MINUTE, SVROBS_MAX_QUEUED_JOBS_PER_TEAM) so that it
measures latency, not throttling; the output says so. Bounded: at most
``--max-requests`` requests, a 10 s timeout per request, the server is stopped
at the end (also on Ctrl-C or an error), and everything binds to 127.0.0.1.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import random
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import httpx  # noqa: E402
import numpy as np  # noqa: E402

from bench.api_server import (  # noqa: E402
    API,
    HOST,
    QUEUED_CAP,
    RATE_LIMIT,
    cpu_seconds,
    free_port,
    start_server,
    stop_server,
    wait_ready,
)

MIX = (("submit", 0.10), ("status", 0.45), ("results", 0.45))
READS = ("status", "results")
P99_TARGET_MS = 100.0

# 2 systems x 2 sigma_w x 5 N x 100 reps x (ols + svr at 4 gammas) = 10,000 cells
BIG_SPEC = {
    "systems": ["paper-stable", "paper-unstable"],
    "sigma_w": [0.1, 1.0],
    "N": [50, 100, 150, 200, 250],
    "reps": 100,
    "gamma": [0.005, 0.01, 0.05, 0.1],
    "estimators": ["ols", "svr"],
    "stages": ["estimate", "bounds"],
    "seed": 1,
}
SUBMIT_SPEC = {
    "systems": ["paper-stable"],
    "sigma_w": [1.0],
    "N": [20, 40],
    "reps": 2,
    "gamma": [0.05],
    "estimators": ["ols", "svr"],
    "seed": 3,
    "tags": ["load"],
}


def synthetic_records(spec, unit: dict, rng: random.Random) -> list[dict]:
    """Records with every field a real unit writes (values are random, shapes real)."""
    from svrobs_core.records import NUMERIC_FIELDS, empty_record

    system = spec.systems[unit["system"]]
    n, m = np.asarray(system.A).shape[0], np.asarray(system.B).shape[1]
    out = []
    for N in unit["N"]:
        for rep in range(*unit["reps"]):
            for est in spec.estimators:
                for g in [None] if est == "ols" else list(spec.gamma):
                    r = empty_record()
                    r.update(
                        {
                            f: rng.random()
                            for f in NUMERIC_FIELDS
                            if f not in ("sigma_w", "N", "N0", "rep", "gamma")
                        }
                    )
                    r.update(
                        system=system.name,
                        sigma_w=spec.sigma_w[unit["sigma_w"]],
                        N=N,
                        N0=N - spec.T0 + 1,
                        estimator=est,
                        gamma=g,
                        rep=rep,
                        seed_key=[unit["system"], unit["sigma_w"], N, rep],
                        A_hat=[[rng.random() for _ in range(n)] for _ in range(n)],
                        B_hat=[[rng.random() for _ in range(m)] for _ in range(n)],
                        thm1_holds_A=rng.random() > 0.3,
                        thm1_holds_B=rng.random() > 0.3,
                        stable_certified=rng.random() > 0.5,
                        notes=None,
                    )
                    out.append(r)
    return out


def prepare(
    db_url: str,
    spec_dict: dict | None = None,
    *,
    team_name: str = "load",
    max_cells: int | None = None,
) -> tuple[str, int, int]:
    """Migrate, create a team and key, store the big job (default ``BIG_SPEC``)
    through ``complete_unit`` -> (key, job id, rows)."""
    from sqlalchemy import func, select

    from service.db import accounts
    from service.db.jobs import create_job, unit_ids_of_job
    from service.db.migrate import upgrade
    from service.db.models import Result
    from service.db.session import dispose_all, session_scope
    from service.db.units import complete_unit, start_unit
    from svrobs_core.parsing import parse_spec

    upgrade(db_url)
    rng = random.Random(0)
    spec_dict = spec_dict or BIG_SPEC
    with session_scope(db_url) as s:
        team = accounts.create_team(s, team_name)
        user = accounts.create_user(s, team.id, f"{team_name}@lab.org")
        _, key = accounts.create_key(s, user.id, name="bench")
        job, _ = create_job(
            s,
            team_id=team.id,
            user_id=user.id,
            spec=spec_dict,
            name=f"{team_name}-big",
            tags=(team_name,),
            max_active_jobs=0,
            max_cells=max_cells,
        )
        job_id = job.id
    spec = parse_spec(spec_dict)
    with session_scope(db_url) as s:
        unit_ids = unit_ids_of_job(s, job_id, pending_only=False)
    for uid in unit_ids:
        with session_scope(db_url) as s:
            claimed = start_unit(s, uid, "bench", 600, max_attempts=0)
            complete_unit(s, uid, synthetic_records(spec, claimed[1], rng))
    with session_scope(db_url) as s:
        rows = s.scalar(select(func.count()).select_from(Result).where(Result.job_id == job_id))
    dispose_all()
    return key, job_id, rows


class Stats:
    """Latencies per kind; requests sent before ``warmup`` seconds only go to ``cold``
    (the first requests of a fresh process compile SQL, fill the connection pools)."""

    def __init__(self, start: float = 0.0, warmup: float = 0.0):
        self.start, self.warmup = start, warmup
        self.lat: dict[str, list[float]] = {k: [] for k, _ in MIX}
        self.cold: list[float] = []
        self.errors: dict[str, int] = {k: 0 for k, _ in MIX}
        self.error_samples: list[str] = []
        self.requests = 0

    def add(
        self, kind: str, seconds: float, ok: bool, why: str = "", sent: float | None = None
    ) -> None:
        if sent is not None and sent - self.start < self.warmup:
            self.cold.append(seconds)
            if ok:
                return
        self.requests += 1
        self.lat[kind].append(seconds)
        if not ok:
            self.errors[kind] += 1
            if len(self.error_samples) < 5:
                self.error_samples.append(f"{kind}: {why}")


async def client_loop(
    i: int,
    base: str,
    key: str,
    big_id: int,
    deadline: float,
    budget: list[int],
    stats: Stats,
    submitted: list[int],
    think: float,
    mix=MIX,
) -> None:
    rng = random.Random(i)
    headers = {"Authorization": f"Bearer {key}"}
    kinds, weights = zip(*mix)
    spec = BIG_SPEC
    async with httpx.AsyncClient(
        base_url=base, headers=headers, timeout=10.0, limits=httpx.Limits(max_connections=1)
    ) as client:
        while time.monotonic() < deadline and budget[0] > 0:
            budget[0] -= 1
            kind = rng.choices(kinds, weights)[0]
            if kind == "submit":
                method, url, params, body, want = "POST", f"{API}/jobs", None, SUBMIT_SPEC, 202
            elif kind == "status":
                jid = rng.choice(submitted) if submitted and rng.random() < 0.5 else big_id
                method, url, params, body, want = "GET", f"{API}/jobs/{jid}", None, None, 200
            else:
                params = rng.choice(
                    [
                        {"estimator": "svr", "gamma": rng.choice(spec["gamma"])},
                        {"N": rng.choice(spec["N"]), "system": rng.choice(spec["systems"])},
                        {"sigma_w": rng.choice(spec["sigma_w"]), "estimator": "ols"},
                        {"rep": rng.randrange(spec["reps"])},
                    ]
                )
                params = {**params, "limit": 100, "offset": rng.choice([0, 0, 100, 500])}
                method, url, body, want = "GET", f"{API}/jobs/{big_id}/results", None, 200
            t0, sent = time.perf_counter(), time.monotonic()
            try:
                r = await client.request(method, url, params=params, json=body)
                dt = time.perf_counter() - t0
                ok = r.status_code == want
                stats.add(kind, dt, ok, f"HTTP {r.status_code} {r.text[:200]}", sent)
                if ok and kind == "submit":
                    submitted.append(r.json()["id"])
            except httpx.HTTPError as exc:
                stats.add(
                    kind, time.perf_counter() - t0, False, f"{type(exc).__name__}: {exc}", sent
                )
            if think:
                await asyncio.sleep(rng.uniform(0.5, 1.5) * think)


async def run_load(
    base: str,
    key: str,
    big_id: int,
    clients: int,
    seconds: float,
    max_requests: int,
    think: float = 0.0,
    mix=MIX,
    warmup: float = 0.0,
) -> tuple[Stats, float]:
    start = time.monotonic()
    stats, submitted, budget = Stats(start, warmup), [], [max_requests]
    deadline = start + warmup + seconds
    await asyncio.gather(
        *(
            client_loop(i, base, key, big_id, deadline, budget, stats, submitted, think, mix)
            for i in range(clients)
        )
    )
    return stats, time.monotonic() - start - warmup


def report(stats: Stats, elapsed: float, clients: int, rows: int) -> bool:
    def pct(xs, q):
        return float(np.percentile(np.asarray(xs) * 1000.0, q)) if xs else float("nan")

    print(
        f"\n{clients} clients, {elapsed:.1f} s, {stats.requests} requests, "
        f"{stats.requests / elapsed:.1f} requests/s; results job: {rows} rows"
    )
    print(
        f"(rate limit raised to {RATE_LIMIT}/min and the queued-jobs cap to {QUEUED_CAP} "
        "for this run: it measures latency, not throttling)"
    )
    if stats.warmup:
        print(
            f"warm-up: the first {stats.warmup:g} s ({len(stats.cold)} requests, p99 "
            f"{pct(stats.cold, 99):.1f} ms, max {pct(stats.cold, 100):.1f} ms) not counted below"
        )
    print(f"{'kind':<10}{'count':>8}{'p50 ms':>10}{'p99 ms':>10}{'max ms':>10}{'errors':>8}")
    everything = []
    for kind, _ in MIX:
        xs = stats.lat[kind]
        everything += xs
        print(
            f"{kind:<10}{len(xs):>8}{pct(xs, 50):>10.1f}{pct(xs, 99):>10.1f}"
            f"{(max(xs) * 1000 if xs else float('nan')):>10.1f}{stats.errors[kind]:>8}"
        )
    reads = [x for k in READS for x in stats.lat[k]]
    n_err = sum(stats.errors.values())
    print(
        f"{'reads':<10}{len(reads):>8}{pct(reads, 50):>10.1f}{pct(reads, 99):>10.1f}"
        f"{(max(reads) * 1000 if reads else float('nan')):>10.1f}"
        f"{sum(stats.errors[k] for k in READS):>8}"
    )
    print(
        f"{'overall':<10}{len(everything):>8}{pct(everything, 50):>10.1f}"
        f"{pct(everything, 99):>10.1f}"
        f"{(max(everything) * 1000 if everything else float('nan')):>10.1f}{n_err:>8}"
    )
    rate = n_err / stats.requests if stats.requests else 0.0
    print(f"error rate: {rate:.4%}")
    for s in stats.error_samples:
        print(f"  e.g. {s}")
    ok = pct(reads, 99) < P99_TARGET_MS and n_err == 0
    print(f"targets (reads p99 < {P99_TARGET_MS:.0f} ms, no errors): {'met' if ok else 'NOT met'}")
    return ok


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--clients", type=int, default=20)
    ap.add_argument(
        "--max-requests",
        type=int,
        default=500_000,
        help="stop after this many requests even before --seconds",
    )
    ap.add_argument(
        "--api-workers",
        type=int,
        default=1,
        help="uvicorn worker processes (default 1, as `svrobs serve`)",
    )
    ap.add_argument(
        "--think-ms",
        type=float,
        default=0.0,
        help="mean pause between a client's requests (default 0: closed loop, "
        "each client sends its next request as soon as it has an answer)",
    )
    ap.add_argument(
        "--mix",
        default=",".join(f"{k}={w:g}" for k, w in MIX),
        help="request weights, e.g. status=1 or submit=0.1,status=0.45,results=0.45",
    )
    ap.add_argument(
        "--warmup-s",
        type=float,
        default=5.0,
        help="seconds of load before measuring (reported apart: a fresh API "
        "process compiles SQL and opens its pools on the first requests)",
    )
    ap.add_argument("--keep", action="store_true", help="keep the temporary folder")
    args = ap.parse_args(argv)
    try:
        mix = tuple((k, float(w)) for k, w in (item.split("=") for item in args.mix.split(",")))
    except ValueError:
        ap.error("--mix: comma-separated kind=weight pairs")
    if not mix or any(k not in dict(MIX) or w < 0 for k, w in mix) or not sum(w for _, w in mix):
        ap.error(f"--mix: kinds among {[k for k, _ in MIX]}, weights >= 0, not all 0")
    if not (
        0 < args.seconds <= 3600
        and 0 < args.clients <= 200
        and 0 < args.api_workers <= 16
        and 0 <= args.think_ms <= 60_000
        and 0 <= args.warmup_s <= 600
    ):
        ap.error(
            "--seconds in (0, 3600], --clients in (0, 200], --api-workers in (0, 16], "
            "--think-ms in [0, 60000]"
        )

    tmp = Path(tempfile.mkdtemp(prefix="svrobs-load-"))
    db_url = f"sqlite:///{tmp / 'svrobs.db'}"
    proc = None
    try:
        t0 = time.monotonic()
        key, big_id, rows = prepare(db_url)
        print(
            f"prepared job {big_id} with {rows} result rows in {time.monotonic() - t0:.1f} s "
            f"({db_url})"
        )
        port = free_port()
        base = f"http://{HOST}:{port}"
        proc = start_server(tmp, db_url, port, args.api_workers)
        wait_ready(base, proc)
        load1 = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
        print(
            f"API (uvicorn, {args.api_workers} process(es)) on {base}; {args.clients} clients "
            f"for {args.seconds:g} s, think time {args.think_ms:g} ms; machine: "
            f"{os.cpu_count()} CPUs, load average {load1:.2f} before the run ...",
            flush=True,
        )
        cpu0, own0 = cpu_seconds(proc.pid), time.process_time()
        stats, elapsed = asyncio.run(
            run_load(
                base,
                key,
                big_id,
                args.clients,
                args.seconds,
                args.max_requests,
                args.think_ms / 1000.0,
                mix,
                args.warmup_s,
            )
        )
        cpu1, own1 = cpu_seconds(proc.pid), time.process_time()
        if proc.poll() is not None:
            print(f"the API process died (code {proc.returncode}); see {tmp / 'api.log'}")
            return 1
        ok = report(stats, elapsed, args.clients, rows)
        if cpu0 is not None and cpu1 is not None and stats.requests:
            api = cpu1 - cpu0
            n_all = stats.requests + len(stats.cold)
            seconds_all = elapsed + args.warmup_s
            print(
                f"CPU: API {api:.1f} s ({api / seconds_all:.0%} of one core, "
                f"{api / n_all * 1000:.1f} ms per request); load clients "
                f"{own1 - own0:.1f} s; load average after {os.getloadavg()[0]:.2f}"
            )
        return 0 if ok else 1
    finally:
        if proc is not None:
            stop_server(proc)
        if args.keep:
            print(f"kept {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
