/* The jobs list as a runs table: runs ticked to compare stay ticked while the table
 * polls (it is replaced every 2 s while a job runs), and the column chooser hides
 * columns, kept in the URL (?hide=owner,tags). */
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
    document.getElementById("runs-selected").textContent =
      n ? `${n} run${n === 1 ? "" : "s"} ticked: ${[...picked].map((i) => "#" + i).join(", ")}` : "Tick runs to compare them.";
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
  document.body.addEventListener("htmx:afterSwap", apply);
  apply();
})();
