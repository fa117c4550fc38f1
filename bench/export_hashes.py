"""sha256 of every export of one job stored through the worker's write path: run it in
two checkouts (e.g. before and after a storage change) and compare the lines.

    python bench/export_hashes.py sqlite:////tmp/a.db
    python bench/export_hashes.py postgresql+psycopg://postgres@host/empty_db

The job has every stage and three systems (the paper's two and a 2-state one with
one input and one output), so every matrix shape and field is exported.
"""

import hashlib
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # before bench/service.py

from fastapi.testclient import TestClient

from service.app import create_app
from service.config import Settings
from service.db import accounts, jobs, units
from service.db.migrate import upgrade
from service.db.session import session_scope
from svrobs_core.parsing import parse_spec
from svrobs_core.runner import run_unit_result

url = sys.argv[1]
SPEC = {
    "systems": [
        "paper-stable",
        "paper-unstable",
        {"name": "custom", "A": [[0.9, 0.2], [0.0, 0.7]], "B": [[1.0], [0.5]], "C": [[1.0, 0.0]]},
    ],
    "sigma_w": [1.0, 0.1],
    "N": [20, 60],
    "gamma": [0.05, 0.1],
    "estimators": ["ols", "svr"],
    "reps": 3,
    "stages": ["estimate", "bounds", "gain", "cost", "cost_bound", "sls"],
    "mc_reps": 1,
    "mc_runs": 20,
    "horizon": 30,
    "seed": 3,
}
upgrade(url)
with session_scope(url) as s:
    team = accounts.create_team(s, "t")
    user = accounts.create_user(s, team.id, "a@t.org")
    _, key = accounts.create_key(s, user.id)
    job, _ = jobs.create_job(s, team_id=team.id, user_id=None, spec=SPEC)
    jid = job.id
spec = parse_spec(SPEC)
with session_scope(url) as s:
    ids = jobs.unit_ids_of_job(s, jid)
for uid in ids:
    with session_scope(url) as s:
        _, payload = units.start_unit(s, uid, "w", 60, max_attempts=0)
    r = run_unit_result(spec, payload)
    with session_scope(url) as s:
        units.complete_unit(s, uid, r)
app = create_app(Settings(DATABASE_URL=url, BROKER_URL="memory://", RATE_LIMIT_PER_MINUTE=100000))
app.state.broker_check = lambda: None
c = TestClient(app)
h = {"Authorization": f"Bearer {key}"}
for params in (
    {"format": "json", "limit": 10000},
    {"format": "jsonl"},
    {"format": "csv"},
    {"format": "json", "N": 60, "estimator": "svr", "limit": 7, "offset": 3},
    {"format": "csv", "system": "custom"},
):
    r = c.get(f"/api/v1/jobs/{jid}/results", params=params, headers=h)
    assert r.status_code == 200, r.text
    print(params, len(r.content), hashlib.sha256(r.content).hexdigest()[:16])
r = c.get(f"/api/v1/jobs/{jid}/summary", headers=h)
print("summary", hashlib.sha256(r.content).hexdigest()[:16])
