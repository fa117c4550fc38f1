"""Helpers shared by the service tests (a unique module name: tests/ is not a package)."""

from __future__ import annotations

from service.config import Settings
from svrobs_core.planning import plan_units
from svrobs_core.spec import parse_spec


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
