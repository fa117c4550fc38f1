"""/healthz, /readyz and 503 (never a 500 or a traceback) when the DB is down."""

from __future__ import annotations

from fastapi.testclient import TestClient

from service.app import create_app
from service.http.deps import get_broker_check
from tests.service.svc_helpers import make_settings, no_broker_check

BAD_DB = "postgresql+psycopg://postgres@127.0.0.1:1/nowhere"


def test_healthz_readyz(client):
    assert client.get("/healthz").json() == {"status": "ok"}
    r = client.get("/readyz")
    assert r.status_code == 200 and r.json()["checks"] == {"database": "ok", "broker": "ok"}


def test_readyz_503_when_db_unreachable():
    app = create_app(make_settings(BAD_DB))
    app.dependency_overrides[get_broker_check] = lambda: no_broker_check
    client = TestClient(app, raise_server_exceptions=False)
    r = client.get("/readyz")
    assert r.status_code == 503
    body = r.json()
    assert body["checks"]["database"].startswith("error") and body["checks"]["broker"] == "ok"
    assert "database" in body["detail"]


def test_readyz_503_when_broker_unreachable(db_url):
    app = create_app(make_settings(db_url, BROKER_URL="redis://127.0.0.1:1/0", BROKER_TIMEOUT=0.5))
    r = TestClient(app, raise_server_exceptions=False).get("/readyz")
    assert r.status_code == 503 and r.json()["checks"]["broker"] != "ok"


def test_routes_answer_503_json_when_db_down():
    app = create_app(make_settings(BAD_DB))
    client = TestClient(app, raise_server_exceptions=False)
    for method, url in [
        ("get", "/api/v1/jobs"),
        ("get", "/api/v1/jobs/1"),
        ("post", "/api/v1/jobs/1/cancel"),
    ]:
        r = getattr(client, method)(url, headers={"Authorization": "Bearer svr_abcdefgh_x"})
        assert r.status_code == 503, (url, r.text)
        assert r.json()["detail"] and "Traceback" not in r.text
    r = client.post(
        "/api/v1/jobs",
        json={"systems": ["paper-stable"], "sigma_w": [1], "N": [20]},
        headers={"Authorization": "Bearer svr_abcdefgh_x"},
    )
    assert r.status_code == 503


def test_openapi_docs(client):
    assert client.get("/docs").status_code == 200
    spec = client.get("/openapi.json").json()
    assert "/api/v1/jobs" in spec["paths"] and "/api/v1/compare" in spec["paths"]
