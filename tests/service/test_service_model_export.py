"""GET /jobs/{id}/model: one cell of a job computed by the core, exported as JSON, NPZ
and MAT, opened back with json / numpy.load / scipy.io.loadmat, equals the stored
record (the results API's); the cell is picked by any set of coordinates that names
one; a dataset job's export carries the dataset's sha256 and sample time. Also
POST /systems/from-file."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
import scipy.io
from sqlalchemy import update

from service.db import jobs as job_store
from service.db import units
from service.db.models import Job
from svrobs_core import parse_spec
from svrobs_core.runner import run_unit
from svrobs_core.systems import resolve_system
from tests.datasets import files

API = "/api/v1"
SYSTEM = {
    "name": "plant",
    "A": [[0.9, 0.2], [0.0, 0.7]],
    "B": [[0.0], [1.0]],
    "C": [[1.0, 0.0]],
    "sigma_v": 0.1,
}
SPEC = {
    "systems": [SYSTEM, "paper-stable"],
    "sigma_w": [0.5],
    "N": [20, 30],
    "reps": 2,
    "estimators": ["ols", "svr"],
    "gamma": [0.1],
    "stages": ["estimate", "bounds", "gain"],
    "delta": 0.05,
    "seed": 4,
}
MATRICES = ("A_hat", "B_hat", "radii_A", "radii_B", "L", "K")
SCALARS = ("r_A", "r_B", "eps_A", "eps_B", "g_L", "sigma_w")


@pytest.fixture
def computed(client, session, make_account):
    """A job whose every unit the core ran, and the team's account."""
    acc = make_account()
    r = client.post(f"{API}/jobs", json=SPEC, headers=acc.headers)
    assert r.status_code == 202, r.text
    jid = r.json()["id"]
    for uid in job_store.unit_ids_of_job(session, jid, pending_only=False):
        spec, payload = units.start_unit(session, uid, "w1", 60, max_attempts=0)
        units.complete_unit(session, uid, run_unit(parse_spec(spec), payload))
        session.commit()
    return acc, jid


def _record(client, acc, jid, **filters) -> dict:
    items = client.get(f"{API}/jobs/{jid}/results", params=filters, headers=acc.headers).json()
    assert items["total"] == 1, items
    return items["items"][0]


def _model(client, acc, jid, cell, fmt):
    r = client.get(
        f"{API}/jobs/{jid}/model", params={"cell": cell, "format": fmt}, headers=acc.headers
    )
    assert r.status_code == 200, r.text
    return r


def test_each_format_opens_back_to_the_record(client, computed):
    acc, jid = computed
    rec = _record(client, acc, jid, system="plant", N=30, estimator="svr", rep=1)
    assert rec["L"] is not None and rec["radii_A"] is not None  # the gain stage ran
    cell = "system=plant,N=30,estimator=svr,rep=1"
    C = resolve_system(SYSTEM).C

    j = _model(client, acc, jid, cell, "json")
    assert j.headers["content-type"].startswith("application/json")
    assert 'filename="job-' in j.headers["content-disposition"]
    body = j.json()
    for f in MATRICES + SCALARS + ("system", "N", "estimator", "gamma", "rep", "certified"):
        assert body[f] == rec[f], f
    assert body["C"] == C.tolist() and body["delta"] == 0.05 and body["sample_time"] is None
    assert body["sigma_w_estimated"] is False
    prov = body["provenance"]
    assert prov["job_id"] == jid and prov["dataset"] is None
    assert prov["spec"] == client.get(f"{API}/jobs/{jid}", headers=acc.headers).json()["spec"]
    assert prov["version"] and "git_commit" in prov

    npz = np.load(io.BytesIO(_model(client, acc, jid, cell, "npz").content), allow_pickle=False)
    for f in MATRICES:
        assert npz[f].tobytes() == np.array(rec[f], dtype=float).tobytes(), f
    for f in SCALARS:
        assert float(npz[f]) == rec[f], f
    assert npz["C"].tolist() == C.tolist() and float(npz["delta"]) == 0.05
    assert str(npz["estimator"]) == "svr" and bool(npz["certified"]) == rec["certified"]
    assert json.loads(str(npz["provenance"])) == prov

    mat = scipy.io.loadmat(io.BytesIO(_model(client, acc, jid, cell, "mat").content))
    for f in MATRICES:
        assert np.array_equal(mat[f], np.array(rec[f], dtype=float)), f
    for f in SCALARS:
        assert mat[f].item() == rec[f], f
    assert np.array_equal(mat["C"], C) and mat["delta"].item() == 0.05
    assert mat["system"][0] == "plant" and json.loads(mat["provenance"][0]) == prov


def test_an_ols_cell_and_the_preset_system(client, computed):
    acc, jid = computed
    rec = _record(client, acc, jid, system="paper-stable", N=20, gamma="null", rep=0)
    cell = json.dumps({"system": "paper-stable", "N": 20, "gamma": None, "rep": 0})
    body = _model(client, acc, jid, cell, "json").json()
    assert body["estimator"] == "ols" and body["gamma"] is None
    assert body["A_hat"] == rec["A_hat"] and body["C"] == np.eye(3).tolist()
    npz = np.load(
        io.BytesIO(
            _model(client, acc, jid, "system=paper-stable,N=20,gamma=null,rep=0", "npz").content
        )
    )
    assert "gamma" not in npz.files and np.array_equal(npz["A_hat"], rec["A_hat"])


@pytest.mark.parametrize(
    ("cell", "message"),
    [
        (
            "system=plant,N=30",
            r"^4 cells of job \d+ have system=plant, N=30; give estimator \(ols, svr\); gamma \(null, 0\.1\); rep \(0, 1\)$",
        ),
        (
            "system=plant,N=31,estimator=ols,rep=0",
            r"^no cell of job \d+ has system=plant, N=31, estimator=ols, rep=0$",
        ),
        ("colour=red", r"^unknown coordinate 'colour'"),
        ("N=3.5", r"^N must be an integer, got '3\.5'$"),
        ("N", r"^'N' is not KEY=VALUE$"),
        ("N=20,N=30", r"^N given twice$"),
        ("{bad json", r"^not a JSON object"),
        ('{"system":' + "[" * 1985, r"^not a JSON object"),
        ('{"system": "\\ud800"}', r"^system: '\\ud800': a name is 1 to 64 printable"),
        ("sigma_w=nan", r"^sigma_w must be a finite number"),
    ],
)
def test_a_cell_that_is_not_one_cell_is_a_422_naming_it(client, computed, cell, message):
    import re

    acc, jid = computed
    r = client.get(f"{API}/jobs/{jid}/model", params={"cell": cell}, headers=acc.headers)
    assert r.status_code == 422 and r.json()["field"] == "cell", r.text
    assert re.search(message, r.json()["detail"]), r.json()["detail"]


def test_a_cell_the_job_has_not_computed_names_the_jobs_state(client, session, make_account):
    """Queued or running: a 409 saying so (the cell may come); cancelled: the 422 of a
    missing cell, saying the job was cancelled."""
    acc = make_account()
    jid = client.post(f"{API}/jobs", json=SPEC, headers=acc.headers).json()["id"]
    cell = {"cell": "system=plant,N=20,estimator=ols,rep=0"}
    wanted = "no computed cell has system=plant, N=20, estimator=ols, rep=0 yet"
    for status in ("queued", "running"):
        r = client.get(f"{API}/jobs/{jid}/model", params=cell, headers=acc.headers)
        assert r.status_code == 409 and r.json()["field"] == "cell", r.text
        assert r.json()["detail"] == (
            f"job {jid} is {status} (0 of 16 cells computed): {wanted};"
            " export it once the job has computed it"
        )
        uid = job_store.unit_ids_of_job(session, jid, pending_only=False)[0]
        units.start_unit(session, uid, "w1", 60, max_attempts=0)
        session.commit()
    assert client.post(f"{API}/jobs/{jid}/cancel", headers=acc.headers).status_code == 200
    r = client.get(f"{API}/jobs/{jid}/model", params=cell, headers=acc.headers)
    assert r.status_code == 422 and r.json()["field"] == "cell", r.text
    assert r.json()["detail"].endswith("(it was cancelled with 0 of 16 cells computed)")


def test_format_and_team_scoping(client, computed, make_account):
    acc, jid = computed
    cell = "system=plant,N=20,estimator=ols,rep=0"
    r = client.get(
        f"{API}/jobs/{jid}/model", params={"cell": cell, "format": "xml"}, headers=acc.headers
    )
    assert r.status_code == 422 and r.json()["field"] == "format"
    other = make_account()
    r = client.get(f"{API}/jobs/{jid}/model", params={"cell": cell}, headers=other.headers)
    assert r.status_code == 404


def test_a_pruned_jobs_export_is_a_410_as_its_results(client, session, computed):
    """Retention dropped the cell rows: the model of a cell is gone, as the results are
    (the cell named is right; a 422 naming it said otherwise)."""
    from service.db.retention import prune_job

    acc, jid = computed
    cell = {"cell": "system=plant,N=20,estimator=ols,rep=0"}
    r = client.get(f"{API}/jobs/{jid}/model", params=cell, headers=acc.headers)
    assert r.status_code == 200
    prune_job(session, jid)
    session.commit()
    for path, params in ((f"/jobs/{jid}/model", cell), (f"/jobs/{jid}/results", {})):
        r = client.get(f"{API}{path}", params=params, headers=acc.headers)
        assert r.status_code == 410 and "retention policy" in r.json()["detail"], r.text
    bad = client.get(f"{API}/jobs/{jid}/model", params={"cell": "x"}, headers=acc.headers)
    assert bad.status_code == 422 and bad.json()["field"] == "cell"  # a bad cell is still one


def test_a_dataset_jobs_export_names_the_dataset(client, session, computed):
    acc, jid = computed
    X, U = files.rollouts(lengths=(4, 5), n=2, m=1)
    data = files.csv_bytes(X, U)
    ds = client.post(
        f"{API}/datasets",
        files={"file": ("plant.csv", data)},
        data={"name": "plant runs", "sample_time": "0.02"},
        headers=acc.headers,
    ).json()
    session.execute(update(Job).where(Job.id == jid).values(dataset_id=ds["id"]))
    session.commit()
    body = _model(client, acc, jid, "system=plant,N=20,estimator=ols,rep=0", "json").json()
    assert body["sample_time"] == 0.02
    assert body["provenance"]["dataset"] == {
        "id": ds["id"],
        "name": "plant runs",
        "sha256": ds["sha256"],
        "arrays_sha256": ds["arrays_sha256"],
        "sample_time": 0.02,
        "state_names": ["x1", "x2"],
        "input_names": ["u1"],
    }
    mat = scipy.io.loadmat(
        io.BytesIO(_model(client, acc, jid, "system=plant,N=20,estimator=ols,rep=0", "mat").content)
    )
    assert mat["sample_time"].item() == 0.02


def test_system_from_file(client, make_account, tmp_path):
    acc = make_account()
    buf = io.BytesIO()
    np.savez(
        buf, A=np.array(SYSTEM["A"]), B=np.array(SYSTEM["B"]), C=np.array(SYSTEM["C"]), sigma_v=0.1
    )
    r = client.post(
        f"{API}/systems/from-file",
        files={"file": ("plant.npz", buf.getvalue())},
        headers=acc.headers,
    )
    assert r.status_code == 200, r.text
    want = resolve_system(SYSTEM).to_dict()
    assert r.json() == want
    mat = io.BytesIO()
    scipy.io.savemat(mat, {"A": np.array(SYSTEM["A"]), "B": np.array(SYSTEM["B"])})
    r = client.post(
        f"{API}/systems/from-file",
        files={"file": ("m.mat", mat.getvalue())},
        data={"name": "lab plant"},
        headers=acc.headers,
    )
    assert (
        r.status_code == 200
        and r.json()["name"] == "lab plant"
        and r.json()["C"] == np.eye(2).tolist()
    )
    # the returned object is a spec's system as is
    spec = {"systems": [r.json()], "sigma_w": [0.1], "N": [20], "reps": 1}
    assert client.post(f"{API}/jobs", json=spec, headers=acc.headers).status_code == 202
    bad = io.BytesIO()
    np.savez(bad, A=np.ones((2, 3)), B=np.ones((2, 1)))
    r = client.post(
        f"{API}/systems/from-file", files={"file": ("b.npz", bad.getvalue())}, headers=acc.headers
    )
    assert r.status_code == 422 and r.json()["field"] == "file"
    assert r.json()["detail"] == "A: must be square, got 2x3"
    nob = io.BytesIO()
    np.savez(nob, A=np.eye(2))
    r = client.post(
        f"{API}/systems/from-file", files={"file": ("b.npz", nob.getvalue())}, headers=acc.headers
    )
    assert r.status_code == 422 and r.json()["detail"].startswith("no variable 'B'")


@pytest.mark.parametrize(
    ("in_file", "form", "field", "message"),
    [
        ("\ud800", None, "file", r"^name: '\\ud800': a name is 1 to 64 printable characters$"),
        ("a\x00b", None, "file", r"^name: 'a\\x00b': a name is 1 to 64 printable characters$"),
        ("\udce9" * 100, None, "file", r"^name: '(\\udce9){80}'\.\.\. \(cut, 100 characters\)"),
        ("plant", "a\x01b", "name", r"^'a\\x01b': a name is 1 to 64 printable characters$"),
    ],
)
def test_a_system_files_name_is_printable_text(client, make_account, in_file, form, field, message):
    import re

    acc = make_account()
    buf = io.BytesIO()
    np.savez(buf, A=np.eye(2) * 0.5, B=np.ones((2, 1)), name=np.array(in_file))
    r = client.post(
        f"{API}/systems/from-file",
        files={"file": ("s.npz", buf.getvalue())},
        data={} if form is None else {"name": form},
        headers=acc.headers,
    )
    assert r.status_code == 422 and r.json()["field"] == field, r.text
    assert re.search(message, r.json()["detail"]), r.json()["detail"]


def test_a_dataset_specs_output_matrix_and_estimated_noise():
    """C of a dataset job: the spec's, else I for the full state, else the rows of the
    ARX state x_k = [y_k, y_(k-1), u_(k-1)] that pick y_k; sigma_w "estimate" (the
    record's key -1) is exported as null with sigma_w_estimated."""
    from svrobs_lab.datasets.model_export import model_payload

    record = {"system": "dataset-5", "sigma_w": -1.0, "N": 4, "estimator": "ols", "gamma": None}
    record.update(rep=0, A_hat=np.eye(3).tolist(), B_hat=[[1.0], [0.0], [0.0]])
    dataset = {"id": 5, "name": "d", "sha256": "s", "arrays_sha256": "a", "sample_time": 0.5}
    dataset.update(n=1, m=1, state_names=["y1"], input_names=["u1"])
    arx = {"dataset": 5, "N": [4], "state": {"lags": {"y": 2, "u": 1}}, "reps": 1}
    job = Job(id=9, team_id=1, spec=parse_spec(arx).to_dict(), provenance={})
    body = model_payload(record, job=job, dataset=dataset)
    assert body["C"] == [[1.0, 0.0, 0.0]] and body["sample_time"] == 0.5
    assert body["sigma_w"] is None and body["sigma_w_estimated"] is True
    full = {"dataset": 5, "N": [4], "reps": 1, "sigma_w": 0.2}
    job = Job(id=9, team_id=1, spec=parse_spec(full).to_dict(), provenance={})
    body = model_payload({**record, "sigma_w": 0.2}, job=job, dataset={**dataset, "n": 3, "m": 1})
    assert body["C"] == np.eye(3).tolist() and body["sigma_w"] == 0.2
    assert body["sigma_w_estimated"] is False
    given = {**full, "C": [[0.0, 1.0, 0.0]]}
    job = Job(id=9, team_id=1, spec=parse_spec(given).to_dict(), provenance={})
    assert model_payload(record, job=job, dataset={**dataset, "n": 3})["C"] == [[0.0, 1.0, 0.0]]
