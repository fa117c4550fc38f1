"""Datasets, model exports and system files through svrobs_client and the ``svrobs``
CLI against a real server (uvicorn + a celery worker as real processes; embedded
SQLite and PostgreSQL + Redis). Oracles: the example files' own bytes and sha256,
the API read with plain httpx, the job's records (JSONL export), scipy.io.loadmat
and numpy.load of the exports, python-control's StateSpace matrices."""

from __future__ import annotations

import hashlib
import io
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import scipy.io

from svrobs_client import Client, Conflict, Dataset, Model, NotFound, ValidationError
from tests.client.cli_helpers import run_cli
from tests.client.test_client import SPEC
from tests.integration.stack import ROOT

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]
EXAMPLES = ROOT / "docs" / "examples"
FILES = ("rollouts.csv", "rollouts.npz", "rollouts_v5.mat", "rollouts_v73.mat", "rollouts.json")


@pytest.fixture(scope="module")
def client(stack):
    with Client(stack.base_url, stack.key, poll_interval=0.25) as c:
        yield c


@pytest.fixture(scope="module")
def examples(client) -> dict[str, Dataset]:
    """The committed example files, uploaded by path."""
    return {f: client.upload_dataset(EXAMPLES / f, name=f, sample_time=0.1) for f in FILES}


@pytest.fixture(scope="module")
def job(client):
    job = client.submit(SPEC, name="model-export", timeout=150)
    assert job.status == "succeeded", job
    return job


@pytest.fixture
def run(stack, capsys, monkeypatch):
    monkeypatch.setenv("SVROBS_URL", stack.base_url)
    monkeypatch.setenv("SVROBS_API_KEY", stack.key)
    monkeypatch.setenv("SVROBS_CONFIG", "/dev/null")
    return lambda *args: run_cli(capsys, *args)


def test_uploads_by_path_store_one_dataset_and_download_byte_for_byte(
    client, http, examples, tmp_path
):
    assert len({d.arrays_sha256 for d in examples.values()}) == 1
    for f, d in examples.items():
        raw = (EXAMPLES / f).read_bytes()
        assert d.sha256 == hashlib.sha256(raw).hexdigest() and d.size_bytes == len(raw)
        assert (d.rollouts, d.n, d.m, d.lengths, d.sample_time) == (3, 2, 1, [5, 3, 4], 0.1)
        assert client.download_dataset(d) == raw
        path = client.download_dataset(d, tmp_path)
        assert path == tmp_path / f and path.read_bytes() == raw
    one = examples["rollouts.csv"]
    assert client.dataset(one.id).raw == http.get(f"/datasets/{one.id}").json()
    page = client.datasets(limit=100)
    assert {d.id for d in examples.values()} <= {d.id for d in page}
    assert page.total == http.get("/datasets").json()["total"]


def test_arrays_and_dataframes_upload_as_the_same_dataset(client, examples):
    ref = examples["rollouts.csv"]
    npz = np.load(EXAMPLES / "rollouts.npz")
    X = [npz[f"X_{i}"] for i in range(3)]
    U = [npz[f"U_{i}"] for i in range(3)]
    d = client.upload_dataset((X, U), name="arrays", state_names=["p", "v"])
    assert d.arrays_sha256 == ref.arrays_sha256 and d.state_names == ["p", "v"]
    frame = pd.read_csv(EXAMPLES / "rollouts.csv")
    d = client.upload_dataset(frame, name="frame")
    assert d.arrays_sha256 == ref.arrays_sha256 and d.format == "csv"
    # equal lengths as one 3-D array, and no inputs (U None: m = 0)
    cube = np.stack([x[:4] for x in X])
    d = client.upload_dataset((cube, None), name="cube")
    assert (d.rollouts, d.m, d.lengths) == (3, 0, [3, 3, 3])


def test_errors_are_typed_and_name_the_field(client, examples, tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("rollout,k,x1,u1\n0,0,1.5,2\n0,1,abc,\n")
    with pytest.raises(ValidationError) as err:
        client.upload_dataset(bad, name="bad")
    assert (
        err.value.field == "file" and err.value.message == "row 3, column x1: 'abc' is not a number"
    )
    with pytest.raises(ValidationError) as err:
        client.upload_dataset(EXAMPLES / "rollouts.csv", name="x", state_names=["a"])
    assert err.value.field == "state_names"
    with pytest.raises(TypeError):
        client.upload_dataset(42, name="x")
    with pytest.raises(NotFound):
        client.dataset(10**9)


def test_delete_and_its_conflict(client, stack):
    d = client.upload_dataset(EXAMPLES / "rollouts.json", name="to delete")
    client.delete_dataset(d)
    with pytest.raises(NotFound):
        client.dataset(d.id)
    used = client.upload_dataset(EXAMPLES / "rollouts.json", name="used")
    job = client.submit(SPEC, wait=False)
    stack.python(
        "from sqlalchemy import update\n"
        "from service.config import get_settings\n"
        "from service.db.session import session_scope\n"
        "from service.db.models import Job\n"
        "with session_scope(get_settings().DATABASE_URL) as s:\n"
        f"    s.execute(update(Job).where(Job.id == {job.id}).values(dataset_id={used.id}))\n"
    )
    with pytest.raises(Conflict) as err:
        client.delete_dataset(used)
    assert err.value.message == f"dataset {used.id} is used by job {job.id}: delete them first"
    client.wait(job, timeout=150)
    client.delete(job)
    client.delete_dataset(used)


def test_model_is_a_statespace_of_the_record(client, job, tmp_path):
    import control

    rec = client.results_records(job, N=20, estimator="svr", rep=1)[0]
    cell = {"N": 20, "estimator": "svr", "rep": 1}
    sys = client.model(job, cell)
    assert isinstance(sys, control.StateSpace) and sys.dt is True
    assert np.array_equal(sys.A, rec["A_hat"]) and np.array_equal(sys.B, rec["B_hat"])
    assert np.array_equal(sys.C, np.eye(3)) and not sys.D.any()
    data = client.model_data(job, "N=20,estimator=svr,rep=1")
    assert isinstance(data, Model) and data["r_A"] == rec["r_A"] and data["g_L"] == rec["g_L"]
    assert np.array_equal(data.arrays["L"], rec["L"]) and np.array_equal(data["K"], rec["K"])
    assert data.provenance["job_id"] == job.id and data.provenance["spec"] == job.spec
    path = client.download_model(job, cell, format="mat", out=tmp_path / "m.mat")
    mat = scipy.io.loadmat(path)
    assert np.array_equal(mat["radii_A"], rec["radii_A"]) and mat["eps_B"].item() == rec["eps_B"]
    body = json.loads(client.download_model(job, cell, format="json"))
    assert body["A_hat"] == rec["A_hat"] and body["provenance"]["dataset"] is None
    with pytest.raises(ValidationError) as err:
        client.model(job, {"N": 20})
    assert err.value.field == "cell" and "give estimator" in err.value.message


def test_system_from_file_goes_into_a_spec(client):
    system = client.system_from_file(EXAMPLES / "system.npz", name="lab plant")
    npz = np.load(EXAMPLES / "system.npz")
    assert system["name"] == "lab plant"
    assert all(np.array_equal(system[k], npz[k]) for k in ("A", "B", "C"))
    job = client.submit({**SPEC, "systems": [system], "reps": 1}, timeout=150)
    assert job.status == "succeeded" and job.spec["systems"][0]["A"] == system["A"]


def test_cli_round_trip(run, client, http, job, tmp_path):
    code, out, err = run(
        "datasets", "upload", EXAMPLES / "rollouts_v73.mat", "--name", "cli", "--sample-time", "0.1"
    )
    assert code == 0, err
    ds_id = int(out.split()[1])
    api = http.get(f"/datasets/{ds_id}").json()
    assert out.strip() == (
        f"dataset {ds_id} 'cli': 3 rollouts (T 3..5), n=2, m=1, mat73, sha256 {api['sha256'][:12]}"
    )
    # --print-id: only the new id on stdout, the summary on stderr
    code, out, err = run(
        "datasets", "upload", EXAMPLES / "rollouts.csv", "--name", "id", "--print-id"
    )
    assert code == 0, err
    printed = int(out)
    assert out == f"{printed}\n" and printed > ds_id and err.startswith(f"dataset {printed} 'id':")
    assert http.get(f"/datasets/{printed}").json()["name"] == "id"
    code, out, _ = run("datasets", "show", ds_id, "--json")
    assert code == 0 and json.loads(out) == api
    code, out, _ = run("datasets", "show", ds_id)
    assert code == 0 and "x1\tstate\t" in out and "u1\tinput\t" in out
    code, out, _ = run("datasets", "list", "--json", "--limit", "500")
    assert code == 0 and ds_id in [d["id"] for d in json.loads(out)["items"]]
    code, out, _ = run("datasets", "list")
    assert code == 0 and out.splitlines()[0].split("\t")[:3] == ["id", "name", "format"]
    target = tmp_path / "back.mat"
    code, out, err = run("datasets", "download", ds_id, "--out", target)
    assert code == 0, err
    assert target.read_bytes() == (EXAMPLES / "rollouts_v73.mat").read_bytes()
    # a bad file: one line, exit status 2, naming the file, the field and the row
    bad = tmp_path / "bad.csv"
    bad.write_text("rollout,k,x1\n0,0,1\n0,2,2\n")
    code, out, err = run("datasets", "upload", bad, "--name", "bad")
    assert (
        code == 2
        and err
        == "error: bad.csv: file: rollout 0: k jumps from 0 to 2 (row 3); k grows by 1 from row to row\n"
    )
    code, _, err = run("datasets", "delete", ds_id)
    assert code == 2 and err.startswith("error: not deleted")
    code, out, _ = run("datasets", "delete", ds_id, "--yes")
    assert code == 0 and out.strip() == f"dataset {ds_id} deleted"
    code, _, err = run("datasets", "show", ds_id)
    assert code == 2 and err.startswith("error: ") and err.count("\n") == 1
    # svrobs model JOB --cell ... --format mat --out FILE
    rec = client.results_records(job, N=10, estimator="ols", rep=0)[0]
    code, out, err = run(
        "model",
        job.id,
        "--cell",
        "N=10,estimator=ols,rep=0",
        "--format",
        "mat",
        "--out",
        tmp_path / "ols.mat",
    )
    assert code == 0, err
    assert np.array_equal(scipy.io.loadmat(tmp_path / "ols.mat")["A_hat"], rec["A_hat"])
    code, _, err = run("model", job.id, "--cell", "N=10")
    assert code == 2 and err.startswith("error: cell: ") and err.count("\n") == 1
    # svrobs systems from-file, and a spec whose system is a file
    code, out, _ = run("systems", "from-file", EXAMPLES / "system.npz", "--name", "p")
    assert code == 0 and json.loads(out)["A"] == np.load(EXAMPLES / "system.npz")["A"].tolist()
    spec = {
        **SPEC,
        "reps": 1,
        "systems": [{"file": str(EXAMPLES / "system.npz"), "name": "from-file"}],
    }
    spec_path = tmp_path / "spec.json"
    spec_path.write_text(json.dumps(spec))
    code, out, err = run("submit", spec_path)
    assert code == 0, err
    submitted = http.get(f"/jobs/{int(out.split()[1])}").json()["spec"]["systems"][0]
    assert submitted["name"] == "from-file" and submitted["C"] == [[1.0, 0.0]]


def test_uploads_stream_from_a_file_object(client, examples):
    raw = (EXAMPLES / "rollouts.npz").read_bytes()
    d = client.upload_dataset(io.BytesIO(raw), name="stream", filename="s.npz")
    assert d.sha256 == examples["rollouts.npz"].sha256 and d.filename == "s.npz"
    assert Path(EXAMPLES / "rollouts.npz").stat().st_size == d.size_bytes


def test_a_dataset_job_and_its_validation_through_the_client_and_the_cli(
    client, http, run, tmp_path
):
    """The committed plant runs uploaded, a job on them: the client's and the CLI's
    validation are the API's; the model export's matrices are the job's record."""
    d = client.upload_dataset(EXAMPLES / "plant.csv", name="plant", sample_time=0.1)
    assert (d.rollouts, d.n, d.m) == (24, 2, 1)
    spec = {"dataset": d.id, "N": [10, 20], "holdout": 4, "reps": 2, "gamma": [0.05]}
    job = client.submit(spec, name="measured", timeout=150)
    assert job.status == "succeeded", job
    body = client.validation(job)
    assert body == http.get(f"/jobs/{job.id}/validation").json()
    assert [m["estimator"] for m in body["models"]] == ["ols", "svr"]
    code, out, _ = run("validation", str(job.id))
    assert code == 0 and out.startswith("ols: one-step fit x1 ")
    fit = body["models"][0]["validation"]["one_step_fit"][0]
    assert f"x1 {fit:.1f} %" in out
    assert f"excitation of the 20 training rollouts ({body['excitation']['N0']} transitions)" in out
    code, out, _ = run("validation", str(job.id), "--out", str(tmp_path / "v.json"))
    assert code == 0 and json.loads((tmp_path / "v.json").read_text()) == body
    code, _, err = run("validation", "999999")
    assert code == 2 and "not found" in err
    rec = next(
        r
        for r in http.get(f"/jobs/{job.id}/results", params={"limit": 100}).json()["items"]
        if (r["N"], r["estimator"], r["rep"]) == (20, "ols", 0)
    )
    model = client.model_data(job, "N=20,estimator=ols,rep=0")
    assert np.array_equal(model["A_hat"], np.array(rec["A_hat"]))
    assert model.sample_time == 0.1
