/* The compare page's chart: the rows of GET /api/v1/compare (embedded in
 * #compare-card's data-compare) as one line per job and remaining group, the mean
 * against the chosen x field with a ± std band. Labels say only what differs: for
 * each job, the spec fields that tell it apart from the other chosen jobs
 * (data-jobs holds their specs; the job id when no field does), and the group fields
 * that take more than one value; what every line shares is said once above the chart.
 * Points with a null mean are left out, and a job with no value of the metric is
 * named above the chart. The bands and log-y choices are kept in the URL beside the
 * form's own fields. */
(function () {
  "use strict";
  const kit = window.svrobsChartKit;
  const card = document.getElementById("compare-card");
  if (!card || !window.Chart || !kit) return;
  const data = JSON.parse(card.dataset.compare);
  const jobs = JSON.parse(card.dataset.jobs || "[]")
    .sort((a, b) => data.jobs.indexOf(a.id) - data.jobs.indexOf(b.id));  // the compare's order
  const glossary = kit.glossaryOf(card);
  const rest = data.by.filter((b) => b !== data.x);
  const show = (v) => (v === null || v === undefined ? "—" : typeof v === "number" ? kit.fmt(v) : String(v));

  /* A spec as {path: JSON text}: nested objects by dotted path, lists whole. */
  function flatten(spec, prefix, out) {
    Object.entries(spec || {}).forEach(([k, v]) => {
      const path = prefix ? `${prefix}.${k}` : k;
      if (v && typeof v === "object" && !Array.isArray(v)) flatten(v, path, out);
      else out[path] = JSON.stringify(v);
    });
    return out;
  }

  const flat = Object.fromEntries(jobs.map((j) => [j.id, flatten(j.spec, "", {})]));
  const keys = [...new Set(jobs.flatMap((j) => Object.keys(flat[j.id])))];
  const differs = keys.filter((k) => new Set(jobs.map((j) => flat[j.id][k])).size > 1);

  function shown(id, k) {
    const v = flat[id][k];
    const text = v === undefined ? "unset" : v.length > 24 ? v.slice(0, 22) + "…" : v;
    return `${k}=${text.replace(/^"|"$/g, "")}`;
  }

  /* The fields that tell a job apart from each other job: greedily, the field that
   * separates it from most of the jobs not yet told apart (at most 3). */
  function telling(id) {
    let others = jobs.map((j) => j.id).filter((o) => o !== id && flat[o]);
    const keys = [];
    while (others.length && keys.length < 3) {
      let best = null, split = 0;
      for (const k of differs) {
        if (keys.includes(k)) continue;
        const n = others.filter((o) => flat[o][k] !== flat[id][k]).length;
        if (n > split) { best = k; split = n; }
      }
      if (best === null) break;
      keys.push(best);
      others = others.filter((o) => flat[o][best] === flat[id][best]);
    }
    return keys;
  }

  const jobLabels = new Map();
  if (data.jobs.length > 1) {
    data.jobs.forEach((id) => {
      const keys = flat[id] ? telling(id) : [];
      jobLabels.set(id, keys.length ? keys.map((k) => shown(id, k)).join(", ") : `job ${id}`);
    });
    const count = new Map();
    jobLabels.forEach((l) => count.set(l, (count.get(l) || 0) + 1));
    jobLabels.forEach((l, id) => { if (count.get(l) > 1) jobLabels.set(id, `${l} (job ${id})`); });
  }

  function jobLabel(id) { return jobLabels.get(id) || ""; }

  const varies = rest.filter((b) => new Set(data.rows.map((r) => JSON.stringify(r[b]))).size > 1);
  const same = rest.filter((b) => !varies.includes(b) && data.rows.length);

  function groupLabel(r) {
    return varies.filter((b) => !(b === "gamma" && r.gamma === null && varies.includes("estimator")))
      .map((b) => (b === "estimator" ? String(r[b]) : `${kit.label(glossary, b)}=${show(r[b])}`))
      .join(" ");
  }

  const series = new Map();
  for (const r of data.rows) {
    if (r.mean === null || r[data.x] === null) continue;
    const key = JSON.stringify([r.job_id].concat(rest.map((b) => r[b])));
    if (!series.has(key)) {
      const label = [jobLabel(r.job_id), groupLabel(r)].filter(Boolean).join(" · ") || kit.label(glossary, data.metric);
      series.set(key, { label, job: r.job_id, group: Object.fromEntries(rest.map((b) => [b, r[b]])), rows: [] });
    }
    series.get(key).rows.push(r);
  }
  const groupKeys = [...new Set([...series.values()].map((s) => JSON.stringify(s.group)))];
  const jobIndex = (id) => Math.max(0, data.jobs.indexOf(id));
  const positive = [...series.values()].every((s) => s.rows.every((r) => r.mean > 0));

  const q = new URLSearchParams(location.search);
  const bandsBox = document.getElementById("compare-bands");
  const logBox = document.getElementById("compare-logy");
  const manyLines = series.size > 4;  // bands of many lines hide each other: off unless asked
  bandsBox.checked = q.has("bands") ? q.get("bands") === "1" : !manyLines;
  logBox.checked = q.has("logy") ? q.get("logy") === "1" : positive;
  logBox.disabled = !positive;

  function datasets(logY, bands) {
    const colours = kit.palette(), out = [];
    [...series.values()].forEach((s, i) => {
      s.rows.sort((a, b) => a[data.x] - b[data.x]);
      // a group (estimator, γ, ...) is a colour and a marker, a job a dash pattern (and,
      // with one group, its colour and marker too)
      const g = groupKeys.length > 1 ? groupKeys.indexOf(JSON.stringify(s.group)) : jobIndex(s.job);
      const colour = colours[g % colours.length];
      const pts = s.rows.map((r) => ({ x: r[data.x], y: r.mean }));
      out.push({
        label: s.label, data: pts, borderColor: colour, backgroundColor: colour, borderWidth: 2, pointRadius: 4,
        borderDash: kit.style(jobIndex(s.job)).borderDash, pointStyle: kit.style(g).pointStyle, tension: 0,
        svrobs: { role: "mean", series: i, job: s.job, group: s.group, rows: s.rows },
      });
      if (bands) out.push(...kit.band(s.label, pts, s.rows.map((r) => r.mean), s.rows.map((r) => r.std), colour, i, logY));
    });
    return out;
  }

  let chart = null;
  function draw() {
    if (chart) chart.destroy();
    const logY = logBox.checked && positive;
    chart = new window.Chart(document.getElementById("compare-chart"), {
      type: "line",
      data: { datasets: datasets(logY, bandsBox.checked) },
      options: {
        animation: false, parsing: false, responsive: true, maintainAspectRatio: false,
        interaction: { mode: "nearest", intersect: false },
        scales: {
          x: kit.axis("linear", kit.axisTitle(glossary, data.x)),
          y: kit.axis(logY ? "logarithmic" : "linear", kit.axisTitle(glossary, data.metric)),
        },
        plugins: {
          legend: { display: false },
          tooltip: {
            filter: (item) => item.dataset.svrobs.role === "mean",
            callbacks: {
              label: (item) => {
                const r = item.dataset.svrobs.rows[item.dataIndex];
                return `${item.dataset.label}: ${kit.fmt(r.mean)} ± ${kit.fmt(r.std)} (n = ${r.count})`;
              },
            },
          },
        },
      },
    });
    kit.axisTooltips(chart.canvas, chart, { x: kit.describe(glossary, data.x), y: kit.describe(glossary, data.metric) });
    document.getElementById("compare-legend").replaceChildren(kit.legend(chart));
    window.svrobsCompare = { chart, data };
  }

  function note() {
    const shared = same.map((b) => `${kit.label(glossary, b)}=${show(data.rows[0][b])}`);
    if (data.jobs.length > 1 && !differs.length) shared.push("the same spec in every job");
    const box = document.getElementById("compare-legend-note");
    box.textContent = shared.length ? `Every line: ${shared.join(", ")}.` : "";
    // the jobs that draw no line: no value of the metric (in the groups read)
    const drawn = new Set([...series.values()].map((s) => s.job));
    const none = data.jobs.filter((id) => !drawn.has(id));
    if (!none.length) return;
    const metric = `${kit.label(glossary, data.metric)} (${data.metric})`;
    const names = none.map((id) => `job ${id}`).join(", ");
    const read = data.total > data.rows.length ? ` in the first ${data.rows.length} of ${data.total} groups` : "";
    const p = document.createElement("p");
    p.className = "chart-note";
    p.id = "compare-missing";
    p.textContent = none.length === data.jobs.length ?
      `No values of ${metric}${read} in ${none.length > 1 ? "any of " : ""}${names}: nothing to draw.` :
      `No values of ${metric}${read} in ${names}: ${none.length > 1 ? "they have" : "it has"} no line.`;
    box.after(p);
  }

  function specDiff() {
    const box = document.getElementById("spec-diff");
    if (jobs.length < 2) {
      box.replaceChildren(Object.assign(document.createElement("p"), { className: "chart-note", textContent: "Pick two or more jobs to see what differs between their specs." }));
      return;
    }
    if (!differs.length) {
      box.replaceChildren(Object.assign(document.createElement("p"), { className: "chart-note", textContent: "The chosen jobs have the same spec." }));
      return;
    }
    const table = document.createElement("table");
    table.className = "spec-diff";
    table.id = "spec-diff-table";
    const head = table.createTHead().insertRow();
    // a long name is cut (whole in its tooltip): the head of a column stays on one line
    const cut = (name) => (name.length > 40 ? `${name.slice(0, 39)}…` : name);
    [["field", ""]].concat(jobs.map((j) => [`job ${j.id}${j.name ? " · " + cut(j.name) : ""}`, j.name || ""]))
      .forEach(([t, whole]) => {
        const th = document.createElement("th");
        th.scope = "col";
        th.textContent = t;
        if (whole.length > 40) th.title = whole;
        head.appendChild(th);
      });
    const body = table.createTBody();
    differs.forEach((k) => {
      const row = body.insertRow();
      row.dataset.field = k;
      row.insertCell().textContent = k;
      jobs.forEach((j) => { row.insertCell().textContent = flat[j.id][k] === undefined ? "(not set)" : flat[j.id][k]; });
    });
    const wrap = document.createElement("div");
    wrap.className = "table-wrap";
    wrap.tabIndex = 0;
    wrap.appendChild(table);
    box.replaceChildren(wrap);
  }

  function remember() {
    const p = new URLSearchParams(location.search);
    if (bandsBox.checked === !manyLines) p.delete("bands"); else p.set("bands", bandsBox.checked ? "1" : "0");
    if (logBox.checked === positive) p.delete("logy"); else p.set("logy", logBox.checked ? "1" : "0");
    history.replaceState(null, "", `${location.pathname}?${p.toString()}`);
  }

  bandsBox.addEventListener("change", () => { remember(); draw(); });
  logBox.addEventListener("change", () => { remember(); draw(); });
  // "Compare" loads a new page from the form: the bands and log-y choices go with it
  const form = document.getElementById("compare-form");
  if (form) {
    form.addEventListener("submit", () => {
      const p = new URLSearchParams(location.search);
      form.querySelectorAll("input[data-kept]").forEach((i) => i.remove());
      ["bands", "logy"].filter((k) => p.has(k)).forEach((k) => {
        const i = Object.assign(document.createElement("input"), { type: "hidden", name: k, value: p.get(k) });
        i.dataset.kept = "yes";
        form.appendChild(i);
      });
    });
  }
  document.addEventListener("svrobs:theme", draw);
  note();
  specDiff();
  draw();
  card.dataset.ready = "yes";
})();
