"""Stored rows as the JSON bodies the routes answer (shared by every route)."""

from __future__ import annotations

from service.db.models import Job


def job_out(job: Job) -> dict:
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
        "owner": job.user.email if job.user is not None else None,
        "schedule_id": job.schedule_id,
        "idempotency_key": job.idempotency_key,
        "spec": job.spec,
        "provenance": job.provenance or {},
        "error": job.error,
        "timings": job.timings or {},
        "created_at": job.created_at,
        "started_at": job.started_at,
        "finished_at": job.finished_at,
    }
