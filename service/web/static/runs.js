/* The jobs list as a runs table: runs ticked to compare or delete stay ticked while
 * the table polls (it is replaced every 2 s while a job runs); the column chooser
 * hides columns, kept in the URL (?hide=owner,tags); Shift+click on a column head
 * adds it as the next sort key (a click sorts by it alone, the server's link). */
(function () {
  "use strict";
  const form = document.getElementById("runs-form");
  if (!form) return;
  const picked = new Set();
  const q = new URLSearchParams(location.search);
  const hide = new Set((q.get("hide") || "").split(",").filter(Boolean));

  function apply() {
    document.querySelectorAll("#jobs-table .run-pick").forEach((b) => { b.checked = picked.has(b.value); });
    document.querySelectorAll("#jobs-table [data-col]").forEach((cell) => { cell.hidden = hide.has(cell.dataset.col); });
    document.querySelectorAll("#runs-columns input[type=checkbox]").forEach((b) => { b.checked = !hide.has(b.value); });
    const n = picked.size;
    document.getElementById("compare-selected").disabled = n === 0;
    document.getElementById("delete-selected").disabled = n === 0;
    document.getElementById("runs-selected").textContent =
      n ? `${n} run${n === 1 ? "" : "s"} ticked: ${[...picked].map((i) => "#" + i).join(", ")}` : "Tick runs to compare them.";
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
    const shown = new Set([...document.querySelectorAll("#jobs-table .run-pick")].map((b) => b.value));
    [...picked].filter((i) => !shown.has(i)).forEach((i) => {
      const h = document.createElement("input");
      h.type = "hidden";
      h.name = "jobs";
      h.value = i;
      form.appendChild(h);
    });
  }

  document.addEventListener("change", (e) => {
    if (e.target.classList && e.target.classList.contains("run-pick")) {
      if (e.target.checked) picked.add(e.target.value); else picked.delete(e.target.value);
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
