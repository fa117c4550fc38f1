"""The runs table over more than one page, in a real chromium against a real server (the
stack and browser of test_browser): runs ticked on one page stay ticked on the others,
"Compare selected" sends them all and then forgets them."""

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


@pytest.fixture(scope="module")
def runs(stack) -> list[int]:
    """PAGE + 2 finished runs, oldest first: the newest PAGE on the first page."""
    with stack.client() as api:
        ids = [submit(api, {**TINY, "seed": s}, name=f"run {s}")["id"] for s in range(PAGE + 2)]
        for i in ids:
            stack.wait_job(api, i)
    return ids


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
