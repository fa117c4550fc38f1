"""The svrobs REST client: one :class:`httpx.Client` per :class:`Client`.

Covers the routes of ``/api/v1`` (README, "API"): the HTTP calls every route goes
through, jobs, share links, presets and schedules here; results, summaries,
comparisons and reports in :mod:`svrobs_client.results`; datasets, model exports and
system files in :mod:`svrobs_client.datasets`. HTTP errors are raised as the typed
exceptions of :mod:`svrobs_client.errors`; results come as pandas DataFrames (the
``dataframe`` extra) or as plain dicts.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx

from .config import resolve
from .datasets import DatasetCalls
from .errors import (
    ConnectionFailed,
    Unavailable,
    ValidationError,
    WaitTimeout,
    error_from_response,
    not_the_api,
    unreachable,
)
from .models import Job, JobPage, Schedule, ScheduleRun, Share, answer, ident
from .params import RESULT_FILTERS
from .progress import make_bar
from .results import ResultCalls

__all__ = ["Client", "RESULT_FILTERS", "SEED_POLICIES"]

API = "/api/v1"
PAPER_PRESET = "paper-section-6"
SEED_POLICIES = ("fixed", "due-time")


def _load_json(spec: object) -> dict[str, Any]:
    """A spec given as a mapping, a Job (its spec), or a path to a JSON file."""
    if isinstance(spec, Job):
        return dict(spec.spec)
    if isinstance(spec, Mapping):
        return dict(spec)
    if isinstance(spec, (str, os.PathLike)):
        try:
            data = json.loads(Path(spec).read_text(encoding="utf-8"))
        except UnicodeDecodeError:
            raise ValueError(f"{spec}: not a JSON file (not UTF-8 text)") from None
        except (ValueError, RecursionError) as exc:  # RecursionError: nested too deeply
            raise ValueError(f"{spec}: not valid JSON: {exc}") from None
        if not isinstance(data, dict):
            raise ValueError(f"{spec}: the spec must be a JSON object")
        return data
    raise TypeError(f"a spec is a dict or a path to a JSON file, got {type(spec).__name__}")


def json_body(value: Any) -> bytes:
    """A request body as JSON: numpy numbers and arrays as plain numbers and lists; a NaN
    or infinity anywhere is a :class:`ValidationError` naming where it is (JSON has
    none; the API refuses the same value with the same message)."""
    try:
        return json.dumps(value, allow_nan=False, default=_plain).encode("utf-8")
    except ValueError:
        where = _non_finite(json.loads(json.dumps(value, default=_plain)))
        if where is None:  # not a NaN (a circular reference): the encoder's own error
            raise
        raise ValidationError("must be finite (no NaN or inf)", field=where) from None


def _plain(value: Any) -> Any:
    tolist = getattr(value, "tolist", None)  # numpy scalars and arrays
    if callable(tolist):
        return tolist()
    raise TypeError(f"{type(value).__name__} is not JSON: give numbers, text, lists or dicts")


def _non_finite(value: Any, path: str = "") -> str | None:
    """The path (``sigma_w[0]``, ``sls.C_bound``) of the first NaN or infinity."""
    if isinstance(value, float):
        return None if math.isfinite(value) else path or None
    if isinstance(value, dict):
        pairs = [(f"{path}.{k}" if path else str(k), v) for k, v in value.items()]
    elif isinstance(value, list):
        pairs = [(f"{path}[{k}]", v) for k, v in enumerate(value)]
    else:
        return None
    return next((w for p, v in pairs if (w := _non_finite(v, p)) is not None), None)


def _idempotency(key: str | None) -> dict[str, str]:
    """The Idempotency-Key header; a ValidationError naming it for text no HTTP header
    can carry (not printable ASCII)."""
    if not key:
        return {}
    if not (key.isascii() and key.isprintable()):
        raise ValidationError(
            "must be printable ASCII (an HTTP header carries nothing else)",
            field="Idempotency-Key",
        )
    return {"Idempotency-Key": key}


def _answers(headers: httpx.Headers, expect: str) -> bool:
    """Whether an answer is what the API sends: a file (``"attachment"``) or a body of
    the content type ``expect``."""
    if expect == "attachment":
        return str(headers.get("content-disposition", "")).startswith("attachment")
    return expect in str(headers.get("content-type", ""))


def _check_seed_policy(policy: object) -> None:
    if policy not in SEED_POLICIES:
        raise ValueError(f"seed_policy must be 'fixed' or 'due-time', got {policy!r}")


class Client(ResultCalls, DatasetCalls):
    """A client of one svrobs server.

    ``url`` and ``key`` default to ``SVROBS_URL`` / ``SVROBS_API_KEY``, then to the
    config file (``~/.config/svrobs/config.json``, ``{"url", "api_key"}``), as the CLI
    does. Use it as a context manager (or call :meth:`close`)::

        with Client() as c:
            job = c.submit({"systems": ["paper-stable"], "sigma_w": [1.0], "N": [50]})
            df = c.results(job, estimator="svr")
    """

    def __init__(
        self,
        url: str | None = None,
        key: str | None = None,
        *,
        timeout: float = 30.0,
        poll_interval: float = 1.0,
    ):
        self.url, key = resolve(url, key)
        self.poll_interval = poll_interval
        self._http = httpx.Client(
            base_url=self.url + API,
            timeout=timeout,
            headers={"Authorization": f"Bearer {key}", "User-Agent": "svrobs-client/0.1"},
        )

    def __repr__(self) -> str:  # never shows the key
        return f"Client({self.url!r})"

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ HTTP
    def _check(self, r: httpx.Response, *, data: bool) -> None:
        """The typed error of an HTTP error status; a :class:`SvrobsError` for a redirect,
        or with ``data`` for an HTML page (answers of a server that is not the API)."""
        if r.status_code >= 400:
            r.read()
            raise error_from_response(r.status_code, r.content, r.headers, url=self.url)
        if 300 <= r.status_code < 400 or (data and "html" in r.headers.get("content-type", "")):
            raise not_the_api(self.url, r.status_code, r.headers)

    def request(self, method: str, path: str, **kw: Any) -> httpx.Response:
        """One request under ``/api/v1``; a typed :class:`SvrobsError` for any HTTP error
        status or a redirect, :class:`ConnectionFailed` when the server cannot be reached."""
        if "json" in kw:  # encoded here: numpy numbers plain, a NaN named (not httpx's)
            kw["content"] = json_body(kw.pop("json"))
            kw["headers"] = {**kw.get("headers", {}), "Content-Type": "application/json"}
        try:
            r = self._http.request(method, path, **kw)
        except httpx.HTTPError as exc:
            raise unreachable(self.url, exc) from None
        self._check(r, data=False)
        return r

    def request_json(self, method: str, path: str, **kw: Any) -> Any:
        """:meth:`request`, and its JSON body; a :class:`SvrobsError` when the body is not
        JSON (the server is not the API)."""
        r = self.request(method, path, **kw)
        if "json" not in r.headers.get("content-type", ""):
            raise not_the_api(self.url, r.status_code, r.headers)
        try:
            return r.json()
        except ValueError:
            raise not_the_api(self.url, r.status_code, r.headers) from None

    @contextmanager
    def _stream(
        self, path: str, params: dict[str, Any], *, expect: str | None = None
    ) -> Iterator[httpx.Response]:
        """A streamed GET of data (records, a file): errors as :meth:`request`'s, an HTML
        page too, and an answer whose content type lacks ``expect`` (``"attachment"``:
        a file without the API's Content-Disposition); a connection lost mid-answer is
        :class:`ConnectionFailed` saying so."""
        answered = False
        try:
            with self._http.stream("GET", path, params=params) as r:
                self._check(r, data=True)
                if expect is not None and not _answers(r.headers, expect):
                    raise not_the_api(self.url, r.status_code, r.headers)
                answered = True
                yield r
        except httpx.HTTPError as exc:
            if not answered:
                raise unreachable(self.url, exc) from None
            raise ConnectionFailed(f"lost the connection to {self.url}: {exc}") from None

    # ------------------------------------------------------------------ jobs
    def submit(
        self,
        spec: Mapping[str, Any] | str | os.PathLike[str],
        *,
        name: str | None = None,
        tags: Sequence[str] = (),
        idempotency_key: str | None = None,
        wait: bool = True,
        progress: bool = True,
        timeout: float | None = None,
    ) -> Job:
        """Submit a spec (docs/spec.md#spec-fields; a dict or a JSON file) as a job.

        ``tags`` are added to any ``tags`` in the spec; a retry with the same
        ``idempotency_key`` returns the same job. With ``wait`` (the default) this
        returns when the job has finished (see :meth:`wait`); check ``job.status``.
        """
        body = _load_json(spec)
        if name is not None:
            body["name"] = name
        given = body.get("tags")
        if tags and (given is None or isinstance(given, (list, tuple))):  # else the API names it
            body["tags"] = list(given or []) + ([tags] if isinstance(tags, str) else list(tags))
        headers = _idempotency(idempotency_key)
        job = Job.from_json(self.request_json("POST", "/jobs", json=body, headers=headers))
        if wait:
            job = self.wait(job, progress=progress, timeout=timeout)
        return job

    def wait(
        self,
        job: Job | int,
        *,
        timeout: float | None = None,
        interval: float | None = None,
        progress: bool = True,
    ) -> Job:
        """Poll the job until it is succeeded, failed or cancelled, with a progress bar
        (terminal or notebook, :mod:`svrobs_client.progress`). A brief outage (503, lost
        connection) is waited out; :class:`WaitTimeout` after ``timeout`` seconds."""
        interval = self.poll_interval if interval is None else interval
        current = job if isinstance(job, Job) else self.job(job)
        deadline = None if timeout is None else time.monotonic() + timeout
        bar = make_bar(current.id, current.progress.total, current.status, enabled=progress)
        failures = 0
        try:
            bar.update(current.progress.done, current.progress.total, current.status)
            while not current.finished:
                if deadline is not None and time.monotonic() >= deadline:
                    raise WaitTimeout(
                        f"job {current.id} still {current.status} after {timeout} s "
                        f"({current.progress.done}/{current.progress.total} units)"
                    )
                time.sleep(interval)
                try:
                    current = self.job(current.id)
                    failures = 0
                except (Unavailable, ConnectionFailed):
                    failures += 1
                    if failures > 5:
                        raise
                    continue
                bar.update(current.progress.done, current.progress.total, current.status)
        finally:
            bar.close()
        return current

    def jobs(
        self,
        *,
        status: str | None = None,
        tag: str | None = None,
        owner: str | None = None,
        limit: int = 50,
        offset: int = 0,
    ) -> JobPage:
        """The team's jobs, newest first; ``owner`` is an email or ``"me"``."""
        params = {"status": status, "tag": tag, "owner": owner, "limit": limit, "offset": offset}
        body = answer(
            self.request_json(
                "GET", "/jobs", params={k: v for k, v in params.items() if v is not None}
            ),
            "a page of jobs",
            rows="items",
            counts=("total", "limit", "offset"),
        )
        return JobPage(
            items=[Job.from_json(j) for j in body["items"]],
            total=body["total"],
            limit=body["limit"],
            offset=body["offset"],
        )

    def job(self, job: Job | int) -> Job:
        """One job (status, progress, timings, provenance, error)."""
        return Job.from_json(self.request_json("GET", f"/jobs/{ident(job)}"))

    def cancel(self, job: Job | int) -> Job:
        """Cancel a queued or running job (its units not yet started never run);
        :class:`Conflict` if it already succeeded or failed."""
        return Job.from_json(self.request_json("POST", f"/jobs/{ident(job)}/cancel"))

    def delete(self, job: Job | int) -> None:
        """Delete a job with its results and summaries (``DELETE /jobs/{id}``);
        :class:`Conflict` while it runs; :class:`MethodNotAllowed` on a server without
        the route."""
        self.request("DELETE", f"/jobs/{ident(job)}")

    # ------------------------------------------------------------------ share links
    def share(self, job: Job | int, *, days: float = 7, label: str | None = None) -> Share:
        """A read-only link to the job's report and charts that opens without a key and
        expires after ``days``; ``label`` says what it is for (shown in the lists).
        ``share.url`` (with its token) is returned only now."""
        body: dict[str, Any] = {"days": days}
        if label is not None:
            body["label"] = label
        return Share.from_json(self.request_json("POST", f"/jobs/{ident(job)}/shares", json=body))

    def shares(self, job: Job | int) -> list[Share]:
        """The job's share links, newest first (without their URLs: tokens are not kept)."""
        links = answer(self.request_json("GET", f"/jobs/{ident(job)}/shares"), "a list of links")
        return [Share.from_json(s) for s in links]

    def revoke_share(self, share: Share | int) -> None:
        """Revoke a link: opening it is a 404 from now on (revoking twice is harmless)."""
        self.request("DELETE", f"/shares/{ident(share)}")

    # ------------------------------------------------------------------ presets
    def presets(self) -> list[dict[str, Any]]:
        """The system presets (name, matrices, noise levels) a spec may name."""
        presets: list[dict[str, Any]] = answer(
            self.request_json("GET", "/presets"), "a list of presets"
        )
        return presets

    def run_paper_preset(
        self,
        *,
        scale: str = "full",
        experiments: Sequence[str] | None = None,
        idempotency_key: str | None = None,
        wait: bool = False,
        progress: bool = True,
    ) -> list[Job]:
        """Queue the paper's Section 6 (E1-E4 and the audits A1, A2, or ``experiments``),
        one job each, at ``scale`` ``"full"`` or ``"reduced"``; with ``wait``, return
        them finished."""
        body: dict[str, Any] = {"scale": scale}
        if experiments is not None:
            body["experiments"] = list(experiments)
        headers = _idempotency(idempotency_key)
        out = self.request_json("POST", f"/presets/{PAPER_PRESET}/run", json=body, headers=headers)
        jobs = [Job.from_json(j) for j in out]
        if wait:
            jobs = [self.wait(j, progress=progress) for j in jobs]
        return jobs

    # ------------------------------------------------------------------ schedules
    def schedules(self) -> list[Schedule]:
        """The team's schedules."""
        schedules = answer(self.request_json("GET", "/schedules"), "a list of schedules")
        return [Schedule.from_json(s) for s in schedules]

    def schedule(self, schedule: Schedule | int) -> Schedule:
        return Schedule.from_json(self.request_json("GET", f"/schedules/{ident(schedule)}"))

    def create_schedule(
        self,
        name: str,
        cron: str,
        spec_template: Mapping[str, Any] | Job | str | os.PathLike[str],
        *,
        timezone: str = "UTC",
        tags: Sequence[str] = (),
        enabled: bool = True,
        seed_policy: str = "fixed",
        **extra: Any,
    ) -> Schedule:
        """Create a schedule: a 5-field cron expression (or ``@daily`` etc.) in an IANA
        ``timezone``; ``spec_template`` is a spec (dict, JSON file, or a Job's spec).
        ``seed_policy`` ``"fixed"`` runs the template's seed every time; ``"due-time"``
        derives each run's seed from its due time, so nightly runs add fresh
        repetitions. ``extra`` fields go into the body as given."""
        _check_seed_policy(seed_policy)
        body = {
            "name": name,
            "cron": cron,
            "timezone": timezone,
            "spec_template": _load_json(spec_template),
            "tags": [tags] if isinstance(tags, str) else list(tags),
            "enabled": enabled,
            "seed_policy": seed_policy,
            **extra,
        }
        return Schedule.from_json(self.request_json("POST", "/schedules", json=body))

    def update_schedule(self, schedule: Schedule | int, **changes: Any) -> Schedule:
        """Change any of ``name``, ``cron``, ``timezone``, ``spec_template``, ``tags``,
        ``enabled``, ``seed_policy``."""
        if "seed_policy" in changes:
            _check_seed_policy(changes["seed_policy"])
        if "spec_template" in changes:
            changes["spec_template"] = _load_json(changes["spec_template"])
        return Schedule.from_json(
            self.request_json("PATCH", f"/schedules/{ident(schedule)}", json=changes)
        )

    def enable_schedule(self, schedule: Schedule | int) -> Schedule:
        return self.update_schedule(schedule, enabled=True)

    def disable_schedule(self, schedule: Schedule | int) -> Schedule:
        return self.update_schedule(schedule, enabled=False)

    def delete_schedule(self, schedule: Schedule | int) -> None:
        """Delete a schedule (its jobs stay)."""
        self.request("DELETE", f"/schedules/{ident(schedule)}")

    def schedule_runs(self, schedule: Schedule | int) -> list[ScheduleRun]:
        """The due times already turned into jobs, newest first (last 100)."""
        runs = answer(
            self.request_json("GET", f"/schedules/{ident(schedule)}/runs"), "a list of runs"
        )
        return [ScheduleRun.from_json(x) for x in runs]
