"""JSON columns are written by ``service.db.session.json_text`` (orjson, else
``json.dumps``): what is stored reads back as the value ``json.dumps`` would have
stored, on SQLite and PostgreSQL. Oracle: ``json.loads(json.dumps(value))``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from service.db.models import Summary
from service.db.session import json_text

VALUES = [
    {"mean": 1e-07, "std": 0.00001, "count": 3, "note": "Ω ≥ 1"},
    {"a": [1, None, True, 2.5e300, -0.0], "b": {"c": "x"}},
    [1.7976931348623157e308, 5e-324, 0.1, 1 / 3],
    {"big": 2**70, "neg": -(2**64)},  # beyond 64 bits: json.dumps writes it
    {1: "int key", "n": np.float64(0.25)},  # orjson refuses both: json.dumps writes them
]


@pytest.mark.parametrize("value", VALUES)
def test_the_text_reads_back_as_json_dumps_would_store_it(value):
    assert json.loads(json_text(value)) == json.loads(json.dumps(value))


def test_non_finite_floats_are_null():
    assert json.loads(json_text({"x": float("nan"), "y": [float("inf")]})) == {
        "x": None,
        "y": [None],
    }


def test_a_summary_row_round_trips(session, make_account, connection):
    """Through the service's engine (the rolled-back connection of the fixtures),
    into a JSON column and back as the database returns it."""
    from service.db.jobs import create_job
    from tests.service.svc_helpers import SMALL_SPEC

    acct = make_account()
    job, _ = create_job(session, team_id=acct.team.id, user_id=acct.user.id, spec=SMALL_SPEC)
    session.flush()
    stats = {"rmse_A": {"mean": 1e-07, "std": 2.5e-05, "count": 45}, "big": 2**70}
    session.execute(
        Summary.__table__.insert(),
        [
            {
                "job_id": job.id,
                "system": "S",
                "sigma_w": 0.1,
                "N": 10,
                "estimator": "svr",
                "gamma": 0.05,
                "gamma_key": 0.05,
                "count": 45,
                "stats": stats,
            }
        ],
    )
    session.flush()
    raw = connection.exec_driver_sql(
        "SELECT stats FROM summaries WHERE job_id = %d" % job.id
    ).scalar_one()
    got = json.loads(raw) if isinstance(raw, str) else raw  # PostgreSQL's driver parses JSON
    assert got == json.loads(json.dumps(stats))
