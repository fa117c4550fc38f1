"""A job's live share links are capped (SVROBS_MAX_SHARES_PER_JOB, docs/security.md):
one more is a 422 naming the setting and the cap; revoked and expired links do not
count."""

from __future__ import annotations

from datetime import timedelta

from sqlalchemy import func, select, update

from service.db.models import ShareLink, utcnow
from tests.service.svc_helpers import TINY_SPEC

API = "/api/v1"


def test_a_jobs_live_share_links_are_capped(build_client, session, make_account):
    client, _ = build_client(MAX_SHARES_PER_JOB=3)
    acc = make_account()
    jid = client.post(f"{API}/jobs", json=TINY_SPEC, headers=acc.headers).json()["id"]

    def share():
        return client.post(f"{API}/jobs/{jid}/shares", json={"days": 1}, headers=acc.headers)

    made = [share() for _ in range(3)]
    assert [r.status_code for r in made] == [201] * 3, [r.text for r in made]
    r = share()
    assert r.status_code == 422, r.text
    assert "the limit is 3 (SVROBS_MAX_SHARES_PER_JOB)" in r.json()["detail"], r.text
    assert session.scalar(select(func.count(ShareLink.id))) == 3
    # a revoked link does not count
    revoked = made[0].json()["id"]
    assert client.delete(f"{API}/shares/{revoked}", headers=acc.headers).status_code == 204
    assert share().status_code == 201
    assert share().status_code == 422
    # nor does an expired one
    expired = made[1].json()["id"]
    gone = update(ShareLink).where(ShareLink.id == expired)
    session.execute(gone.values(expires_at=utcnow() - timedelta(seconds=1)))
    session.commit()
    assert share().status_code == 201
    assert share().status_code == 422
