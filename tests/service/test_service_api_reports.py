"""REST: the paper preset run and the HTML job report."""

from __future__ import annotations

import re

from service.config import Settings
from service.db import jobs, units
from service.db import jobs as jobs_db
from svrobs_core.paper import paper_specs
from svrobs_core.parsing import parse_spec
from svrobs_core.report import table2
from svrobs_core.runner import run_unit
from svrobs_lab.report_html import job_report_html

API = "/api/v1"


def run_units_with_core(session, job_id):
    """Run every unit of the job through the real core, as a worker would."""
    records = []
    for uid in jobs.unit_ids_of_job(session, job_id, pending_only=False):
        spec_dict, payload = units.start_unit(session, uid, "test", 60, max_attempts=0)
        recs = run_unit(parse_spec(spec_dict), payload)
        units.complete_unit(session, uid, recs)
        session.commit()
        records += recs
    return records


def test_preset_run_queues_one_job_per_experiment(client, publisher, session, make_account):
    acc = make_account()
    r = client.post(
        f"{API}/presets/paper-section-6/run", json={"scale": "reduced"}, headers=acc.headers
    )
    assert r.status_code == 202, r.text
    jobs = r.json()
    specs = paper_specs("reduced")
    assert [j["name"] for j in jobs] == [f"paper-section-6 {e} (reduced)" for e in sorted(specs)]
    for j in jobs:
        e = j["tags"][1]
        assert j["tags"] == ["paper-section-6", e]
        assert j["spec"] == parse_spec(specs[e]).to_dict()
        assert j["n_cells"] == parse_spec(specs[e]).n_cells
    # the team's fair share is published at once (oldest job first), the rest as units finish
    total = sum(j["progress"]["total"] for j in jobs)
    first = sorted(u for j in jobs for u in jobs_db.unit_ids_of_job(session, j["id"]))
    assert publisher.published == first[: min(total, Settings().fair_share()[0])]
    listed = client.get(f"{API}/jobs", params={"tag": "paper-section-6"}, headers=acc.headers)
    assert listed.json()["total"] == len(specs)


def test_preset_run_rejects_unknown_fields_and_experiments(client, make_account):
    acc = make_account()
    for body, field in (
        ({"scale": "huge"}, "scale"),
        ({"experiments": ["E9"]}, "experiments"),
        ({"team_id": 3}, "team_id"),
    ):
        r = client.post(f"{API}/presets/paper-section-6/run", json=body, headers=acc.headers)
        assert r.status_code == 422, r.text
        assert field in r.text
    assert client.get(f"{API}/jobs", headers=acc.headers).json()["total"] == 0


def test_job_report_is_html_from_stored_records_and_team_scoped(client, session, make_account):
    acc, other = make_account(), make_account()
    spec = paper_specs("reduced")["E1"]
    jid = client.post(f"{API}/jobs", json={**spec, "name": "e1"}, headers=acc.headers).json()["id"]
    records = run_units_with_core(session, jid)
    r = client.get(f"{API}/jobs/{jid}/report", headers=acc.headers)
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    assert r.headers["x-svrobs-report"] == str(jid)  # what the client checks before saving
    html = r.text
    assert "<img" in html and "data:image/png;base64," in html
    # Table 2 values in the page are the ones computed from the stored records
    rows = table2(records)
    assert rows, "Table 2 has rows"
    for row in rows:
        for key in ("ols", "svr"):
            v = row.get(key)
            if isinstance(v, float):
                assert f"{v:.4g}" in html  # the report prints 4 significant digits
    # the reduced grid is not the paper's: the published values are left out, saying why
    assert not re.search(r"0\.0261", html)
    assert "published Table 2 values are not shown" in html and "N has 3 values 10..50" in html
    # the same records under the paper's E1 spec: the published value, labelled as such
    assert re.search(r"0\.0261", job_report_html(paper_specs("full")["E1"], records))
    assert client.get(f"{API}/jobs/{jid}/report", headers=other.headers).status_code == 404
    assert client.get(f"{API}/jobs/999999/report", headers=acc.headers).status_code == 404
