"""Stored rows as the JSON bodies the routes answer (shared by every route)."""

from __future__ import annotations

from service.db.jobs import spec_summary
from service.db.models import Job


def job_item(job: Job) -> dict:
    """A job as ``GET /jobs`` lists it: ``spec_summary`` instead of the spec."""
    out = job_out(job, spec=False)
    out["spec_summary"] = job.spec_summary or spec_summary(job.spec, job.n_cells)
    return out


def job_out(job: Job, *, spec: bool = True) -> dict:
    total = job.progress_total or 0
    done = job.progress_done or 0
    return {
        "id": job.id,
        "name": job.name,
        "tags": list(job.tags or []),
        "status": job.status,
        "progress": {
            "done": done,
            "total": total,
            "fraction": (done / total) if total else (1.0 if job.status == "succeeded" else 0.0),
        },
        "n_cells": job.n_cells,
        "cells_done": job.cells_done or 0,
        "owner": job.user.email if job.user is not None else None,
        "schedule_id": job.schedule_id,
        "idempotency_key": job.idempotency_key,
        **({"spec": job.spec} if spec else {}),
        "provenance": job.provenance or {},
        "error": job.error,
        "timings": job.timings or {},
        "created_at": job.created_at,
        "started_at": job.started_at,
        "finished_at": job.finished_at,
        "pruned_at": job.pruned_at,
    }
