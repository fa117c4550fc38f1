"""The runs table over more than one page, in a real chromium against a real server (the
stack and browser of test_browser): runs ticked on one page stay ticked on the others,
"Compare selected" sends them all and then forgets them; a run's long name (one word of
200 characters) wraps in its column and is cut in the compare page's spec table."""

from __future__ import annotations

import pytest
from playwright.sync_api import expect

from tests.integration.stack import submit

from . import test_browser as base
from .test_browser import follow, sign_in

browser = base.browser
only_the_server = base.only_the_server
pytestmark = base.pytestmark

TINY = {"systems": ["paper-stable"], "sigma_w": [1.0], "N": [10], "reps": 1, "stages": ["estimate"]}
PAGE = 25  # runs per page of /jobs
LONG = "x" * 200  # the oldest run's name: the longest a name may be, one word


@pytest.fixture(scope="module")
def runs(stack) -> list[int]:
    """PAGE + 2 finished runs, oldest first: the newest PAGE on the first page."""
    with stack.client() as api:
        names = [LONG] + [f"run {s}" for s in range(1, PAGE + 2)]
        ids = [submit(api, {**TINY, "seed": s}, name=n)["id"] for s, n in enumerate(names)]
        for i in ids:
            stack.wait_job(api, i)
    return ids


# the box named fits its content: it does not scroll sideways
FITS = "sel => { const b = document.querySelector(sel); return b.scrollWidth <= b.clientWidth; }"


def ticked(page) -> list[str]:
    return page.eval_on_selector_all("#jobs-table .run-pick:checked", "bs => bs.map(b => b.value)")


def test_ticks_stay_across_pages_until_compared(browser, stack, runs):
    page = browser.page(stack.base_url)
    sign_in(page, stack.key)
    newest, second, oldest = runs[-1], runs[-2], runs[0]
    page.check(f"#job-{newest} .run-pick")
    page.check(f"#job-{second} .run-pick")
    follow(page, "#jobs-table a[rel=next]")  # older →
    assert page.locator(f"#job-{oldest}").count() == 1 and ticked(page) == []
    assert page.evaluate(FITS, "#jobs-scroll")  # the long name wraps: no column pushed out
    status = page.locator("#runs-selected")
    expect(status).to_have_text(f"2 runs ticked (2 not on this page): #{newest}, #{second}")
    page.check(f"#job-{oldest} .run-pick")
    expect(status).to_contain_text("3 runs ticked (2 not on this page)")
    follow(page, "#jobs-table a[rel=prev]")  # ← newer: its ticks are there
    assert sorted(ticked(page)) == sorted([str(newest), str(second)])
    expect(status).to_contain_text("3 runs ticked (1 not on this page)")
    page.click("#compare-selected")
    page.wait_for_selector("#compare-card[data-ready=yes]")
    assert sorted(page.evaluate("window.svrobsCompare.data.jobs")) == sorted(
        [newest, second, oldest]
    )
    head = page.locator("#spec-diff-table th", has_text=f"job {oldest}")  # (seeds differ)
    expect(head).to_have_text(f"job {oldest} · {LONG[:39]}…")
    assert head.get_attribute("title") == LONG and page.evaluate(FITS, "#spec-diff .table-wrap")
    page.goto("/jobs")  # compared: the ticks are forgotten
    assert ticked(page) == [] and page.is_disabled("#compare-selected")
    expect(status).to_have_text("Tick runs to compare them.")


def test_untick_all_forgets_the_ticks_of_every_page(browser, stack, runs):
    page = browser.page(stack.base_url)
    sign_in(page, stack.key)
    follow(page, "#jobs-table a[rel=next]")
    page.check(f"#job-{runs[0]} .run-pick")
    follow(page, "#jobs-table a[rel=prev]")
    expect(page.locator("#runs-selected")).to_contain_text("1 run ticked (1 not on this page)")
    page.click("#runs-clear")
    expect(page.locator("#runs-selected")).to_have_text("Tick runs to compare them.")
    assert page.is_hidden("#runs-clear") and page.is_disabled("#compare-selected")
    follow(page, "#jobs-table a[rel=next]")
    assert ticked(page) == []
