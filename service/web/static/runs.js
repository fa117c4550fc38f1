/* The jobs list as a runs table: runs ticked to compare or delete stay ticked while
 * the table polls (it is replaced every 2 s while a job runs) and across the pages,
 * sorts and filters of the list (kept in the tab's sessionStorage); "Compare selected"
 * sends every ticked run, on this page or not, and then forgets the ticks; deleted
 * runs are forgotten. The column chooser hides columns, kept in the URL
 * (?hide=owner,tags); Shift+click on a column head adds it as the next sort key (a
 * click sorts by it alone, the server's link). */
(function () {
  "use strict";
  const form = document.getElementById("runs-form");
  if (!form) return;
  const STORE = "svrobs.jobs.picked";

  function stored() {
    try {
      const ids = JSON.parse(sessionStorage.getItem(STORE) || "[]");
      return Array.isArray(ids) ? ids.map(String).filter((i) => /^\d+$/.test(i)) : [];
    } catch (e) { return []; }  // storage off or spoiled: no ticks kept
  }

  function keep() {
    try {
      if (picked.size) sessionStorage.setItem(STORE, JSON.stringify([...picked]));
      else sessionStorage.removeItem(STORE);
    } catch (e) { /* storage off: the ticks live on this page only */ }
  }

  const picked = new Set(stored());
  // runs just deleted (/jobs?deleted=3,4) are no longer there to compare
  (new URLSearchParams(location.search).get("deleted") || "").split(",").forEach((i) => picked.delete(i));
  keep();
  const q = new URLSearchParams(location.search);
  const hide = new Set((q.get("hide") || "").split(",").filter(Boolean));

  function apply() {
    document.querySelectorAll("#jobs-table .run-pick").forEach((b) => { b.checked = picked.has(b.value); });
    document.querySelectorAll("#jobs-table [data-col]").forEach((cell) => { cell.hidden = hide.has(cell.dataset.col); });
    document.querySelectorAll("#runs-columns input[type=checkbox]").forEach((b) => { b.checked = !hide.has(b.value); });
    const n = picked.size;
    document.getElementById("compare-selected").disabled = n === 0;
    document.getElementById("delete-selected").disabled = n === 0;
    const here = new Set([...document.querySelectorAll("#jobs-table .run-pick")].map((b) => b.value));
    const away = [...picked].filter((i) => !here.has(i)).length;
    document.getElementById("runs-selected").textContent =
      n ? `${n} run${n === 1 ? "" : "s"} ticked${away ? ` (${away} not on this page)` : ""}: ` +
        `${[...picked].map((i) => "#" + i).join(", ")}` : "Tick runs to compare them.";
    clear.hidden = n === 0;
    // the hidden columns go along with every link and filter of the page
    const h = [...hide].join(",");
    const box = document.getElementById("runs-hide");
    if (box) box.value = h;
    document.querySelectorAll("#jobs-table th a[data-sort-field], #jobs-table .pager a").forEach((a) => {
      const u = new URL(a.href, location.href);
      if (h) u.searchParams.set("hide", h); else u.searchParams.delete("hide");
      a.href = u.pathname + u.search;
    });
    // ticked runs not on this page still go to the compare
    form.querySelectorAll("input[type=hidden][name=jobs]").forEach((h) => h.remove());
    [...picked].filter((i) => !here.has(i)).forEach((i) => {
      const h = document.createElement("input");
      h.type = "hidden";
      h.name = "jobs";
      h.value = i;
      form.appendChild(h);
    });
  }

  const clear = document.createElement("button");  // untick every run, here or not
  clear.type = "button";
  clear.className = "secondary";
  clear.id = "runs-clear";
  clear.textContent = "Untick all";
  document.getElementById("runs-selected").after(clear);
  clear.addEventListener("click", () => { picked.clear(); keep(); apply(); });

  form.addEventListener("submit", (e) => {
    if (e.submitter && e.submitter.id === "compare-selected") {  // compared: the ticks are done with
      picked.clear();
      keep();
    }
  });
  window.addEventListener("pageshow", (e) => {  // back to a page kept in memory: the ticks kept now
    if (!e.persisted) return;
    picked.clear();
    stored().forEach((i) => picked.add(i));
    apply();
  });

  document.addEventListener("change", (e) => {
    if (e.target.classList && e.target.classList.contains("run-pick")) {
      if (e.target.checked) picked.add(e.target.value); else picked.delete(e.target.value);
      keep();
      apply();
    } else if (e.target.closest && e.target.closest("#runs-columns")) {
      if (e.target.checked) hide.delete(e.target.value); else hide.add(e.target.value);
      const p = new URLSearchParams(location.search);
      if (hide.size) p.set("hide", [...hide].join(",")); else p.delete("hide");
      history.replaceState(null, "", location.pathname + (p.toString() ? `?${p}` : ""));
      apply();
    }
  });
  document.addEventListener("click", (e) => {
    const a = e.target.closest && e.target.closest("#jobs-table th a[data-sort-field]");
    if (!a || !e.shiftKey) return;
    e.preventDefault();
    const p = new URLSearchParams(location.search);
    const keys = (p.get("sort") || "").split(",").filter(Boolean);
    const field = a.dataset.sortField;
    const at = keys.findIndex((k) => k.replace(/^-/, "") === field);
    if (at >= 0) keys[at] = keys[at].startsWith("-") ? field : `-${field}`;
    else keys.push(field);
    p.set("sort", keys.join(","));
    p.delete("page");
    location.assign(`/jobs?${p.toString()}`);
  }, true);
  document.body.addEventListener("htmx:afterSwap", apply);
  apply();
})();
