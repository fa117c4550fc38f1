"""The image deploys: every service of docker-compose.yml starts from what the
Dockerfile builds, and a job submitted to its api succeeds (docs/deploy.md#the-image-test).

There is no Docker engine here, so the test builds what the Dockerfile would: exactly
the files its COPY lines take from the build context (.dockerignore applied), the RUN
pip line run for real into a fresh virtual environment that sees only pyproject's
runtime dependencies (:mod:`tests.deploy.python_env`). It then runs migrate, api,
worker and beat with their compose commands and environments, mapped onto this
machine's PostgreSQL (a private database) and Redis, as USER would run them
(:mod:`tests.deploy.compose`): the image's files read-only, the state folder and the
volumes writable. One knob is added: beat ticks every second instead of every minute.
"""

from __future__ import annotations

import os
import re
import secrets
import shlex
import shutil
import tempfile
import time
import tomllib
from pathlib import Path

import httpx
import pytest
import redis
import sqlalchemy as sa
from sqlalchemy.engine import make_url

from svrobs_core import parse_spec
from tests.deploy import compose, dockerfile
from tests.integration.stack import (
    PG_URL,
    REDIS_URL,
    cell_key,
    fetch_jsonl,
    in_process_records,
    same,
)
from tests.integration.test_stack import TINY_SPEC as SPEC

ROOT = Path(__file__).resolve().parents[2]
COMMIT = "0123456789abcdef0123456789abcdef01234567"  # docker compose build's SVROBS_GIT_COMMIT
ADMIN_LINE = re.compile(r"^docker compose run --rm (\S+) (svrobs admin [^#\n]*?)\s*(?:#.*)?$", re.M)

pytestmark = [
    pytest.mark.integration,
    pytest.mark.timeout(300),
    pytest.mark.skipif(
        not (PG_URL and REDIS_URL), reason="needs SVROBS_TEST_DATABASE_URL/BROKER_URL"
    ),
]


def _flush(url: str) -> None:
    r = redis.Redis.from_url(url)
    r.flushdb()
    r.close()


@pytest.fixture(scope="module")
def deployment():
    doc = compose.load(ROOT / "docker-compose.yml", {"SVROBS_GIT_COMMIT": COMMIT})
    ours = [s for s in doc["services"].values() if "build" in s]
    build_args = {k: str(v) for k, v in (ours[0]["build"].get("args") or {}).items()}
    image = dockerfile.parse(ROOT / "Dockerfile", ROOT, build_args)
    if dockerfile.python_version(image.base) != dockerfile.this_python():
        pytest.skip(f"the image runs {image.base}, this test Python {dockerfile.this_python()}")
    if os.geteuid() == 0 and not shutil.which("setpriv"):
        pytest.skip("running the services as a user without root's rights needs setpriv")
    folder = Path(tempfile.mkdtemp(prefix="svrobs-image-"))
    folder.chmod(0o755)  # the services (another user's rights) reach their files
    db = f"svrobs_image_{os.getpid()}_{secrets.token_hex(3)}"
    admin = sa.create_engine(PG_URL, isolation_level="AUTOCOMMIT")
    with admin.connect() as c:
        c.exec_driver_sql(f'CREATE DATABASE "{db}"')
    pg = make_url(PG_URL).set(database=db).render_as_string(hide_password=False)
    servers = {}
    for name, service in doc["services"].items():
        kind = str(service.get("image", "")).split(":")[0]
        if kind in ("postgres", "redis"):
            servers[name] = pg if kind == "postgres" else REDIS_URL
    deployment = None
    try:
        _flush(REDIS_URL)
        built = dockerfile.build(image, ROOT, folder)
        deployment = compose.Deployment(
            built, doc, folder, servers, extra_env={"beat": {"SVROBS_TICK_SECONDS": "1"}}
        )
        deployment.up(["api", "worker", "beat"])
        deployment.wait_healthy("api")
        deployment.wait_log("worker", "ready.")
        deployment.wait_log("beat", "beat: Starting")
        yield deployment
    finally:
        if deployment is not None:
            deployment.down()
            deployment.unseal()
        shutil.rmtree(folder, ignore_errors=True)
        with admin.connect() as c:
            c.exec_driver_sql(f'DROP DATABASE IF EXISTS "{db}" WITH (FORCE)')
        admin.dispose()
        _flush(REDIS_URL)


def _api(deployment) -> str:
    return f"http://127.0.0.1:{deployment.ports[8000]}"


@pytest.fixture(scope="module")
def job(deployment):
    """A team, user and key made with docs/deploy.md's admin commands, and a job
    submitted with that key to the api, finished."""
    lines = ADMIN_LINE.findall((ROOT / "docs" / "deploy.md").read_text())
    assert [cmd.split()[2] for _, cmd in lines] == ["create-team", "create-user", "create-key"]
    for service, cmd in lines:
        proc = deployment.run(service, shlex.split(cmd))
        assert proc.returncode == 0, f"{cmd}:\n{proc.stderr[-3000:]}"
    key = proc.stdout.strip().splitlines()[-1]
    client = httpx.Client(
        base_url=_api(deployment) + "/api/v1",
        headers={"Authorization": f"Bearer {key}"},
        timeout=30,
    )
    r = client.post("/jobs", json=SPEC)
    assert r.status_code == 202, r.text
    job_id = r.json()["id"]
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        job = client.get(f"/jobs/{job_id}").json()
        if job["status"] in ("succeeded", "failed", "cancelled"):
            break
        time.sleep(0.25)
    yield client, job
    client.close()


def test_the_job_succeeds_with_the_records_of_the_core(deployment, job):
    client, done = job
    assert done["status"] == "succeeded", f"{done}\n{deployment.tail()}"
    records = fetch_jsonl(client, done["id"])
    assert len(records) == parse_spec(SPEC).n_cells
    expected = in_process_records(SPEC)
    for r in records:
        assert same(r, expected[cell_key(r)]) == [], cell_key(r)
    version = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    assert done["provenance"]["git_commit"] == COMMIT
    assert done["provenance"]["version"] == version


def test_beat_stores_the_report_of_the_finished_job(deployment, job):
    client, done = job
    deployment.wait_log("beat", f"tick: stored the reports of jobs [{done['id']}]", timeout=90)
    r = client.get(f"/jobs/{done['id']}/report")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")


def test_migrate_printed_an_admin_key_once_and_runs_again_cleanly(deployment):
    log = (deployment.logs / "migrate.log").read_text()
    keys = re.findall(r"admin API key \(shown once\): (\S+)", log)
    assert len(keys) == 1, log[-3000:]
    r = httpx.get(_api(deployment) + "/api/v1/jobs", headers={"Authorization": f"Bearer {keys[0]}"})
    assert r.status_code == 200, r.text
    deployment.start("migrate")  # the next `docker compose up`
    assert deployment.wait_exit("migrate") == 0, deployment.tail("migrate")
    assert "admin API key" not in (deployment.logs / "migrate.log").read_text()


def test_the_web_pages_are_served_with_their_files(deployment):
    base = _api(deployment)
    page = httpx.get(base + "/login")
    assert page.status_code == 200 and "<form" in page.text
    assets = re.findall(r'(?:href|src)="(/static/[^"]+)"', page.text)
    assert assets, page.text[:2000]
    for asset in assets:
        assert httpx.get(base + asset).status_code == 200, asset
    # the session secret went to the api's own volume (the image's files are read-only)
    assert (deployment.folder / "volumes" / "apidata" / "secret_key").stat().st_size > 0


def test_every_long_running_service_is_still_up(deployment, job):
    for name in ("api", "worker", "beat"):
        assert deployment.children[name].poll() is None, deployment.tail(name)
    assert deployment.healthy("api")
