"""/healthz (the process is up) and /readyz (the DB and the broker answer, and a worker
runs when the API knows where its workers are: SVROBS_WORKER_PID_DIR)."""

from __future__ import annotations

import concurrent.futures
from collections.abc import Callable

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from service.db.clock import ping
from service.http.deps import BrokerCheckDep, SessionFactoryDep, SettingsDep
from service.worker_pids import check_workers
from svrobs_lab.dispatch import SessionFactory

router = APIRouter(tags=["health"])
_pool = concurrent.futures.ThreadPoolExecutor(max_workers=4, thread_name_prefix="readyz")


@router.get("/healthz")
def healthz() -> dict:
    return {"status": "ok"}


def _check_db(session_factory: SessionFactory) -> None:
    session = session_factory(False)
    try:
        ping(session)
    finally:
        session.close()


@router.get(
    "/readyz", responses={503: {"description": "DB or broker unreachable, or no worker running"}}
)
def readyz(session_factory: SessionFactoryDep, broker_check: BrokerCheckDep, settings: SettingsDep):
    timeout = settings.BROKER_TIMEOUT + 3
    checks: dict[str, str] = {}
    todo: list[tuple[str, Callable[..., object], tuple[object, ...]]] = [
        ("database", _check_db, (session_factory,)),
        ("broker", broker_check, ()),
    ]
    if settings.WORKER_PID_DIR:
        todo.append(("worker", check_workers, (settings.WORKER_PID_DIR,)))
    for name, fn, args in todo:
        try:
            _pool.submit(fn, *args).result(timeout=timeout)
            checks[name] = "ok"
        except concurrent.futures.TimeoutError:
            checks[name] = "timeout"
        except Exception as exc:  # noqa: BLE001 - report, never raise
            checks[name] = f"error: {type(exc).__name__}: {str(exc).splitlines()[0][:200]}"
    ok = all(v == "ok" for v in checks.values())
    body: dict[str, str | dict[str, str] | None] = {
        "status": "ready" if ok else "not ready",
        "checks": checks,
    }
    if not ok:
        body["detail"] = "; ".join(f"{k} {v}" for k, v in checks.items() if v != "ok")
        body["field"] = None
    return JSONResponse(body, status_code=200 if ok else 503)
