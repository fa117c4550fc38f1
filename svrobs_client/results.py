"""The client's calls on a job's results and what is made of them (records, streamed or
written to a file; the summary; comparisons across jobs; the HTML report and its
figures), mixed into :class:`svrobs_client.Client`."""

from __future__ import annotations

import html
import json
import os
import re
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import IO, Any

from . import frames
from .errors import REPORT_HEADER, not_a_report
from .files import write_atomic, writer
from .models import Job, Report, answer, ident
from .params import results_params

FORMATS = ("csv", "jsonl", "json")
# the content type the API streams each format as (json: built here from jsonl)
MEDIA = {"csv": "text/csv", "jsonl": "application/x-ndjson"}
_FIGURE = re.compile(r"<img[^>]*?alt='([^']*)'[^>]*?src='data:image/png;base64,([^']+)'")


class ResultCalls:
    """Records, summaries, comparisons and reports (methods of :class:`Client`)."""

    url: str  # Client.url
    request: Any  # Client.request
    request_json: Any
    _stream: Any

    # ------------------------------------------------------------------ results
    def iter_results(
        self, job: Job | int, *, sort: str | Sequence[str] | None = None, **filters: Any
    ) -> Iterator[dict[str, Any]]:
        """The job's records one by one, streamed as JSON lines (docs/spec.md#record-fields;
        matrices as nested lists, null never NaN), in grid order or by ``sort``
        (``"-rmse_A,N"``: numeric fields, ``-`` descending, nulls last).

        Filters: ``system``, ``sigma_w``, ``N``, ``estimator``, ``gamma`` (``None`` =
        OLS) and ``rep``, each a value or a sequence of values; ranges
        ``<field>_lt``, ``_lte``, ``_gt``, ``_gte`` on a numeric field
        (``rmse_A_lt=0.01``); ``limit`` / ``offset``. An unknown name is a TypeError,
        a bad value a ValueError, before any request (:mod:`svrobs_client.params`)."""
        params = {**results_params(filters, sort), "format": "jsonl"}
        with self._stream(f"/jobs/{ident(job)}/results", params, expect=MEDIA["jsonl"]) as r:
            for line in r.iter_lines():
                if line.strip():
                    yield json.loads(line)

    def results_records(
        self, job: Job | int, *, sort: str | Sequence[str] | None = None, **filters: Any
    ) -> list[dict[str, Any]]:
        """:meth:`iter_results` as a list of plain dicts (no pandas needed)."""
        return list(self.iter_results(job, sort=sort, **filters))

    def results(
        self, job: Job | int, *, sort: str | Sequence[str] | None = None, **filters: Any
    ) -> Any:
        """The job's records as a pandas DataFrame, one row per cell, columns in record
        order; ``A_hat``, ``B_hat``, ``L`` and ``K`` hold 2-D numpy arrays (or None).
        ``sort`` and filters as in :meth:`iter_results`."""
        return frames.records_frame(self.results_records(job, sort=sort, **filters))

    def download_results(
        self,
        job: Job | int,
        out: str | os.PathLike[str] | IO[str],
        *,
        format: str = "csv",
        sort: str | Sequence[str] | None = None,
        **filters: Any,
    ) -> None:
        """Write the job's records as ``csv``, ``jsonl`` or ``json`` (one array, written a
        record at a time), streamed, to a path or a text stream; ``sort`` and filters as in
        :meth:`iter_results`. A path is written through a temporary file and renamed,
        so a failed download leaves no file behind."""
        if format not in FORMATS:
            raise ValueError(f"format must be one of {list(FORMATS)}, got {format!r}")
        params = {**results_params(filters, sort), "format": format}  # checked first

        def chunks() -> Iterator[str]:
            if format == "json":  # one array, as json.dumps writes it, a record at a time
                records = self.iter_results(job, sort=sort, **filters)
                first = next(records, None)  # the answer is checked before "[" is written
                if first is None:
                    yield "[]\n"
                    return
                yield "[" + json.dumps(first)
                for record in records:
                    yield ", " + json.dumps(record)
                yield "]\n"
                return
            with self._stream(f"/jobs/{ident(job)}/results", params, expect=MEDIA[format]) as r:
                yield from r.iter_text()

        if hasattr(out, "write"):
            for chunk in chunks():
                out.write(chunk)
            return
        write_atomic(Path(out), lambda f: [f.write(c.encode("utf-8")) for c in chunks()])

    def summary_json(self, job: Job | int, *, page_size: int = 10_000) -> dict[str, Any]:
        """``GET /jobs/{id}/summary`` as the API sends it, every page's groups in one
        body (pages of ``page_size`` groups; the API sends at most 10,000 a request)."""
        path = f"/jobs/{ident(job)}/summary"
        body: dict[str, Any] = answer(
            self.request_json("GET", path, params={"limit": page_size}),
            "a job's summary",
            rows="groups",
            counts=("total",),
        )
        groups = list(body["groups"])
        while groups and len(groups) < body["total"]:
            params = {"limit": page_size, "offset": len(groups)}
            page = answer(
                self.request_json("GET", path, params=params),
                "a job's summary",
                rows="groups",
                counts=("total",),
            )
            if not page["groups"]:  # a running job's groups changed meanwhile
                break
            groups += page["groups"]
            body["total"], body["partial"] = page["total"], page.get("partial")
        return {**body, "groups": groups}  # the first page's body, with every group

    def summary(self, job: Job | int, *, long: bool = False) -> Any:
        """Mean, std and count of every numeric field per (system, sigma_w, N, estimator,
        gamma) as a DataFrame (see :func:`svrobs_client.frames.summary_frame`)."""
        return frames.summary_frame(self.summary_json(job), long=long)

    def compare_json(
        self,
        jobs: Iterable[Job | int | str],
        metric: str,
        by: Sequence[str] | str = ("N", "estimator", "gamma"),
        *,
        page_size: int = 10_000,
    ) -> dict[str, Any]:
        """``GET /compare`` as the API sends it (its first page), with every page's rows
        (the next pages of ``page_size`` groups; the API sends at most 10,000 a request)."""
        by = by if isinstance(by, str) else ",".join(by)
        ids = ",".join(str(ident(j)) for j in jobs)
        params: dict[str, Any] = {"jobs": ids, "metric": metric, "by": by}
        body: dict[str, Any] = answer(
            self.request_json("GET", "/compare", params=params),
            "a comparison",
            rows="rows",
            counts=("total",),
        )
        rows = list(body["rows"])
        while rows and len(rows) < body["total"]:
            more = {**params, "limit": page_size, "offset": len(rows)}
            page = answer(
                self.request_json("GET", "/compare", params=more),
                "a comparison",
                rows="rows",
                counts=("total",),
            )
            if not page["rows"]:  # a running job's groups changed meanwhile
                break
            rows += page["rows"]
            body["total"] = page["total"]
        return {**body, "rows": rows}  # the first page's body, with every row

    def compare(
        self,
        jobs: Iterable[Job | int | str],
        metric: str,
        by: Sequence[str] | str = ("N", "estimator", "gamma"),
    ) -> Any:
        """One numeric field across jobs: mean, std (ddof 0) and count per job and per
        combination of the ``by`` grid fields, as a DataFrame."""
        return frames.compare_frame(self.compare_json(jobs, metric, by))

    def report_html(self, job: Job | int) -> str:
        """The job's HTML report (tables, embedded figures, spec, provenance, findings);
        a :class:`SvrobsError` for a page without the API's report header (another
        server's page, :func:`~svrobs_client.errors.not_a_report`)."""
        r = self.request("GET", f"/jobs/{ident(job)}/report", timeout=300)
        if REPORT_HEADER not in r.headers:
            raise not_a_report(self.url, r.status_code, r.headers)
        text: str = r.text
        return text

    def report(
        self, job: Job | int, folder: str | os.PathLike[str], *, figures: bool = True
    ) -> Report:
        """Write ``report.html`` into ``folder`` (created if needed) and, with
        ``figures``, each embedded figure as ``figures/NN-title.png``."""
        folder = Path(folder)
        text = self.report_html(job)
        page = folder / "report.html"
        write_atomic(page, lambda f: f.write(text.encode("utf-8")))
        written = []
        if figures:
            import base64

            for i, (alt, data) in enumerate(_FIGURE.findall(text), start=1):
                slug = re.sub(r"[^A-Za-z0-9]+", "-", html.unescape(alt)).strip("-").lower()
                path = folder / "figures" / f"{i:02d}-{slug[:60] or 'figure'}.png"
                png = base64.b64decode(data)
                write_atomic(path, writer(png))
                written.append(path)
        return Report(html=page, figures=written)
