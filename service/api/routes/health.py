"""/healthz (the process is up) and /readyz (the DB and the broker answer)."""

from __future__ import annotations

import concurrent.futures

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse
from sqlalchemy import text

router = APIRouter(tags=["health"])
_pool = concurrent.futures.ThreadPoolExecutor(max_workers=4, thread_name_prefix="readyz")


@router.get("/healthz")
def healthz() -> dict:
    return {"status": "ok"}


def _check_db(request: Request) -> None:
    session = request.app.state.session_factory(False)
    try:
        session.execute(text("SELECT 1"))
    finally:
        session.close()


def _check_broker(request: Request) -> None:
    check = getattr(request.app.state, "broker_check", None)
    if check is not None:
        check()
        return
    from service.broker import check_broker

    get_celery = getattr(request.app.state.publisher, "get_celery", None)
    if get_celery is None:  # a test publisher without a broker
        return
    check_broker(get_celery(), timeout=request.app.state.settings.BROKER_TIMEOUT)


@router.get("/readyz", responses={503: {"description": "DB or broker unreachable"}})
def readyz(request: Request):
    timeout = request.app.state.settings.BROKER_TIMEOUT + 3
    checks: dict[str, str] = {}
    for name, fn in (("database", _check_db), ("broker", _check_broker)):
        try:
            _pool.submit(fn, request).result(timeout=timeout)
            checks[name] = "ok"
        except concurrent.futures.TimeoutError:
            checks[name] = "timeout"
        except Exception as exc:  # noqa: BLE001 - report, never raise
            checks[name] = f"error: {type(exc).__name__}: {str(exc).splitlines()[0][:200]}"
    ok = all(v == "ok" for v in checks.values())
    body = {"status": "ready" if ok else "not ready", "checks": checks}
    if not ok:
        body["detail"] = "; ".join(f"{k} {v}" for k, v in checks.items() if v != "ok")
        body["field"] = None
    return JSONResponse(body, status_code=200 if ok else 503)
