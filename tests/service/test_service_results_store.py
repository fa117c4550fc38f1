"""The worker's write path (``units.complete_unit`` of a unit's column arrays) on both
dialects: the stored cells are the core's records bit for bit, and a redelivered
unit overwrites its cells on the cell key (no second row, no stale value)."""

from __future__ import annotations

from sqlalchemy import func, select

from service.db import jobs, results_store, units
from service.db.models import RESULT_SCALAR_FIELDS, Result
from svrobs_core.parsing import parse_spec
from svrobs_core.records import RECORD_FIELDS, json_value
from svrobs_core.runner import run_unit_result
from tests.service.svc_fakes import fake_records
from tests.service.svc_helpers import SMALL_SPEC

SPEC = {  # every stage, so that every column holds values (and NaNs become NULLs)
    **SMALL_SPEC,
    "systems": ["paper-unstable", "paper-stable"],
    "sigma_w": [1.0],
    "N": [12, 40],
    "reps": 2,
    "stages": ["estimate", "bounds", "gain", "cost", "sls"],
    "mc_reps": 1,
    "mc_runs": 20,
}


def bits(v):
    """A value with every float as its exact bits (``float.hex``), ints and bools apart."""
    if isinstance(v, float):
        return ("float", v.hex())
    if isinstance(v, (list, tuple)):
        return [bits(x) for x in v]
    return (type(v).__name__, v)


def cell(r: dict) -> tuple:
    return (r["system"], r["N"], r["estimator"], r["gamma"], r["rep"])


def _count(session, job_id: int) -> int:
    return session.scalar(select(func.count()).select_from(Result).where(Result.job_id == job_id))


def _raw_scalars(session, job_id: int) -> dict[tuple, dict]:
    """The stored scalar columns as they are in the table (no decoding)."""
    t = Result.__table__
    names = [c for c in RESULT_SCALAR_FIELDS if c in RECORD_FIELDS] + ["system", "estimator"]
    rows = session.execute(select(*(t.c[c] for c in names)).where(t.c.job_id == job_id)).all()
    return {cell(r): r for r in (dict(zip(names, row)) for row in rows)}


def test_stored_rows_equal_the_unit_columns_bit_for_bit(session, make_account):
    acc = make_account()
    job, _ = jobs.create_job(session, team_id=acc.team.id, user_id=None, spec=SPEC)
    session.commit()
    want: dict[tuple, dict] = {}
    for uid in jobs.unit_ids_of_job(session, job.id):
        spec_dict, payload = units.start_unit(session, uid, "w", 60, max_attempts=0)
        result = run_unit_result(parse_spec(spec_dict), payload)
        assert units.complete_unit(session, uid, result)
        for rec in result.records():  # the oracle: the core's record dicts, NaN as null
            want[cell(rec)] = {k: json_value(v) for k, v in rec.items()}
    session.commit()
    assert _count(session, job.id) == len(want) == parse_spec(SPEC).n_cells
    raw = _raw_scalars(session, job.id)
    decoded = {cell(r): r for r in results_store.load_records(session, job.id)}
    assert set(raw) == set(decoded) == set(want)
    nulls = set()
    for key, rec in want.items():
        for f, v in raw[key].items():
            assert bits(v) == bits(rec[f]), (key, f)
            if v is None:
                nulls.add(f)
        assert bits(decoded[key]) == bits(rec), key  # matrices, seed_key, notes too
    # the grid exercised NULLs beside values (gamma of OLS, a stage's NaNs)
    assert "gamma" in nulls and any(raw[k]["gamma"] is not None for k in raw)
    assert any(r["L"] is not None and r["sls_status"] is not None for r in decoded.values())


def test_a_redelivered_unit_overwrites_its_cells_and_adds_no_row(session, make_account):
    acc = make_account()
    job, _ = jobs.create_job(session, team_id=acc.team.id, user_id=None, spec=SMALL_SPEC)
    session.commit()
    uid = jobs.unit_ids_of_job(session, job.id)[0]
    spec_dict, payload = units.start_unit(session, uid, "w", 60, max_attempts=0)
    result = run_unit_result(parse_spec(spec_dict), payload)
    units.complete_unit(session, uid, result)
    session.commit()
    stored = results_store.load_records(session, job.id)
    first = {cell(r): bits(r) for r in stored}
    assert len(first) == len(result) and all(r["r_A"] is not None for r in stored)

    units.complete_unit(session, uid, result)  # the same message delivered again
    session.commit()
    assert _count(session, job.id) == len(result)
    assert {cell(r): bits(r) for r in results_store.load_records(session, job.id)} == first

    # a delivery whose cells differ: every stored value is replaced, also by a NULL
    # where a column is NULL in every new row (such a column is not sent at all)
    recs = fake_records(spec_dict, payload)
    assert all(r["H_A"] is not None for r in recs)
    for r in recs:
        r["H_A"] = None
        r["rmse_A"] = 0.125 + r["rep"]
    units.complete_unit(session, uid, recs)
    session.commit()
    assert _count(session, job.id) == len(result) == len(recs)
    got = {cell(r): r for r in results_store.load_records(session, job.id)}
    for r in recs:
        stored = got[cell(r)]
        assert stored["H_A"] is None and bits(stored["rmse_A"]) == bits(r["rmse_A"])
        assert stored["A_hat"] == r["A_hat"] and stored["notes"] == r["notes"]
        assert stored["r_A"] is None  # set by the first delivery, absent from this one


def test_the_columns_left_unchecked_hold_what_the_check_gives():
    """``unit_columns`` skips the per-value check of a field whose arrays are plain
    (``UnitResult.plain_fields``): for every scalar column, of every array kind a
    field can hold (numeric with NaN and infinities, bool, object with numpy
    scalars and None, a bool array in a float field, a float array in a bool
    field), the stored values equal ``_clean_scalar`` of each value, type and bits."""
    import numpy as np

    spec = parse_spec({**SPEC, "systems": ["paper-unstable"], "N": [40]})
    from svrobs_core import plan_units

    result = run_unit_result(spec, plan_units(spec)[0])
    ds = result.datasets[0]
    R, E = len(result.reps), len(result.axis.names)
    shape = (R, E)
    odd = np.full(shape, 0.25)
    odd.flat[0], odd.flat[-1] = np.nan, -np.inf
    obj = np.empty(shape, dtype=object)
    obj.flat[:] = [np.float64(1.5), None, np.float32(2.0), np.int64(3)][: R * E] + [None] * (
        R * E - 4
    )
    ds.fields.update(
        {
            "rmse_A": odd,  # numeric, with NaN and -inf: plain
            "rmse_B": obj,  # object: checked
            "eps_A": np.ones(shape, dtype=bool),  # bool in a float field: checked
            "thm1_holds_A": np.array(np.eye(*shape), dtype=float),  # float in a bool field
            "stable_certified": np.zeros(shape, dtype=bool),  # bool in a bool field: plain
            "J_exact": np.arange(R * E, dtype=np.int64).reshape(shape),  # ints: plain floats
        }
    )
    kinds = result.plain_fields()
    assert kinds["rmse_A"] == "float" and kinds["J_exact"] == "float"
    assert kinds["stable_certified"] == kinds["eps_A"] == "bool" and "rmse_B" not in kinds
    got = results_store.unit_columns(result).columns
    values = result.value_columns()
    for f in RESULT_SCALAR_FIELDS:
        want = [results_store._clean_scalar(f, v) for v in values[f]]
        assert bits(got[f]) == bits(want), f
