/* Two more views of a job page, drawn from GET /api/v1/jobs/{id}/summary (asked once,
 * when one of them is first opened):
 * - a scatter of each summary group's mean of a chosen field against γ, N and σ_w
 *   (a panel each; colour by estimator or system);
 * - the certificates: per group and N, the share of cells with stable_certified and
 *   with certified (means of the booleans over the repetitions), beside the mean
 *   coverage of the true A's entries, under the job's bounds method.
 * Which are open, the scatter's field and its colouring are in the page's URL
 * (?scatter=1&scatter_field=…&scatter_colour=…&certificates=1).
 * window.svrobsViews holds what is drawn, for the tests. */
(function () {
  "use strict";
  const kit = window.svrobsChartKit;
  const ui = window.svrobsUi;
  const card = document.getElementById("views-card");
  if (!card || !kit || !window.Chart) return;
  const glossary = kit.glossaryOf(card);
  const views = { scatter: [], certificates: [], summary: null };
  window.svrobsViews = views;
  let pending = null;

  function summary() {
    if (!pending) {
      pending = fetch(card.dataset.summaryUrl, { credentials: "same-origin", headers: { Accept: "application/json" } })
        .then((r) => (r.ok ? r.json() : Promise.reject(new Error(`HTTP ${r.status}`))))
        .then((s) => { views.summary = s; return s; });
    }
    return pending;
  }

  const mean = (g, f) => { const s = (g.stats || {})[f]; return s && s.mean !== null && s.mean !== undefined ? s.mean : null; };

  function fieldsWithData(groups) {
    const seen = new Set();
    groups.forEach((g) => Object.entries(g.stats || {}).forEach(([f, s]) => { if (s && s.mean !== null) seen.add(f); }));
    return [...seen];
  }

  function drawScatter(groups) {
    const metric = card.querySelector("#scatter-metric").value;
    const colourBy = card.querySelector("#scatter-colour").value;
    views.scatter.forEach((c) => c.chart.destroy());
    views.scatter = [];
    const box = card.querySelector("#scatter-charts");
    box.replaceChildren();
    const cats = [...new Set(groups.map((g) => String(g[colourBy])))].sort();
    const colours = kit.palette();
    const positive = groups.every((g) => mean(g, metric) === null || mean(g, metric) > 0);
    ["gamma", "N", "sigma_w"].forEach((x) => {
      const { canvas } = window.svrobsUi.chartPanel(box,
        `${kit.label(glossary, metric)} against ${kit.label(glossary, x)}`,
        `${metric} of each summary group against ${x}`, { x: x });
      const datasets = cats.map((cat, i) => {
        const members = groups.filter((g) => String(g[colourBy]) === cat && g[x] !== null && mean(g, metric) !== null);
        return {
          label: `${kit.label(glossary, colourBy)} ${cat}`,
          data: members.map((g) => ({ x: g[x], y: mean(g, metric), g })),
          backgroundColor: kit.alpha(colours[i % colours.length], 0.75), borderColor: colours[i % colours.length],
          pointRadius: 4.5, pointStyle: kit.style(i).pointStyle, svrobs: { role: "mean", series: i },
        };
      });
      const xs = datasets.flatMap((d) => d.data.map((p) => p.x));
      const logX = x !== "sigma_w" && xs.length && xs.every((v) => v > 0);
      const chart = new Chart(canvas, {
        type: "scatter",
        data: { datasets },
        options: {
          animation: false, responsive: true, maintainAspectRatio: false, parsing: false,
          scales: {
            x: kit.axis(logX ? "logarithmic" : "linear", kit.axisTitle(glossary, x)),
            y: kit.axis(positive ? "logarithmic" : "linear", kit.axisTitle(glossary, metric)),
          },
          plugins: {
            legend: { display: false },
            tooltip: {
              callbacks: {
                label: (item) => {
                  const g = item.raw.g, s = g.stats[metric];
                  const gamma = g.gamma === null ? "—" : kit.fmt(g.gamma);
                  return `${g.system} · σ_w ${kit.coord("sigma_w", g.sigma_w)} · N ${g.N} · ${g.estimator} γ ${gamma}: ` +
                    `${kit.fmt(s.mean)} ± ${kit.fmt(s.std)} (n = ${s.count})`;
                },
              },
            },
          },
        },
      });
      kit.axisTooltips(canvas, chart, { x: kit.describe(glossary, x), y: kit.describe(glossary, metric) });
      kit.figureLegend(chart);
      views.scatter.push({ x, chart });
    });
    const note = card.querySelector("#scatter-note");
    note.textContent = `${groups.length} summary groups; ols has no γ and is left out of the γ panel. ` +
      kit.describe(glossary, metric);
    card.dataset.scatter = "ready";
  }

  function pct(v) { return v === null ? "—" : `${Math.round(v * 100)} %`; }

  function drawCertificates(groups, spec) {
    const box = card.querySelector("#certificates");
    const method = (spec && spec.bounds_method) || "paper";
    const Ns = [...new Set(groups.map((g) => g.N))].sort((a, b) => a - b);
    const key = (g) => JSON.stringify([g.system, g.sigma_w, g.estimator, g.gamma]);
    const rows = new Map();
    groups.forEach((g) => {
      if (!rows.has(key(g))) rows.set(key(g), { system: g.system, sigma_w: g.sigma_w, estimator: g.estimator, gamma: g.gamma, byN: {} });
      rows.get(key(g)).byN[g.N] = {
        stable: mean(g, "stable_certified"), certified: mean(g, "certified"), coverage: mean(g, "coverage_A"),
        count: ((g.stats || {}).stable_certified || {}).count || 0,
      };
    });
    views.certificates = [...rows.values()];
    const any = views.certificates.some((r) => Object.values(r.byN).some((c) => c.stable !== null || c.certified !== null));
    const note = card.querySelector("#certificates-note");
    if (!any) {
      note.textContent = "No certificates in this job's summaries: they need the bounds stage (and gain, for certified).";
      box.replaceChildren();
      card.dataset.certificates = "ready";
      return;
    }
    note.textContent = `Bounds method: ${method}. Each cell: the share of repetitions with stable_certified ` +
      "(ρ upper bound < 1), with certified (g(L) < 1, needs the gain stage), and the mean share of the true " +
      "entries of A inside their intervals (coverage A, the audited coverage).";
    const table = document.createElement("table");
    table.id = "certificates-table";
    table.className = "data";
    const head = table.createTHead().insertRow();
    ["system", "σ_w", "estimator", "γ"].concat(Ns.map((n) => `N = ${n}`)).forEach((t) => {
      const th = document.createElement("th");
      th.scope = "col";
      th.textContent = t;
      head.appendChild(th);
    });
    const body = table.createTBody();
    views.certificates.forEach((r) => {
      const tr = body.insertRow();
      [r.system, kit.coord("sigma_w", r.sigma_w), r.estimator, r.gamma === null ? "—" : kit.fmt(r.gamma)].forEach((t) => { tr.insertCell().textContent = t; });
      Ns.forEach((n) => {
        const c = r.byN[n], td = tr.insertCell();
        td.className = "cert";
        if (!c) { td.textContent = "—"; return; }
        td.dataset.n = String(n);
        td.dataset.stable = c.stable === null ? "" : String(c.stable);
        td.dataset.certified = c.certified === null ? "" : String(c.certified);
        td.textContent = `stable ${pct(c.stable)} · certified ${pct(c.certified)} · coverage ${pct(c.coverage)}`;
        const level = c.stable === null ? 0 : c.stable;
        td.style.setProperty("--level", String(level));
      });
    });
    const wrap = document.createElement("div");
    wrap.className = "table-wrap";
    wrap.tabIndex = 0;
    wrap.appendChild(table);
    box.replaceChildren(wrap);
    card.dataset.certificates = "ready";
  }

  function open(which) {
    const status = card.querySelector("#views-status");
    status.textContent = "Loading the summaries…";
    summary().then((s) => {
      status.textContent = s.partial ? "The job is not finished: the groups stored so far." : "";
      const spec = JSON.parse(card.dataset.spec || "{}");
      if (which === "scatter") {
        const sel = card.querySelector("#scatter-metric");
        if (!sel.options.length) {
          const fields = fieldsWithData(s.groups);
          const order = Object.keys(glossary).filter((f) => fields.includes(f));
          sel.replaceChildren(...order.map((f) => {
            const o = document.createElement("option");
            o.value = f;
            o.textContent = `${kit.label(glossary, f)} · ${f}`;
            o.title = kit.describe(glossary, f);
            return o;
          }));
          pick(sel, ui.queryValue("scatter_field"));
        }
        drawScatter(s.groups);
      } else {
        drawCertificates(s.groups, spec);
      }
    }).catch((e) => { status.textContent = `Could not load the summaries (${e.message}).`; });
  }

  /* ``select`` set to ``value`` when it has that option. */
  function pick(select, value) {
    if (value !== null && [...select.options].some((o) => o.value === value)) select.value = value;
  }

  const VIEWS = { scatter: "#scatter-view", certificates: "#certificates-view" };
  const metricList = card.querySelector("#scatter-metric"), colourList = card.querySelector("#scatter-colour");

  /* The scatter's field and colouring in the URL (the first of each list, the default,
   * left out). */
  function rememberScatter() {
    ui.setQuery({
      scatter_field: metricList.selectedIndex > 0 ? metricList.value : null,
      scatter_colour: colourList.selectedIndex > 0 ? colourList.value : null,
    });
  }

  /* The views of the URL: its choices set, its views opened (and the others closed);
   * an open scatter whose choices changed is drawn again. */
  function restore() {
    const before = [metricList.value, colourList.value].join();
    pick(metricList, ui.queryValue("scatter_field") || (metricList.options[0] || {}).value);
    pick(colourList, ui.queryValue("scatter_colour") || colourList.options[0].value);
    const scatter = card.querySelector(VIEWS.scatter);
    if (scatter.open && views.summary && [metricList.value, colourList.value].join() !== before) {
      drawScatter(views.summary.groups);
    }
    Object.entries(VIEWS).forEach(([key, sel]) => { card.querySelector(sel).open = ui.queryValue(key) === "1"; });
  }

  Object.entries(VIEWS).forEach(([key, sel]) => card.querySelector(sel).addEventListener("toggle", (e) => {
    ui.setQuery({ [key]: e.target.open ? "1" : null });
    if (e.target.open) open(key);
  }));
  [metricList, colourList].forEach((list) => list.addEventListener("change", () => {
    rememberScatter();
    summary().then((s) => drawScatter(s.groups));
  }));
  window.addEventListener("popstate", restore);
  restore();
  document.addEventListener("svrobs:theme", () => { if (views.summary && card.querySelector("#scatter-view").open) drawScatter(views.summary.groups); });
})();
