"""axe-core (vendored, service/web/static/vendor) and a horizontal-overflow probe, run
inside a Playwright page: the checks of the accessibility and layout sweep."""

from __future__ import annotations

AXE = "/static/vendor/axe-4.14.1.min.js"
BLOCKING = ("serious", "critical")

# axe's default rules and target-size (WCAG 2.2 AA 2.5.8: a pointer target at least
# 24x24 CSS px, or that far from its neighbours), which axe 4.x leaves off by default.
RUN_AXE = """async () => {
  const r = await axe.run(document, {resultTypes: ["violations"],
                                     rules: {"target-size": {enabled: true}}});
  return r.violations.map(v => ({id: v.id, impact: v.impact, help: v.help,
    nodes: v.nodes.slice(0, 5).map(n => n.target.join(" ") + " :: " + n.failureSummary)}));
}"""

# Elements wider than the viewport, named (what makes the page scroll sideways).
OVERFLOW = """() => {
  const w = window.innerWidth, out = [];
  if (document.documentElement.scrollWidth <= w) return {scroll: document.documentElement.scrollWidth, width: w, wide: []};
  for (const el of document.body.querySelectorAll("*")) {
    const r = el.getBoundingClientRect();
    if (r.right > w + 0.5 && getComputedStyle(el).position !== "fixed") {
      let p = el.parentElement, clipped = false;
      while (p && p !== document.body) {
        const o = getComputedStyle(p).overflowX;
        if (o === "auto" || o === "scroll" || o === "hidden") { clipped = true; break; }
        p = p.parentElement;
      }
      if (!clipped) out.push(el.tagName.toLowerCase() + (el.id ? "#" + el.id : "") +
        (el.className && typeof el.className === "string" ? "." + el.className.split(" ").join(".") : "") +
        " right=" + Math.round(r.right));
    }
  }
  return {scroll: document.documentElement.scrollWidth, width: w, wide: out.slice(0, 10)};
}"""


def violations(page) -> list[dict]:
    """axe's violations of serious or critical impact on the page as it is now."""
    if not page.evaluate("() => typeof window.axe !== 'undefined'"):
        page.add_script_tag(url=AXE)
        page.wait_for_function("() => typeof window.axe !== 'undefined'")
    return [v for v in page.evaluate(RUN_AXE) if v["impact"] in BLOCKING]


def overflow(page) -> dict:
    """``{scroll, width, wide}``: the document's scrollWidth, the viewport's width and
    the elements that stick out (empty when scrollWidth <= innerWidth)."""
    return page.evaluate(OVERFLOW)
