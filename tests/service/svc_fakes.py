"""Deterministic stand-in records for a work unit (the service tests must not depend
on how far the core science is)."""

from __future__ import annotations

import random

from svrobs_core.parsing import parse_spec
from svrobs_core.records import empty_record


def fake_records(spec_dict: dict, unit: dict) -> list[dict]:
    spec = parse_spec(spec_dict)
    out = []
    for N in unit["N"]:
        for rep in range(*unit["reps"]):
            for est in spec.estimators:
                for g in [None] if est == "ols" else list(spec.gamma):
                    rnd = random.Random(str((unit["system"], unit["sigma_w"], N, rep, est, g)))
                    r = empty_record()
                    r.update(
                        system=spec.systems[unit["system"]].name,
                        sigma_w=spec.sigma_w[unit["sigma_w"]],
                        N=N,
                        N0=N - spec.T0 + 1,
                        estimator=est,
                        gamma=g,
                        rep=rep,
                        seed_key=[unit["system"], unit["sigma_w"], N, rep],
                        A_hat=[[rnd.random() for _ in range(3)] for _ in range(3)],
                        B_hat=[[rnd.random()] for _ in range(3)],
                        rmse_A=rnd.random() / N,
                        rmse_B=float("nan"),
                        H_A=1.0 + rnd.random(),
                        thm1_holds_A=rnd.random() > 0.3,
                        stable_certified=None,
                        notes="fake" if est == "ols" else None,
                    )
                    out.append(r)
    return out


def run_job_units(session, job_id: int, worker: str = "w1", *, count: int | None = None) -> int:
    """Start and complete every unit of a job (its first ``count``) with fake records;
    returns records written."""
    from service.db import jobs, units

    n = 0
    for uid in jobs.unit_ids_of_job(session, job_id, pending_only=False)[:count]:
        claimed = units.start_unit(session, uid, worker, 60, max_attempts=0)
        if claimed is None:
            continue
        spec, payload = claimed
        recs = fake_records(spec, payload)
        units.complete_unit(session, uid, recs)
        session.commit()
        n += len(recs)
    return n


def stored_job(client, session, acc, spec: dict) -> int:
    """The id of a job of ``acc``'s team submitted through the API, every unit of which
    is completed with fake records."""
    r = client.post("/api/v1/jobs", json=spec, headers=acc.headers)
    assert r.status_code == 202, r.text
    run_job_units(session, r.json()["id"])
    return r.json()["id"]
