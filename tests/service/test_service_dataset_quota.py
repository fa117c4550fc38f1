"""A team's datasets under quota (docs/datasets.md#limits), on SQLite and PostgreSQL:
the count and the stored bytes (upload + float64 arrays, recomputed here from the
files) are capped per team, a refused upload is one 422 naming the setting and
stores nothing; uploads being read are bounded per team and per process (429 with
Retry-After); the excitation check is made once, at upload, and the page shows it
without reading the arrays."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from sqlalchemy import update

from service.db.models import Dataset
from svrobs_lab.auth import Caller
from svrobs_lab.datasets import overview
from svrobs_lab.datasets.upload_slots import UploadSlots
from svrobs_lab.errors import RateLimited
from tests.datasets import files
from tests.service.test_service_datasets import API, counts, upload

MB = 2**20


def held(X, U, data: bytes) -> int:
    """What a dataset holds: its file and its arrays as float64, counted here."""
    return len(data) + 8 * (sum(x.size for x in X) + sum(u.size for u in U))


def test_a_teams_dataset_count_is_capped(build_client, session, make_account):
    client, _ = build_client(MAX_DATASETS_PER_TEAM=2)
    acc, other = make_account(), make_account()
    data = files.csv_bytes(*files.rollouts())
    made = [upload(client, acc, "r.csv", data) for _ in range(2)]
    assert [r.status_code for r in made] == [201, 201]
    before = counts(session)
    r = upload(client, acc, "r.csv", data)
    assert r.status_code == 422 and r.json()["field"] == "file", r.text
    assert "2 datasets" in r.json()["detail"]
    assert "SVROBS_MAX_DATASETS_PER_TEAM" in r.json()["detail"]
    assert counts(session) == before
    # another team counts its own
    assert upload(client, other, "r.csv", data).status_code == 201
    # deleting one makes room for one
    first = made[0].json()["id"]
    assert client.delete(f"{API}/datasets/{first}", headers=acc.headers).status_code == 204
    assert upload(client, acc, "r.csv", data).status_code == 201
    assert upload(client, acc, "r.csv", data).status_code == 422


def test_a_teams_stored_bytes_are_capped(build_client, session, make_account):
    client, _ = build_client(MAX_TEAM_DATASETS_MB=1)
    acc = make_account()
    big_X, big_U = files.rollouts(seed=4, lengths=(5000,), n=3, m=2)
    big = files.csv_bytes(big_X, big_U)
    small_X, small_U = files.rollouts(seed=5, lengths=(5,))
    small = files.csv_bytes(small_X, small_U)
    one = held(big_X, big_U, big)
    assert one <= MB < 2 * one and one + held(small_X, small_U, small) <= MB
    assert upload(client, acc, "big.csv", big).status_code == 201
    before = counts(session)
    r = upload(client, acc, "big.csv", big)
    assert r.status_code == 422 and r.json()["field"] == "file", r.text
    detail = r.json()["detail"]
    assert f"hold {one / MB:,.1f} MB" in detail and f"add {one / MB:,.1f} MB" in detail
    assert "the limit is 1 MB (SVROBS_MAX_TEAM_DATASETS_MB)" in detail
    assert counts(session) == before
    # what still fits is stored
    assert upload(client, acc, "small.csv", small).status_code == 201


def test_no_cap_when_the_settings_are_zero(build_client, make_account):
    client, _ = build_client(MAX_DATASETS_PER_TEAM=0, MAX_TEAM_DATASETS_MB=0)
    acc = make_account()
    data = files.csv_bytes(*files.rollouts())
    assert [upload(client, acc, "r.csv", data).status_code for _ in range(3)] == [201] * 3


def test_upload_slots_per_team_and_in_all():
    slots = UploadSlots(per_team=2, at_once=3)
    with slots.hold(1), slots.hold(1):
        with pytest.raises(RateLimited, match="SVROBS_UPLOADS_PER_TEAM"):
            with slots.hold(1):
                pass
        with slots.hold(2):
            with pytest.raises(RateLimited, match="SVROBS_UPLOADS_AT_ONCE") as busy:
                with slots.hold(3):
                    pass
            assert busy.value.retry_after >= 1
    # every slot is given back, also by a block that raised
    with pytest.raises(ValueError):
        with slots.hold(1):
            raise ValueError
    with slots.hold(1), slots.hold(1), slots.hold(2):
        pass


def test_upload_slots_hold_under_threads():
    slots = UploadSlots(per_team=3, at_once=100)
    inside, peak, lock = [0], [0], threading.Lock()
    refused = []
    go = threading.Barrier(12)

    def one():
        go.wait(5)
        try:
            with slots.hold(7):
                with lock:
                    inside[0] += 1
                    peak[0] = max(peak[0], inside[0])
                threading.Event().wait(0.05)
                with lock:
                    inside[0] -= 1
        except RateLimited:
            refused.append(1)

    threads = [threading.Thread(target=one) for _ in range(12)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    assert peak[0] <= 3 and len(refused) >= 1 and inside[0] == 0


def test_an_upload_without_a_free_slot_is_a_429(build_client, session, make_account):
    client, _ = build_client(UPLOADS_PER_TEAM=1)
    acc, other = make_account(), make_account()
    data = files.csv_bytes(*files.rollouts())
    before = counts(session)
    with client.app.state.upload_slots.hold(acc.team.id):
        r = upload(client, acc, "r.csv", data)
        assert r.status_code == 429 and int(r.headers["Retry-After"]) >= 1, r.text
        assert "SVROBS_UPLOADS_PER_TEAM" in r.json()["detail"]
        assert counts(session) == before
        assert upload(client, other, "r.csv", data).status_code == 201  # another team's
    assert upload(client, acc, "r.csv", data).status_code == 201


def test_the_excitation_check_is_made_at_upload(client, session, make_account, monkeypatch):
    acc = make_account()
    X, U = files.rollouts(seed=6, lengths=(30, 45), n=2, m=1)
    r = upload(client, acc, "e.csv", files.csv_bytes(X, U))
    assert r.status_code == 201, r.text
    stored = r.json()["excitation"]
    # oracle: the eigenvalues of the mean Gram of z = [x_k; u_k] over every transition
    Z = np.vstack([np.hstack([x[:-1], u]) for x, u in zip(X, U)])
    lam = np.linalg.eigvalsh(Z.T @ Z / len(Z))
    np.testing.assert_allclose(stored["eigenvalues"], lam, rtol=1e-10)
    assert stored["N0"] == len(Z) and stored["cond"] == pytest.approx(lam[-1] / lam[0])
    got = client.get(f"{API}/datasets/{r.json()['id']}", headers=acc.headers).json()
    assert got["excitation"] == stored
    # the page shows the stored check: the arrays are not read for it
    caller = Caller(key_id=acc.key_row.id, team_id=acc.team.id, user_id=None, is_admin=False)

    def no_read(*a, **k):
        raise AssertionError("the arrays were read")

    with monkeypatch.context() as m:
        m.setattr(overview, "measured_data", no_read)
        assert overview.dataset_overview(session, caller, got["id"])["excitation"] == stored
    # a dataset stored before the check was: made on view, the same numbers
    session.execute(update(Dataset).where(Dataset.id == got["id"]).values(excitation=None))
    session.commit()
    again = overview.dataset_overview(session, caller, got["id"])["excitation"]
    np.testing.assert_allclose(again["eigenvalues"], stored["eigenvalues"], rtol=1e-12)
