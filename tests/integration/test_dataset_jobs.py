"""A job on a dataset end to end with real processes (uvicorn, a celery worker, the
database), on the embedded stack and on PostgreSQL + Redis: a dataset simulated from
a known system (no preset) is uploaded as a file; the job's records, computed by
the worker from the arrays it reads in the database, equal the core's measured path
run in this process on the same arrays, bit for bit; its validation is what
``validation_summary`` gives in process; its report and its model export are served."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from svrobs_core import RECORD_FIELDS, parse_spec
from svrobs_core.measured import MeasuredData, run_measured_unit
from svrobs_lab.validation import summarize
from tests.datasets import files

from .stack import cell_key, fetch_jsonl, same, submit

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]

# 2 states, 1 input, of no preset
A_TRUE = np.array([[0.85, -0.2], [0.15, 0.7]])
B_TRUE = np.array([[0.5], [1.0]])


SPEC = {
    "N": [6, 10, 14],
    "holdout": 4,
    "reps": 400,  # two work units: N 6 and 10, then 14
    "gamma": [0.05],
    "estimators": ["ols", "svr"],
    "sigma_w": "estimate",
    "seed": 21,
}


def test_dataset_job_over_rest_equals_the_core_on_the_arrays(stack):
    X, U = files.simulate(A_TRUE, B_TRUE, 17, lengths=(20,) * 18)
    with stack.client() as c:
        r = c.post(
            "/datasets",
            files={"file": ("plant.npz", files.npz_bytes(X, U))},
            data={"name": "plant", "sample_time": "0.05"},
        )
        assert r.status_code == 201, r.text
        ds = r.json()
        spec = {**SPEC, "dataset": ds["id"]}
        job = submit(c, spec, name="measured")
        assert job["progress"]["total"] == 2
        done = stack.wait_job(c, job["id"], timeout=200)
        assert done["status"] == "succeeded", done
        got = fetch_jsonl(c, job["id"])
        validation = c.get(f"/jobs/{job['id']}/validation")
        report = c.get(f"/jobs/{job['id']}/report")
        cell = "N=14,estimator=ols,rep=0"
        model = c.get(f"/jobs/{job['id']}/model", params={"cell": cell, "format": "npz"})

    parsed = parse_spec(spec)
    data = MeasuredData(X=X, U=U, sample_time=0.05)
    unit = {"system": 0, "sigma_w": 0, "N": list(parsed.N), "reps": [0, parsed.reps]}
    want = {
        cell_key(r): json.loads(json.dumps(r, allow_nan=False))
        for r in run_measured_unit(parsed, unit, data).records()
    }
    assert len(got) == len(want) == parsed.n_cells
    by_key = {cell_key(r): r for r in got}
    diffs = [d for k, w in want.items() for f in RECORD_FIELDS for d in same(by_key[k][f], w[f], f)]
    assert not diffs, diffs[:10]

    assert validation.status_code == 200, validation.text
    body = validation.json()
    assert body.pop("job_id") == job["id"] and body.pop("dataset") == ds["id"]
    assert not same(body, json.loads(json.dumps(summarize(spec, data), allow_nan=False)))
    assert body["plots"]["sample_time"] == 0.05

    assert report.status_code == 200 and "measured data: no true system" in report.text
    assert model.status_code == 200, model.text
    exported = np.load(io.BytesIO(model.content))
    assert np.array_equal(
        exported["A_hat"],
        np.array(want[(f"dataset-{ds['id']}", -1.0, 14, "ols", -1.0, 0)]["A_hat"]),
    )
    print(f"\n[{stack.kind}] {len(got)} dataset records over REST, bit-identical")


def test_no_inputs_over_rest_and_a_used_dataset_is_not_deleted(stack):
    """m = 0 (an autonomous system, a CSV with no input column) through the API and a
    worker: records equal the core's with n x 0 B matrices, the validation and the
    model export have them too; deleting the dataset while its job exists is a 409
    naming the job, and once the job is deleted the dataset goes."""
    X, U = files.simulate(A_TRUE, np.zeros((2, 0)), 23, lengths=(15,) * 10)
    assert U[0].shape == (15, 0)
    spec = {
        "N": [3, 6],
        "holdout": 3,
        "reps": 2,
        "gamma": [0.05],
        "stages": ["estimate", "bounds", "gain", "cost"],
        "sigma_w": 0.1,
        "seed": 3,
    }
    with stack.client() as c:
        r = c.post(
            "/datasets",
            files={"file": ("free.csv", files.csv_bytes(X, U))},
            data={"name": "free", "input_columns": ""},
        )
        assert r.status_code == 201, r.text
        ds = r.json()
        assert (ds["n"], ds["m"], ds["input_names"]) == (2, 0, [])
        spec = {**spec, "dataset": ds["id"]}
        job = submit(c, spec, name="no inputs")
        done = stack.wait_job(c, job["id"], timeout=200)
        assert done["status"] == "succeeded", done
        got = {cell_key(r): r for r in fetch_jsonl(c, job["id"])}
        validation = c.get(f"/jobs/{job['id']}/validation").json()
        cell = "N=6,estimator=svr,rep=1"
        model = c.get(f"/jobs/{job['id']}/model", params={"cell": cell, "format": "json"})
        in_use = c.delete(f"/datasets/{ds['id']}")
        still = c.get(f"/datasets/{ds['id']}").status_code
        assert c.delete(f"/jobs/{job['id']}").status_code == 204
        gone = c.delete(f"/datasets/{ds['id']}").status_code
        after = c.get(f"/datasets/{ds['id']}").status_code

    parsed = parse_spec(spec)
    unit = {"system": 0, "sigma_w": 0, "N": list(parsed.N), "reps": [0, parsed.reps]}
    want = {
        cell_key(r): json.loads(json.dumps(r, allow_nan=False))
        for r in run_measured_unit(parsed, unit, MeasuredData(X=X, U=U)).records()
    }
    assert set(got) == set(want) and len(got) == parsed.n_cells
    diffs = [d for k, w in want.items() for f in RECORD_FIELDS for d in same(got[k][f], w[f], f)]
    assert not diffs, diffs[:10]
    assert all(r["B_hat"] == [[], []] and r["L"] is not None for r in got.values())
    assert [m["B_hat"] for m in validation["models"]] == [[[], []], [[], []]]
    assert all(m["validation"]["channels"] == ["x1", "x2"] for m in validation["models"])
    assert model.status_code == 200, model.text
    exported = model.json()
    key = (f"dataset-{ds['id']}", 0.1, 6, "svr", 0.05, 1)
    assert exported["A_hat"] == want[key]["A_hat"] and exported["B_hat"] == [[], []]

    assert in_use.status_code == 409 and still == 200
    assert in_use.json()["detail"] == (
        f"dataset {ds['id']} is used by job {job['id']}: delete them first"
    )
    assert (gone, after) == (204, 404)
