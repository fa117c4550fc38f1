"""REST datasets (service/api/routes/datasets.py) on SQLite and PostgreSQL: the same
rollouts uploaded in five formats are stored as the same float64 arrays (bit for
bit); every kind of bad file is one named 422 leaving no row and no chunk; the size
limit is a 413 whether declared or streamed; team scoping, pagination, delete and
its 409 while jobs use the dataset, the download's bytes."""

from __future__ import annotations

import hashlib
import io
import re
import uuid
from urllib.parse import unquote

import numpy as np
import pytest
from sqlalchemy import func, select, update

from service.db import datasets as store
from service.db import jobs as job_store
from service.db.models import Dataset, DatasetChunk, Job
from service.http.security import attachment
from svrobs_core import parse_spec
from svrobs_core.errors import SpecError
from svrobs_lab.datasets.catalog import resolve_dataset
from svrobs_lab.errors import DatasetNotFound
from tests.datasets import bad_files, files
from tests.service.svc_helpers import SMALL_SPEC

API = "/api/v1"


def upload(client, acc, filename: str, data: bytes, **fields):
    form = {"name": f"ds-{uuid.uuid4().hex[:6]}", **fields}
    return client.post(
        f"{API}/datasets", files={"file": (filename, data)}, data=form, headers=acc.headers
    )


def counts(session) -> tuple[int, int]:
    session.expire_all()
    return (
        session.scalar(select(func.count()).select_from(Dataset)),
        session.scalar(select(func.count()).select_from(DatasetChunk)),
    )


def test_five_formats_store_the_same_arrays_and_the_original_bytes(
    client, session, make_account, tmp_path
):
    acc = make_account()
    X, U = files.rollouts(lengths=(6, 2, 9), n=3, m=2)
    bodies = {}
    for fmt, (name, data) in files.all_formats(X, U, tmp_path).items():
        r = upload(client, acc, name, data, sample_time="0.25", description="bench run")
        assert r.status_code == 201, r.text
        body = bodies[fmt] = r.json()
        assert r.headers["location"] == f"{API}/datasets/{body['id']}"
        assert body["format"] == fmt and body["sha256"] == hashlib.sha256(data).hexdigest()
        assert (body["n"], body["m"], body["rollouts"], body["lengths"]) == (3, 2, 3, [6, 2, 9])
        assert (body["samples"], body["T_min"], body["T_max"]) == (17, 2, 9)
        assert body["sample_time"] == 0.25 and body["size_bytes"] == len(data)
        assert body["filename"] == name and body["owner"] == acc.user.email
        # the arrays a worker loads: the file's numbers, bit for bit, without parsing it
        Xs, Us, meta = store.load_arrays(session, body["id"])
        assert [x.tobytes() for x in Xs] == [x.tobytes() for x in X]
        assert [u.tobytes() for u in Us] == [u.tobytes() for u in U]
        assert meta["lengths"] == [6, 2, 9] and meta["sha256"] == body["sha256"]
        # the download is the upload, byte for byte, with its media type and name
        d = client.get(f"{API}/datasets/{body['id']}/file", headers=acc.headers)
        assert d.status_code == 200 and d.content == data
        assert d.headers["content-type"].startswith(body["media_type"])
        assert f'filename="{name}"' in d.headers["content-disposition"]
        assert d.headers["etag"] == f'"{body["sha256"]}"'
    assert len({b["arrays_sha256"] for b in bodies.values()}) == 1
    assert len({b["sha256"] for b in bodies.values()}) == 5
    stacked = np.vstack(U)
    stats = bodies["csv"]["stats"]["inputs"]["u2"]
    assert stats["mean"] == pytest.approx(stacked[:, 1].mean(), rel=1e-14)
    assert (stats["min"], stats["max"]) == (stacked[:, 1].min(), stacked[:, 1].max())


def test_no_inputs_end_to_end(client, session, make_account):
    acc = make_account()
    X, U = files.rollouts(lengths=(5, 8), n=2, m=0)
    r = upload(client, acc, "auto.csv", files.csv_bytes(X, U))
    assert r.status_code == 201, r.text
    assert (
        r.json()["m"] == 0 and r.json()["input_names"] == [] and r.json()["stats"]["inputs"] == {}
    )
    Xs, Us, _ = store.load_arrays(session, r.json()["id"])
    assert [u.shape for u in Us] == [(5, 0), (8, 0)]
    assert [x.tobytes() for x in Xs] == [x.tobytes() for x in X]


def _npz(**arrays) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


_X3 = files.rollouts(seed=5, lengths=(4, 3), n=1, m=0)[0]
_NPZ = files.npz_bytes(_X3, [np.zeros((len(x) - 1, 0)) for x in _X3])
_NAME_RULE = r"a name is 1 to 64 printable characters$"
# text that UTF-8 cannot encode (a lone surrogate) or too deep or too long to read
UNREADABLE = [
    (
        "json-surrogate-name",
        "d.json",
        b'{"X": [[[1], [2]]], "state_names": ["\\ud800"]}',
        {},
        "file",
        r"^state_names: '\\ud800': " + _NAME_RULE,
    ),
    (
        "npz-surrogate-name",
        "d.npz",
        _npz(X=np.zeros((1, 3, 1)), state_names=np.array(["\ud800"])),
        {},
        "file",
        r"^state_names: '\\ud800': " + _NAME_RULE,
    ),
    (
        "field-surrogate-name",
        "d.npz",
        _NPZ,
        {"state_names": '["\\ud800"]'},
        "state_names",
        r"^'\\ud800': " + _NAME_RULE,
    ),
    (
        "field-surrogate-column",
        "d.csv",
        bad_files.GOOD_CSV.replace(b"x3", b"x3\xe9", 1),  # not UTF-8: read as x3\udce9
        {"state_columns": '["x1", "x2", "x3\\udce9"]'},
        "state_columns",
        r"^'x3\\udce9': " + _NAME_RULE,
    ),
    (
        "npz-long-name-cut",
        "d.npz",
        _npz(X=np.zeros((1, 3, 1)), state_names=np.array(["a" * 200_000])),
        {},
        "file",
        r"^state_names: 'a{80}'\.\.\. \(cut, 200,000 characters\): " + _NAME_RULE,
    ),
    (
        "csv-long-column-cut",
        "d.csv",
        bad_files.GOOD_CSV,
        {"state_columns": '["%s"]' % ("c" * 100_000)},
        "state_columns",
        r"^no column 'c{80}'\.\.\. \(cut, 100,000 characters\) in the file's header",
    ),
    (
        "json-integer-too-long-in-X",
        "d.json",
        b'{"X": [[[%s], [1]]]}' % (b"1" * 5000),
        {},
        "file",
        r"^an integer of more than [0-9,]+ digits",
    ),
    (
        "json-integer-too-long-sample-time",
        "d.json",
        b'{"X": [[[1], [2]]], "sample_time": %s}' % (b"1" * 5000),
        {},
        "file",
        r"^an integer of more than [0-9,]+ digits",
    ),
] + [
    (f"field-{key}-nested", "d.csv", bad_files.GOOD_CSV, {key: "[" * 100_000}, key, r"^not a JSON")
    for key in ("state_columns", "input_columns", "state_names", "input_names")
]
# a dataset's name and description are printable text (svrobs_core/text.py): no C1
# control (U+009B starts a terminal escape sequence) nor U+2028/U+2029 (which split lines)
_PRINTABLE_RULE = r"^must be printable text"
UNPRINTABLE_FIELDS = [
    (f"field-{key}-{cid}", "d.csv", bad_files.GOOD_CSV, {key: text}, key, _PRINTABLE_RULE)
    for key in ("name", "description")
    for cid, text in (
        ("c1", "run \x9b2J"),
        ("line-separator", "a\u2028b"),
        ("paragraph-separator", "a\u2029b"),
    )
]
BAD = bad_files.cases() + UNREADABLE + UNPRINTABLE_FIELDS


@pytest.mark.parametrize("case", BAD, ids=[c[0] for c in BAD])
def test_each_bad_file_is_one_named_422_and_stores_nothing(client, session, make_account, case):
    cid, name, data, fields, field, pattern = case
    acc = make_account()
    before = counts(session)
    r = upload(client, acc, name, data, **fields)
    body = r.json()
    assert r.status_code == 422, (cid, r.text)
    assert body["field"] == field, (cid, body)
    assert re.search(pattern, body["detail"]), (cid, body["detail"])
    assert "Traceback" not in r.text
    assert counts(session) == before, cid  # no dataset row, no chunk


def test_bad_file_kinds_are_at_least_fifteen():
    kinds = {c[0] for c in BAD if c[4] == "file"}
    assert len(kinds) >= 15


def test_a_download_holds_no_database_session_between_its_chunks(
    client, session_factory, make_account
):
    """The file is sent chunk by chunk, each read in a short session: while the client
    has not taken a chunk, no session of the download is open (one session for the
    whole download held a pooled connection for as long as the slowest client took:
    sixteen stalled downloads made every other team's GET a 503 after 30 s)."""
    from svrobs_lab.datasets.catalog import file_chunks
    from tests.service.svc_helpers import track_sessions

    acc = make_account()
    rng = np.random.default_rng(1)
    data = _npz(X=rng.standard_normal((4, 20_001, 3)), U=rng.standard_normal((4, 20_000, 2)))
    assert len(data) > 2 * store.CHUNK_BYTES
    made = upload(client, acc, "big.npz", data)
    assert made.status_code == 201, made.text
    opened = track_sessions(client.app, session_factory)
    chunks = file_chunks(client.app.state.session_factory, made.json()["id"])
    got = []
    for chunk in chunks:
        assert not any(s.in_transaction() for s in opened), len(got)
        got.append(chunk)
    assert b"".join(got) == data and len(got) >= 3
    whole = client.get(f"{API}/datasets/{made.json()['id']}/file", headers=acc.headers)
    assert whole.status_code == 200 and whole.content == data


def test_size_limit_is_a_413_declared_or_streamed(build_client, session, make_account):
    client, _ = build_client(MAX_DATASET_MB=1)
    acc = make_account()
    X, U = files.rollouts(lengths=(12000,), n=3, m=2)
    data = files.csv_bytes(X, U)
    assert len(data) > 2**20
    before = counts(session)
    r = upload(client, acc, "big.csv", data)
    assert r.status_code == 413 and r.json()["field"] == "file"
    assert "SVROBS_MAX_DATASET_MB" in r.json()["detail"]
    # without a Content-Length: the body is counted as it streams
    boundary = "b0undary"
    head = (
        f'--{boundary}\r\nContent-Disposition: form-data; name="name"\r\n\r\nbig\r\n'
        f'--{boundary}\r\nContent-Disposition: form-data; name="file"; filename="big.csv"\r\n'
        "Content-Type: text/csv\r\n\r\n"
    ).encode()
    tail = f"\r\n--{boundary}--\r\n".encode()

    def body():
        yield head
        for i in range(0, len(data), 65536):
            yield data[i : i + 65536]
        yield tail

    r = client.post(
        f"{API}/datasets",
        content=body(),
        headers={**acc.headers, "Content-Type": f"multipart/form-data; boundary={boundary}"},
    )
    assert r.status_code == 413 and r.json()["field"] == "file"
    assert counts(session) == before
    # under the limit the same streamed encoding is stored
    small = files.csv_bytes(*files.rollouts(lengths=(5,)))
    data = small
    r = client.post(
        f"{API}/datasets",
        content=body(),
        headers={**acc.headers, "Content-Type": f"multipart/form-data; boundary={boundary}"},
    )
    assert r.status_code == 201, r.text
    assert r.json()["sha256"] == hashlib.sha256(small).hexdigest()


def test_a_description_may_hold_tabs_and_line_breaks(client, make_account):
    acc = make_account()
    text = "bench run\tday 2\r\nsecond line"
    r = upload(client, acc, "d.csv", bad_files.GOOD_CSV, description=text)
    assert r.status_code == 201 and r.json()["description"] == text, r.text


def _upload_named(client, acc, filename: str):
    """An upload whose multipart header names the file ``filename`` as it is."""
    body = (
        (
            '--b0\r\nContent-Disposition: form-data; name="name"\r\n\r\nd\r\n'
            f'--b0\r\nContent-Disposition: form-data; name="file"; filename="{filename}"\r\n\r\n'
        ).encode()
        + files.csv_bytes(*files.rollouts(lengths=(5,)))
        + b"\r\n--b0--\r\n"
    )
    headers = {**acc.headers, "Content-Type": "multipart/form-data; boundary=b0"}
    return client.post(f"{API}/datasets", content=body, headers=headers)


def test_an_uploaded_file_name_is_kept_without_unprintable_characters(client, make_account):
    """The file name is shown in listings and terminals: its tabs, line breaks, C1
    controls and U+2028/U+2029 are dropped at upload, as its folders are."""
    acc = make_account()
    up = _upload_named(client, acc, "runs\\a\tb\x9bc\u2028d\u2029e\x1b[0m.csv")
    assert up.status_code == 201 and up.json()["filename"] == "abcde[0m.csv", up.text
    d = client.get(f"{API}/datasets/{up.json()['id']}", headers=acc.headers)
    assert d.json()["filename"] == "abcde[0m.csv"


def test_a_downloads_file_name_cannot_split_its_header(client, make_account):
    """The file name a download is saved under is the uploader's, kept without its LF
    (a multipart header may hold one): no LF, quote, semicolon or path reaches the
    header; RFC 6266: the name in ``filename*`` (UTF-8), an ASCII fallback."""
    acc = make_account()
    up = _upload_named(client, acc, "x\nSet-Cookie: s=1;r\u00e9sum\u00e9.csv")
    kept = "xSet-Cookie: s=1;r\u00e9sum\u00e9.csv"
    assert up.status_code == 201 and up.json()["filename"] == kept, up.text
    d = client.get(f"{API}/datasets/{up.json()['id']}/file", headers=acc.headers)
    value = d.headers["content-disposition"]
    assert value.isascii() and value.isprintable()
    fallback, star = (
        "xSet-Cookie_ s=1_r_sum_.csv",
        "xSet-Cookie%3A%20s%3D1%3Br%C3%A9sum%C3%A9.csv",
    )
    assert value == f"attachment; filename=\"{fallback}\"; filename*=UTF-8''{star}"
    assert unquote(star) == kept
    for name, saved in (("..", "download"), ('a"b\\c/d', "a_b_c_d"), ("\ud800.x", "_.x")):
        assert attachment(name).startswith(f'attachment; filename="{saved}"; ')


@pytest.mark.parametrize("name", ["a\r\nb", "a\x1b\x9bb", "a\u2028\u2029b"])
def test_a_downloads_file_name_holds_only_printable_text(name):
    """Whatever name a download is given: the characters no name holds
    (svrobs_core/text.py) become ``_`` in ``filename*`` as in the fallback."""
    assert attachment(name) == "attachment; filename=\"a__b\"; filename*=UTF-8''a__b"


def test_not_multipart_and_no_file(client, make_account):
    acc = make_account()
    r = client.post(f"{API}/datasets", json={"name": "x"}, headers=acc.headers)
    assert r.status_code == 422 and r.json()["field"] == "file"
    r = client.post(
        f"{API}/datasets", data={"name": "x"}, files={"other": ("a", b"1")}, headers=acc.headers
    )
    assert r.status_code == 422
    r = client.post(
        f"{API}/datasets", files={"name": (None, "x"), "file": (None, "text")}, headers=acc.headers
    )
    assert r.status_code == 422 and r.json()["field"] == "file"
    assert client.post(f"{API}/datasets", files={"file": ("a.csv", b"x")}).status_code == 401


def test_team_scoping_listing_and_delete(client, session, make_account):
    a, b = make_account(), make_account()
    data = files.csv_bytes(*files.rollouts(lengths=(3, 4)))
    ids = [upload(client, a, "a.csv", data, name=f"a{i}").json()["id"] for i in range(3)]
    other = upload(client, b, "b.csv", data).json()["id"]
    page = client.get(f"{API}/datasets", params={"limit": 2}, headers=a.headers).json()
    assert page["total"] == 3 and [d["id"] for d in page["items"]] == ids[::-1][:2]
    assert "lengths" not in page["items"][0] and "stats" not in page["items"][0]
    rest = client.get(f"{API}/datasets", params={"limit": 2, "offset": 2}, headers=a.headers)
    assert [d["id"] for d in rest.json()["items"]] == [ids[0]]
    for path in (f"/datasets/{other}", f"/datasets/{other}/file"):
        r = client.get(f"{API}{path}", headers=a.headers)
        assert r.status_code == 404 and r.json()["detail"] == f"dataset {other} not found"
    assert client.delete(f"{API}/datasets/{other}", headers=a.headers).status_code == 404
    assert client.get(f"{API}/datasets/{other}", headers=b.headers).status_code == 200
    assert (
        client.get(f"{API}/datasets/+{ids[0]}", headers=a.headers).json()["field"] == "dataset_id"
    )
    r = client.delete(f"{API}/datasets/{ids[0]}", headers=a.headers)
    assert r.status_code == 204
    session.expire_all()
    chunks = select(func.count()).select_from(DatasetChunk).where(DatasetChunk.dataset_id == ids[0])
    assert session.scalar(chunks) == 0
    assert client.get(f"{API}/datasets/{ids[0]}", headers=a.headers).status_code == 404
    with pytest.raises(DatasetNotFound) as err:
        resolve_dataset(session, a.team.id, other)
    assert err.value.field == "dataset"
    assert resolve_dataset(session, b.team.id, other).id == other


def test_delete_is_a_409_naming_the_jobs_that_use_it(client, session, make_account):
    acc = make_account()
    ds = upload(client, acc, "a.csv", files.csv_bytes(*files.rollouts(lengths=(3, 4)))).json()
    jobs = [
        client.post(f"{API}/jobs", json=SMALL_SPEC, headers=acc.headers).json()["id"]
        for _ in range(2)
    ]
    session.execute(update(Job).where(Job.id.in_(jobs)).values(dataset_id=ds["id"]))
    session.commit()
    r = client.delete(f"{API}/datasets/{ds['id']}", headers=acc.headers)
    assert r.status_code == 409
    assert (
        r.json()["detail"]
        == f"dataset {ds['id']} is used by jobs {jobs[0]}, {jobs[1]}: delete them first"
    )
    assert counts(session)[0] >= 1 and store.team_dataset(session, acc.team.id, ds["id"])
    for j in jobs:
        assert client.post(f"{API}/jobs/{j}/cancel", headers=acc.headers).status_code == 200
        assert client.delete(f"{API}/jobs/{j}", headers=acc.headers).status_code == 204
    assert client.delete(f"{API}/datasets/{ds['id']}", headers=acc.headers).status_code == 204


def test_delete_is_a_409_naming_the_schedules_that_run_on_it(client, make_account):
    """A schedule's template that names the dataset keeps it, as a job does: its next
    run would otherwise find no data (or, had ids been reused, another dataset)."""
    acc = make_account()
    ds = upload(client, acc, "a.csv", files.csv_bytes(*files.rollouts(lengths=(3, 4)))).json()
    template = {"dataset": ds["id"], "N": [1], "holdout": 1, "reps": 1, "sigma_w": 0.2}
    sids = [
        client.post(
            f"{API}/schedules",
            headers=acc.headers,
            json={"name": name, "cron": "0 2 * * *", "spec_template": template},
        ).json()["id"]
        for name in ("nightly", "hourly")
    ]
    r = client.delete(f"{API}/datasets/{ds['id']}", headers=acc.headers)
    assert r.status_code == 409
    assert r.json()["detail"] == (
        f"dataset {ds['id']} is named by schedules 'hourly', 'nightly': change or delete them first"
    )
    assert client.get(f"{API}/datasets/{ds['id']}", headers=acc.headers).status_code == 200
    for sid in sids:
        assert client.delete(f"{API}/schedules/{sid}", headers=acc.headers).status_code == 204
    assert client.delete(f"{API}/datasets/{ds['id']}", headers=acc.headers).status_code == 204


def test_a_spec_names_the_teams_dataset(client, session, make_account):
    """create_job links a job to its spec's dataset, refuses another team's and checks
    the spec against the dataset's shape (the store check every path to create_job
    goes through)."""
    a, b = make_account(), make_account()
    data = files.csv_bytes(*files.rollouts(lengths=(3, 4)))
    mine = upload(client, a, "a.csv", data).json()["id"]
    theirs = upload(client, b, "b.csv", data).json()["id"]
    assert store.linked_dataset(session, a.team.id, {"dataset": mine}) == mine
    assert store.linked_dataset(session, a.team.id, {"systems": ["paper-stable"]}) is None
    with pytest.raises(DatasetNotFound) as err:
        store.linked_dataset(session, a.team.id, {"dataset": theirs})
    assert err.value.field == "dataset" and err.value.message == f"no dataset {theirs} in your team"
    spec = {"dataset": mine, "N": [1, 2], "reps": 1, "sigma_w": 0.1}
    assert store.linked_dataset(session, a.team.id, parse_spec(spec)) == mine
    with pytest.raises(SpecError) as err:  # 2 rollouts, 1 held out: N = 2 is too many
        store.linked_dataset(session, a.team.id, parse_spec({**spec, "holdout": 1}))
    assert err.value.field == "N" and "the dataset has 1 for training" in err.value.message
    with pytest.raises(DatasetNotFound):
        job_store.create_job(
            session, team_id=a.team.id, user_id=None, spec={**spec, "dataset": theirs}
        )
    job, _ = job_store.create_job(session, team_id=a.team.id, user_id=None, spec=spec)
    assert job.dataset_id == mine and job.spec_summary["systems"] == [f"dataset-{mine}"]
    assert job.n_cells == parse_spec(spec).n_cells == 2 * 1 * 2  # N x reps x (ols, svr)


def test_a_malformed_multipart_body_is_a_422_naming_the_body(client, make_account):
    """A system file's form (parsed by FastAPI) and a dataset upload (streamed) both
    answer a multipart body that does not parse with one 422."""
    acc = make_account()
    bad = b"--b0\r\nK\xc2\x97--b0--\r\n"
    headers = {**acc.headers, "Content-Type": "multipart/form-data; boundary=b0"}
    r = client.post(f"{API}/systems/from-file", content=bad, headers=headers)
    assert r.status_code == 422 and r.json()["field"] == "body", r.text
    assert r.json()["detail"].startswith("not valid multipart/form-data: ")
    r = client.post(f"{API}/datasets", content=bad, headers=headers)
    assert r.status_code == 422 and r.json()["field"] == "file", r.text
