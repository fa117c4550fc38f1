"""The dashboard's pictures of README.md and docs/web.md (docs/web.md#pages), made
afresh: an embedded stack (SQLite, the filesystem broker, one worker; the real
processes of ``svrobs serve``) runs two small jobs, a share link and a schedule are
made, and Playwright drives Debian's chromium (/usr/bin/chromium) through the
pages at 1400×900 (desktop), 390×844 (phone) and in the dark theme, saving PNGs
to docs/img/ (each reduced to a palette of 256 colours when it would exceed
300 KB).

    PYTHONPATH=. .venv/bin/python docs/screenshots.py [--out docs/img]

A script, not a test: it checks nothing but that every page it pictures opens.
"""

from __future__ import annotations

import argparse
import io
import logging
import re
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.integration.stack import Stack, submit  # noqa: E402 - after the path
from tests.web.browser import Browser  # noqa: E402

log = logging.getLogger(__name__)
MAX_BYTES = 300_000
DESKTOP = (1400, 900)
PHONE = (390, 844)
SPEC = {
    "systems": ["paper-stable", "paper-unstable"],
    "sigma_w": [0.1, 1.0],
    "N": [10, 20, 40, 80],
    "gamma": [0.01, 0.1],
    "estimators": ["ols", "svr"],
    "reps": 3,
    "stages": ["estimate", "bounds", "gain"],
    "seed": 11,
}


def save(target, path: Path, *, full_page: bool = False) -> None:
    """A page's (or an element's) screenshot, as a 256-colour PNG when the full-colour
    one is larger than MAX_BYTES."""
    kw = {"full_page": full_page} if hasattr(target, "set_viewport_size") else {}
    png = target.screenshot(**kw)
    if len(png) > MAX_BYTES:
        from PIL import Image

        small = io.BytesIO()
        Image.open(io.BytesIO(png)).convert("RGB").quantize(256).save(small, "PNG", optimize=True)
        png = small.getvalue()
    path.write_bytes(png)
    log.info("%s: %d KB", path.name, len(png) // 1024)


def sign_in(page, key: str) -> None:
    page.goto("/login")
    page.fill("#key", key)
    page.click("form[action='/login'] button[type=submit]")
    page.wait_for_url(re.compile(r"/jobs$"))


def make_site(stack: Stack) -> dict:
    """Two finished jobs (seeds 11 and 12), a cancelled and a queued one, a labelled
    share link of the first and a nightly schedule."""
    with stack.client() as api:
        ids = [
            submit(api, {**SPEC, "seed": s}, name=f"paper systems, seed {s}", tags=["demo"])["id"]
            for s in (11, 12)
        ]
        for i in ids:
            stack.wait_job(api, i, timeout=900)
        tiny = {"systems": ["paper-stable"], "sigma_w": [1.0], "N": [10], "reps": 2}
        cancelled = submit(api, tiny, name="a sweep cancelled")["id"]
        api.post(f"/jobs/{cancelled}/cancel")
        r = api.post(f"/jobs/{ids[0]}/shares", json={"label": "for the reviewers"})
        assert r.status_code == 201, r.text
        r = api.post(
            "/schedules",
            json={"name": "nightly", "cron": "0 2 * * *", "spec_template": SPEC},
        )
        assert r.status_code == 201, r.text
        cell = api.get(
            f"/jobs/{ids[0]}/results",
            params={"system": "paper-unstable", "estimator": "svr", "N": 80, "limit": 1},
        ).json()["items"][0]
    return {"jobs": ids, "cell": cell}


def shoot(stack: Stack, site: dict, out: Path) -> None:
    from service.web.pages.cell import cell_query

    a, b = site["jobs"]
    browser = Browser()
    try:
        page = browser.page(stack.base_url, width=DESKTOP[0], height=DESKTOP[1])
        sign_in(page, stack.key)
        save(page, out / "dashboard-jobs.png")

        page.goto(f"/jobs/{a}")
        page.wait_for_selector("#charts-card[data-state=ready] canvas")
        save(page, out / "dashboard-job.png")
        preset = page.eval_on_selector(
            "#chart-preset",
            "s => [...s.options].map(o => o.value).find(v => v.startsWith('fig_rmse'))",
        )
        if preset:
            loads = page.get_attribute("#charts-card", "data-loads")
            page.select_option("#chart-preset", preset)
            page.wait_for_selector(f"#charts-card:not([data-loads='{loads}'])[data-state=ready]")
            save(page.locator("#charts-card"), out / "dashboard-preset.png")

        page.goto(f"/results?job={a}&system=paper-unstable&estimator=svr&sort=-rmse_A,N")
        page.wait_for_selector("#results-grid")
        save(page, out / "dashboard-results.png")
        page.goto(f"/results/cell?{cell_query(a, site['cell'])}")
        page.wait_for_selector("#cell-matrices figure.matrix")
        save(page, out / "dashboard-cell.png", full_page=True)

        page.goto("/jobs/new?preset=system%3Apaper-stable")
        page.wait_for_selector("#submit-form")
        save(page, out / "dashboard-submit.png")
        page.goto(f"/jobs/{a}/share")
        page.fill("#share-label", "for my supervisor")
        page.click("#share-form button[type=submit]")
        page.wait_for_selector("#share-created")
        save(page, out / "dashboard-share.png")

        dark = browser.page(stack.base_url, width=DESKTOP[0], height=DESKTOP[1], dark=True)
        sign_in(dark, stack.key)
        dark.goto(f"/compare?jobs={a}&jobs={b}&metric=rmse_A")
        dark.wait_for_selector("#compare-card[data-ready=yes]")
        save(dark, out / "dashboard-dark-compare.png")
        dark.goto(f"/jobs/{a}")
        dark.wait_for_selector("#charts-card[data-state=ready] canvas")
        dark.click("#scatter-view summary")
        dark.click("#certificates-view summary")
        dark.wait_for_selector("#views-card[data-scatter=ready][data-certificates=ready]")
        save(dark.locator("#views-card"), out / "dashboard-dark-views.png")

        phone = browser.page(stack.base_url, width=PHONE[0], height=PHONE[1])
        sign_in(phone, stack.key)
        phone.goto(f"/jobs/{a}")
        phone.wait_for_selector("#charts-card[data-state=ready] canvas")
        save(phone, out / "dashboard-phone-job.png")
        phone.goto("/jobs")
        phone.click("#menu-toggle")
        save(phone, out / "dashboard-phone-menu.png")
        phone.goto(f"/results/cell?{cell_query(a, site['cell'])}")
        phone.wait_for_selector("#cell-matrices figure.matrix")
        save(phone, out / "dashboard-phone-cell.png")
    finally:
        browser.close()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "img")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logging.getLogger("httpx").setLevel(logging.WARNING)
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="svrobs-shots-") as tmp:
        stack = Stack("embedded", Path(tmp))
        try:
            stack.setup()
            stack.start_api()
            stack.start_worker()
            shoot(stack, make_site(stack), args.out)
        finally:
            stack.teardown()


if __name__ == "__main__":
    main()
