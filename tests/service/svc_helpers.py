"""Helpers shared by the service tests (a unique module name: tests/ is not a package)."""

from __future__ import annotations

from service.config import Settings
from svrobs_core.parsing import parse_spec
from svrobs_core.planning import plan_units
from tests.core.test_workload import ISSUE_MC


class Account:
    def __init__(self, team, user, key_row, key):
        self.team, self.user, self.key_row, self.key = team, user, key_row, key

    @property
    def headers(self) -> dict:
        return {"Authorization": f"Bearer {self.key}"}


class RecordingPublisher:
    def __init__(self):
        self.calls: list[list[int]] = []
        self.fail = False

    def __call__(self, unit_ids):
        if self.fail:
            return []  # like publish_units when the broker is down
        ids = list(unit_ids)
        self.calls.append(ids)
        return ids

    @property
    def published(self) -> list[int]:
        return [i for c in self.calls for i in c]


def make_settings(db_url: str, **kw) -> Settings:
    base = dict(DATABASE_URL=db_url, BROKER_URL="memory://", RATE_LIMIT_PER_MINUTE=100_000)
    base.update(kw)
    return Settings(**base)


SMALL_SPEC = {
    "systems": ["paper-stable", "paper-unstable"],
    "sigma_w": [0.5, 1.0],
    "N": [20, 40],
    "reps": 3,
    "gamma": [0.05, 0.1],
    "estimators": ["ols", "svr"],
    "seed": 7,
}
# units of SMALL_SPEC as the core plans them (consecutive N values packed per unit)
SMALL_UNITS = len(plan_units(parse_spec(SMALL_SPEC)))


def no_broker_check() -> None:
    """A broker that always answers (for ``app.dependency_overrides[get_broker_check]``)."""


def scope_of(session_factory):
    """``scope(write=...)``: a committing session context on the test's connection (what
    ``worker.tick`` takes instead of ``session_scope``)."""
    from contextlib import contextmanager

    @contextmanager
    def scope(write: bool = True):
        s = session_factory(write)
        try:
            yield s
            s.commit()
        finally:
            s.close()

    return scope


# one cell of about 11 h of CPU (over the core's hard cap on mc_runs * horizon); the core's admission tests use the same cell at 10^4 x 10^4
ITEM6_SPEC = {**ISSUE_MC, "mc_runs": 1_000_000, "horizon": 100_000}
# one small unit
TINY_SPEC = {
    "systems": ["paper-stable"],
    "sigma_w": [1.0],
    "N": [10],
    "reps": 2,
    "estimators": ["ols"],
    "stages": ["estimate", "bounds"],
    "seed": 5,
}
# within every hard cap, but about 2.6 h of CPU by the cost model: refused by its work
HEAVY_SPEC = {**ISSUE_MC, "reps": 1000, "mc_reps": 1000}
# one repetition needs about 2.9 GB (a 10-state system, T0 * N = 10^7 samples)
BIG_MEMORY_SPEC = {
    "systems": [
        {
            "name": "ten",
            "A": [[0.5 if i == j else 0.0 for j in range(10)] for i in range(10)],
            "B": [[1.0] for _ in range(10)],
        }
    ],
    "sigma_w": [1.0],
    "N": [1_000_000],
    "T0": 10,
    "reps": 1,
    "estimators": ["ols"],
    "stages": ["estimate"],
}


def track_sessions(app, session_factory) -> list:
    """The sessions ``app`` makes from now on (its session factory wrapped), to ask
    whether any of them is in a transaction while something runs."""
    opened: list = []

    def factory(write: bool = True):
        s = session_factory(write)
        opened.append(s)
        return s

    app.state.session_factory = factory
    return opened
