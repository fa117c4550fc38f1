"""`svrobs run-local` on a dataset file, run as a user runs it (a subprocess): the
records equal the core's measured path on the file's arrays, ``validation.json`` is
``svrobs_lab.validation.summarize`` of them, a spec may name the file as a path, and a
bad file or a missing one is one line naming the dataset."""

from __future__ import annotations

import json

import numpy as np
import pytest

from svrobs_core import parse_spec
from svrobs_core.measured import MeasuredData, run_measured_unit
from svrobs_lab.validation import summarize
from tests.core.test_run_local_guard import run_local
from tests.datasets import files

SPEC = {"N": [4, 8], "holdout": 2, "reps": 2, "sigma_w": "estimate", "seed": 3}


def _records(path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


@pytest.mark.parametrize("how", ["option", "path in the spec"])
def test_run_local_on_a_file_equals_the_core_on_its_arrays(tmp_path, how):
    X, U = files.rollouts(seed=9, lengths=(12,) * 10, n=3, m=2)
    (tmp_path / "plant.csv").write_bytes(files.csv_bytes(X, U))
    if how == "option":
        spec = {**SPEC, "dataset": 7}
        proc = run_local(tmp_path, spec, "--dataset", str(tmp_path / "plant.csv"))
    else:
        spec = {**SPEC, "dataset": "plant.csv"}  # beside the spec file
        proc = run_local(tmp_path, spec)
    assert proc.returncode == 0, proc.stderr
    assert "records.jsonl, summary.json, validation.json" in proc.stdout
    ident = 7 if how == "option" else 1
    parsed = parse_spec({**spec, "dataset": ident})
    data = MeasuredData(X=X, U=U)
    unit = {"system": 0, "sigma_w": 0, "N": [4, 8], "reps": [0, 2]}
    want = [json.loads(json.dumps(r)) for r in run_measured_unit(parsed, unit, data).records()]
    got = _records(tmp_path / "out" / "records.jsonl")
    key = lambda r: (r["N"], r["rep"], r["estimator"], r["gamma"] or 0)  # noqa: E731
    assert sorted(got, key=key) == sorted(want, key=key)
    assert {r["system"] for r in got} == {f"dataset-{ident}"}
    validation = json.loads((tmp_path / "out" / "validation.json").read_text())
    expected = json.loads(json.dumps(summarize(parsed.to_dict(), data), allow_nan=False))
    assert validation == expected
    assert np.isfinite(validation["models"][0]["validation"]["one_step_fit"]).all()


def test_run_local_names_a_bad_or_missing_dataset(tmp_path):
    (tmp_path / "bad.csv").write_text("rollout,k,x1,u1\n0,0,abc,1\n0,1,2,\n")
    proc = run_local(tmp_path, {**SPEC, "dataset": "bad.csv"})
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.startswith("error: invalid spec: dataset: ")
    assert "'abc' is not a number" in proc.stderr
    proc = run_local(tmp_path, {**SPEC, "dataset": "nowhere.csv"})
    assert proc.returncode == 2 and "nowhere.csv: no such file" in proc.stderr
    proc = run_local(tmp_path, {**SPEC, "dataset": 3})
    assert proc.returncode == 2 and "--dataset FILE" in proc.stderr
    assert not (tmp_path / "out" / "records.jsonl").exists()
