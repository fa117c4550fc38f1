"""Schemathesis against the API's own OpenAPI schema, in process (ASGI, no network).

The app runs on a migrated SQLite file with a fake publisher (no broker). Two
teams: A fuzzes every operation with its key, positive and negative data, each
request checked for no 5xx and for conformance to the schema (status code,
content type, body). Then, for every operation that takes a job or schedule id
(found in the schema, so a new route is covered without editing this file), B's
key is used on A's real ids with generated everything-else: the answer must be
404, never 2xx, exactly as for an id that does not exist; and A's objects are
unchanged afterwards. The number of generated requests is counted and asserted.

Deterministic (hypothesis derandomize) and budgeted: see MAX_EXAMPLES_*.
"""

from __future__ import annotations

import collections
import contextlib
import os
import re
import uuid
from types import SimpleNamespace

import pytest
import schemathesis
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st
from schemathesis import GenerationMode
from schemathesis.checks import not_a_server_error
from schemathesis.python import asgi
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    negative_data_rejection,
    response_schema_conformance,
    status_code_conformance,
)

from service.app import create_app
from service.config import Settings
from service.db import accounts, jobs
from service.db.migrate import upgrade
from service.db.models import Dataset, Job, Result, Schedule, utcnow
from service.db.session import dispose_all, get_sessionmaker
from service.http.deps import get_broker_check
from svrobs_core.records import NUMERIC_FIELDS
from svrobs_lab.auth import MAX_ID
from svrobs_lab.datasets.catalog import DatasetLimits, create_dataset
from tests.service.svc_fakes import run_job_units
from tests.service.svc_helpers import SMALL_SPEC, no_broker_check

# Budget: ~1230 generated requests on SQLite, 30-45 s on 2 cores.
MAX_EXAMPLES_FUZZ = 40  # per operation and generation mode (positive, negative)
MAX_EXAMPLES_AUTHZ = 30  # per id-taking operation, with team B's key on A's ids
MIN_GENERATED_REQUESTS = 1000
MISSING_ID = MAX_ID  # an id that never exists in this database

ID_PARAMS = {"job_id": "job", "schedule_id": "schedule", "dataset_id": "dataset"}
ID_QUERY_PARAMS = {"jobs": "job"}  # /compare?jobs=1,2
# Valid values for parameters the schema leaves as free strings, so that requests reach
# the id lookup rather than stopping at validation.
QUERY_HINTS = {
    "/api/v1/compare": {
        "metric": st.sampled_from(NUMERIC_FIELDS),
        "by": st.sampled_from(["N", "estimator,gamma", "system,sigma_w,rep"]),
    },
}


def _settings(url: str) -> Settings:
    return Settings(
        DATABASE_URL=url,
        BROKER_URL="memory://",
        RATE_LIMIT_PER_MINUTE=0,  # no throttling: every request reaches the routes
        BROKER_TIMEOUT=0.5,
    )


def _operations() -> list[tuple[str, str, dict]]:
    """(METHOD, path, operation) of every operation in the schema."""
    spec = create_app(_settings("sqlite://")).openapi()
    return [
        (method.upper(), path, op)
        for path, item in spec["paths"].items()
        for method, op in item.items()
        if method in ("get", "post", "put", "patch", "delete")
    ]


OPERATIONS = _operations()


def _id_target(op: dict) -> tuple[str, str, str] | None:
    """(location, parameter, kind) of the id an operation takes, if any."""
    for p in op.get("parameters", []):
        if p["in"] == "path" and p["name"] in ID_PARAMS:
            return "path", p["name"], ID_PARAMS[p["name"]]
        if p["in"] == "query" and p["name"] in ID_QUERY_PARAMS:
            return "query", p["name"], ID_QUERY_PARAMS[p["name"]]
    return None


RAW = {(m, p): _id_target(op) for m, p, op in OPERATIONS}
ID_OPERATIONS = [(m, p, _id_target(op)) for m, p, op in OPERATIONS if _id_target(op)]
FUZZ_IDS = [f"{m} {p} {mode}" for m, p, _ in OPERATIONS for mode in ("positive", "negative")]
AUTHZ_IDS = [f"{m} {p}" for m, p, _ in ID_OPERATIONS]

# generated requests per test id (the last test checks the total)
GENERATED: collections.Counter = collections.Counter()


def _hypothesis(max_examples: int):
    return settings(
        max_examples=max_examples,
        deadline=None,
        derandomize=True,
        database=None,
        suppress_health_check=list(HealthCheck),
        print_blob=False,
        phases=[Phase.explicit, Phase.generate, Phase.shrink],
    )


class FakePublisher:
    def __init__(self):
        self.published: list[int] = []

    def __call__(self, unit_ids):
        ids = list(unit_ids)
        self.published += ids
        return ids


def _account(session, name: str):
    team = accounts.create_team(session, name)
    user = accounts.create_user(session, team.id, f"fuzz@{name}.org")
    _, key = accounts.create_key(session, user.id)
    return SimpleNamespace(
        team_id=team.id, user_id=user.id, headers={"Authorization": f"Bearer {key}"}
    )


def _make_job(session, acc, *, run: bool = False, cancel: bool = False) -> int:
    job, _ = jobs.create_job(
        session,
        team_id=acc.team_id,
        user_id=acc.user_id,
        spec=SMALL_SPEC,
        name="fuzz",
        tags=("fuzz",),
        max_active_jobs=0,
    )
    session.commit()
    if run:
        run_job_units(session, job.id)
    if cancel:
        jobs.cancel_job(session, job)
        session.commit()
    return job.id


def _make_schedule(session, acc) -> int:
    now = utcnow()
    s = Schedule(
        team_id=acc.team_id,
        user_id=acc.user_id,
        name=f"nightly-{now.timestamp()}",
        cron="0 2 * * *",
        timezone="UTC",
        spec_template=SMALL_SPEC,
        tags=["fuzz"],
        enabled=True,
        created_at=now,
        updated_at=now,
    )
    session.add(s)
    session.commit()
    return s.id


EXAMPLE_CSV = os.path.join(
    os.path.dirname(__file__), "..", "..", "docs", "examples", "rollouts.csv"
)


def _make_dataset(session, acc) -> int:
    with open(EXAMPLE_CSV, "rb") as f:
        row = create_dataset(
            session,
            team_id=acc.team_id,
            user_id=acc.user_id,
            stream=f,
            filename="rollouts.csv",
            fields={"name": "fuzz"},
            limits=DatasetLimits(max_bytes=2**20),
        )
    session.commit()
    return row.id


@contextlib.contextmanager
def fuzz_env(url: str):
    """The app on a migrated database at ``url``, teams A and B, A's objects, a schema
    and an in-process client."""
    upgrade(url)
    session = get_sessionmaker(url)()
    try:
        a, b = _account(session, "fuzz-a"), _account(session, "fuzz-b")
        # A's data for the fuzzer to find (also reached through random small ids)
        a_jobs = [
            _make_job(session, a, run=True),
            _make_job(session, a),
            _make_job(session, a, cancel=True),
        ]
        a_schedules = [_make_schedule(session, a)]
        a_datasets = [_make_dataset(session, a)]
        _make_job(session, b, run=True)
        _make_schedule(session, b)
        _make_dataset(session, b)
        app = create_app(_settings(url))
        app.state.publisher = FakePublisher()
        app.dependency_overrides[get_broker_check] = lambda: no_broker_check
        schema = schemathesis.openapi.from_asgi("/openapi.json", app)
        with asgi.get_client(app) as client:
            yield SimpleNamespace(
                url=url,
                app=app,
                schema=schema,
                client=client,
                session=session,
                a=a,
                b=b,
                ids={"job": a_jobs, "schedule": a_schedules, "dataset": a_datasets},
            )
    finally:
        session.close()
        dispose_all()


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    with fuzz_env(f"sqlite:///{tmp_path_factory.mktemp('fuzz') / 'svrobs.db'}") as e:
        yield e


def _send(env, case, test_id: str):
    GENERATED[test_id] += 1
    return case.call(session=env.client, timeout=60)  # a report build on a loaded host


FUZZ_CHECKS = [
    not_a_server_error,
    status_code_conformance,
    content_type_conformance,
    response_schema_conformance,
]


@pytest.mark.parametrize(
    ("method", "path", "mode"),
    [(m, p, mode) for m, p, _ in OPERATIONS for mode in ("positive", "negative")],
    ids=FUZZ_IDS,
)
def test_fuzz_operation(env, method, path, mode):
    """No 5xx, documented status codes, content types and bodies; in negative mode
    invalid input is rejected (4xx)."""
    test_id = f"{method} {path} {mode}"
    op = env.schema[path][method]
    gen = GenerationMode(mode)
    strategy = op.as_strategy(gen, headers=env.a.headers)
    if gen.is_positive:
        target = RAW[(method, path)]
        if target and target[0] == "path":  # also A's real ids, so real rows are read
            _, param, kind = target
            strategy = st.one_of(
                strategy,
                st.sampled_from(env.ids[kind]).flatmap(
                    lambda i: op.as_strategy(gen, headers=env.a.headers, path_parameters={param: i})
                ),
            )
    checks = FUZZ_CHECKS + ([negative_data_rejection] if gen.is_negative else [])

    @_hypothesis(MAX_EXAMPLES_FUZZ)
    @given(case=strategy)
    def run(case):
        response = _send(env, case, test_id)
        case.validate_response(response, checks=checks)

    try:
        run()
    except Exception as exc:  # an operation without inputs to negate has no negative cases
        if gen.is_negative and GENERATED[test_id] == 0 and "Unsatisfiable" in type(exc).__name__:
            pytest.skip("nothing to negate")
        raise


@pytest.fixture
def victims(env) -> dict[str, list[int]]:
    """Fresh objects of team A for one cross-team test (the fuzzer may have cancelled or
    deleted the module's own): a finished job with results, a queued one, a cancelled
    one, a schedule and a dataset."""
    s, a = env.session, env.a
    return {
        "job": [_make_job(s, a, run=True), _make_job(s, a), _make_job(s, a, cancel=True)],
        "schedule": [_make_schedule(s, a)],
        "dataset": [_make_dataset(s, a)],
    }


def _snapshot(env, ids) -> dict:
    s = env.session
    s.expire_all()
    jobs = {
        j: (job.status, job.progress_done, job.name, job.tags, job.team_id)
        for j in ids["job"]
        for job in [s.get(Job, j)]
    }
    results = {j: s.query(Result).filter(Result.job_id == j).count() for j in ids["job"]}
    scheds = {
        i: None
        if (x := s.get(Schedule, i)) is None
        else (x.name, x.cron, x.enabled, x.spec_template, x.tags, x.team_id)
        for i in ids["schedule"]
    }
    datasets = {
        i: None if (d := s.get(Dataset, i)) is None else (d.name, d.sha256, d.team_id)
        for i in ids["dataset"]
    }
    s.rollback()
    return {"jobs": jobs, "results": results, "schedules": scheds, "datasets": datasets}


def _without_id(text: str, id_: int) -> str:
    return re.sub(rf"(?<![0-9]){id_}(?![0-9])", "<id>", text)


@pytest.mark.parametrize(("method", "path", "target"), ID_OPERATIONS, ids=AUTHZ_IDS)
def test_other_team_cannot_reach_ids(env, victims, method, path, target):
    """Team B's key on team A's real job/schedule ids: 404 (never 2xx), the same answer
    as for an id that does not exist, and A's data unchanged."""
    test_id = f"authz {method} {path}"
    where, param, kind = target
    op = env.schema[path][method]
    before = _snapshot(env, victims)
    assert all(v is not None for v in before["schedules"].values())
    assert all(v is not None for v in before["datasets"].values())
    assert (
        before["jobs"][victims["job"][0]][0] == "succeeded"
        and before["results"][victims["job"][0]] > 0
    )
    statuses: collections.Counter = collections.Counter()

    def strategy_for(real: int):
        if where == "path":
            return op.as_strategy(
                GenerationMode.POSITIVE, headers=env.b.headers, path_parameters={param: real}
            )
        hints = QUERY_HINTS.get(path, {})
        return st.fixed_dictionaries(hints).flatmap(
            lambda q: op.as_strategy(
                GenerationMode.POSITIVE, headers=env.b.headers, query={**q, param: str(real)}
            )
        )

    @_hypothesis(MAX_EXAMPLES_AUTHZ)
    @given(real=st.sampled_from(victims[kind]), data=st.data())
    def run(real, data):
        case = data.draw(strategy_for(real))
        response = _send(env, case, test_id)
        if where == "path":
            missing = case.derive()
            missing.path_parameters[param] = MISSING_ID
        else:
            missing = case.derive(query={**case.query, param: str(MISSING_ID)})
        baseline = missing.call(session=env.client)
        statuses[response.status_code] += 1
        assert not 200 <= response.status_code < 300, (case.as_curl_command(), response.text)
        assert response.status_code < 500, response.text
        # indistinguishable from a missing id: same status, same body but for the id
        assert response.status_code == baseline.status_code, (response.text, baseline.text)
        assert _without_id(response.text, real) == _without_id(baseline.text, MISSING_ID)
        # 404, unless the input itself was rejected before any lookup (422 either way)
        assert response.status_code == 404 or (
            response.status_code == 422 and baseline.status_code == 422
        ), response.text

    run()
    assert _snapshot(env, victims) == before
    # most generated requests are valid enough to reach the lookup
    assert statuses[404] >= 0.5 * sum(statuses.values()), statuses


PG_ENV = "SVROBS_TEST_DATABASE_URL"
MAX_EXAMPLES_PG = 12  # per operation and mode: a smoke pass for dialect-specific 5xx


@contextlib.contextmanager
def _private_pg_database(base_url: str):
    from sqlalchemy import create_engine, text
    from sqlalchemy.engine import make_url

    url = make_url(base_url)
    name = f"svrobs_fuzz_{os.getpid()}_{uuid.uuid4().hex[:6]}"
    admin_engine = create_engine(url, isolation_level="AUTOCOMMIT")
    try:
        with admin_engine.connect() as c:
            c.execute(text(f'CREATE DATABASE "{name}"'))
        yield url.set(database=name).render_as_string(hide_password=False)
    finally:
        dispose_all()
        with admin_engine.connect() as c:
            c.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin_engine.dispose()


def _pg_pass(pg, op, gen, test_id: str) -> None:
    @_hypothesis(MAX_EXAMPLES_PG)
    @given(case=op.as_strategy(gen, headers=pg.a.headers))
    def run(case):
        response = _send(pg, case, test_id)
        case.validate_response(response, checks=[not_a_server_error])

    run()


@pytest.mark.skipif(not os.environ.get(PG_ENV), reason=f"{PG_ENV} not set")
def test_fuzz_postgresql_no_server_errors():
    """A smaller pass on PostgreSQL, where text and integer limits differ from SQLite
    (NUL characters, 32-bit columns): no 5xx on any operation."""
    failures = []
    with _private_pg_database(os.environ[PG_ENV]) as url, fuzz_env(url) as pg:
        for method, path, _ in OPERATIONS:
            op = pg.schema[path][method]
            for gen in (GenerationMode.POSITIVE, GenerationMode.NEGATIVE):
                test_id = f"pg {method} {path} {gen.value}"
                try:
                    _pg_pass(pg, op, gen, test_id)
                except (Exception, BaseExceptionGroup) as exc:  # noqa: BLE001 - report them all
                    if not (gen.is_negative and "Unsatisfiable" in type(exc).__name__):
                        failures.append(f"{test_id}: {exc}")
    assert not failures, "\n\n".join(failures)


def test_zz_generated_request_count():
    """At least MIN_GENERATED_REQUESTS generated requests when the whole module ran."""
    expected = {t for t in FUZZ_IDS if t.endswith("positive")} | {f"authz {i}" for i in AUTHZ_IDS}
    if not expected <= set(GENERATED):
        pytest.skip("only part of the fuzz module ran")
    total = sum(v for k, v in GENERATED.items() if not k.startswith("pg "))
    pg = sum(v for k, v in GENERATED.items() if k.startswith("pg "))
    print(
        f"\nschemathesis: {total} generated requests over {len(OPERATIONS)} operations on "
        f"SQLite ({sum(v for k, v in GENERATED.items() if k.startswith('authz'))} of them "
        f"cross-team), {pg} more on PostgreSQL"
    )
    assert total >= MIN_GENERATED_REQUESTS, GENERATED
