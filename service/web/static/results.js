/* The results page. The view lives in the URL: after each swap of the grid (a filter,
 * a sort, a page) the address becomes /results?<the grid's own query>, so a reload,
 * a bookmark or a copied link opens the same view and back/forward step through the
 * views. The CSV and JSONL buttons export the view shown: the API's export with the
 * same filters, ranges and sort (every page of it). Shift+click on a column head
 * adds it as the next sort key; the column chooser hides columns (?hide=a,b). A change
 * of a filter asks for the grid; Apply (or Enter in a box) asks for it every time, the
 * same view too (a running job's new rows). A change that is part of an Apply (the box
 * left as the pointer goes down on Apply, the box Enter submits) waits for it: one
 * request. A refused view (a bad sort key) shows its error in the grid, and the boxes
 * keep what was typed. */
(function () {
  "use strict";

  function grid() { return document.getElementById("results-grid"); }

  /* The API's query of a page query: ranges (rf, rmin, rmax) as field_gte / field_lt. */
  function exportQuery(pageQuery, format) {
    const q = new URLSearchParams(pageQuery), out = new URLSearchParams();
    const rf = q.getAll("rf"), lo = q.getAll("rmin"), hi = q.getAll("rmax");
    for (const [k, v] of q) {
      if (["job", "page", "rf", "rmin", "rmax", "hide"].includes(k) || v === "") continue;
      out.append(k, v);
    }
    rf.forEach((f, i) => {
      if (!f) return;
      if (lo[i]) out.append(`${f}_gte`, lo[i]);
      if (hi[i]) out.append(`${f}_lt`, hi[i]);
    });
    out.set("format", format);
    return out.toString();
  }

  function hidden() {
    const box = document.getElementById("results-hide");
    return new Set((box ? box.value : "").split(",").filter(Boolean));
  }

  function applyColumns() {
    const g = grid(), hide = hidden();
    if (!g) return;
    g.querySelectorAll("[data-field]").forEach((cell) => { cell.hidden = hide.has(cell.dataset.field); });
    document.querySelectorAll("#results-columns input[type=checkbox]").forEach((b) => { b.checked = !hide.has(b.value); });
  }

  function sync(push) {
    const g = grid();
    if (!g || g.dataset.query === undefined) return;
    const q = new URLSearchParams(g.dataset.query);
    const hide = [...hidden()].join(",");
    if (hide) q.set("hide", hide); else q.delete("hide");
    const url = `/results?${q.toString()}`;
    // the entry the page was opened on is marked too (replaceState), so that going
    // back to it shows its view again (popstate below)
    if (!push) history.replaceState({ svrobsResults: true }, "", url);
    else if (url !== location.pathname + location.search) history.pushState({ svrobsResults: true }, "", url);
    const job = q.get("job");
    document.querySelectorAll("#results-exports a[data-format]").forEach((a) => {
      a.href = `/api/v1/jobs/${job}/results?${exportQuery(q.toString(), a.dataset.format)}`;
    });
    const sort = document.getElementById("results-sort");
    if (sort && !g.dataset.error) sort.value = g.dataset.sort || "";
    applyColumns();
  }

  /* ``held``: a change not asked for yet; ``pressing``: a pointer is down on Apply. */
  let held = false, pressing = false;

  function ask() {
    held = false;
    window.htmx.trigger(document.getElementById("results-filters"), "svrobs-apply");
  }

  /* A held change is asked for at the end of this task (Enter's submit comes in the same
   * task as its change) or of the press on Apply (its click and submit come in the task
   * of the pointer's release), unless that submit asked meanwhile. */
  function askLater() {
    if (held) setTimeout(() => { if (held) ask(); });
  }

  function apply(e) {
    const form = document.getElementById("results-filters");
    if (!window.htmx || e.target.closest("form") !== form) return;  // (no htmx: the plain GET)
    if (e.type === "submit") {
      e.preventDefault();
      ask();
      return;
    }
    held = true;
    if (!pressing) askLater();
  }

  function pressed(e) {
    pressing = !!e.target.closest("button[type=submit]");
  }

  function released() {
    if (!pressing) return;
    pressing = false;
    askLater();
  }

  /* Shift+click on a column head: the field becomes the next sort key (or, if it is one
   * already, changes direction in place). */
  function addSortKey(e) {
    const a = e.target.closest("th a[data-sort-field]");
    if (!a || !e.shiftKey) return;
    e.preventDefault();
    e.stopPropagation();
    const field = a.dataset.sortField;
    const keys = (grid().dataset.sort || "").split(",").filter(Boolean);
    const at = keys.findIndex((k) => k.replace(/^-/, "") === field);
    if (at >= 0) keys[at] = keys[at].startsWith("-") ? field : `-${field}`;
    else keys.push(field);
    document.getElementById("results-sort").value = keys.join(",");
    document.getElementById("results-filters").requestSubmit();
  }

  function init() {
    const g = grid();
    if (!g) return;
    document.addEventListener("click", addSortKey, true);
    const form = document.getElementById("results-filters");
    if (form) {
      form.addEventListener("change", apply);
      form.addEventListener("submit", apply);
      form.addEventListener("pointerdown", pressed);
      ["pointerup", "pointercancel"].forEach((t) => window.addEventListener(t, released, true));
    }
    document.body.addEventListener("htmx:afterSwap", (e) => {
      if (e.detail.target.id === "results-grid" || (e.detail.elt && e.detail.elt.id === "results-grid")) sync(true);
    });
    document.querySelectorAll("#results-columns input[type=checkbox]").forEach((b) => {
      b.addEventListener("change", () => {
        const hide = hidden();
        if (b.checked) hide.delete(b.value); else hide.add(b.value);
        document.getElementById("results-hide").value = [...hide].join(",");
        sync(false);
      });
    });
    window.addEventListener("popstate", (e) => { if (e.state && e.state.svrobsResults) location.reload(); });
    sync(false);
  }

  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", init);
  else init();
})();
