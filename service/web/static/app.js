/* svrobs job page charts: Chart.js line charts of a summary field against N, σ_w or γ,
 * one panel per remaining grid coordinate, one line per estimator/γ with a mean ± std
 * band; or one of the report's figure series (a preset: its panels, lines, band and
 * log/symlog/linear scale, as the figure). The data come from /jobs/{id}/chart-data
 * (the stored summaries), reloaded while the job runs as its cells complete; a
 * response that arrives after a newer request was sent is dropped. The choices are
 * kept in the page's URL (?metric=…&x=…&panel=…), so a reload or a copied link shows
 * the same view and back/forward step through the views. A view the server refuses
 * (a link with ?metric=nope) shows the server's reason and falls back to the default
 * field, with the list of the fields that have data. Every plotted chart is kept in
 * window.svrobsCharts so that tests can read what is drawn. */
(function () {
  "use strict";

  const kit = window.svrobsChartKit;
  const fmt = kit.fmt;
  const registry = { charts: [], data: null, loads: 0, errors: [], requests: 0, dropped: 0 };
  window.svrobsCharts = registry;

  /* A symmetric log axis (as matplotlib's symlog): linear within ± linthresh, logarithmic
   * beyond; ticks at 0 and at the decades linthresh·10^k each side reaches. */
  class SymlogScale extends Chart.Scale {
    static id = "symlog";
    static defaults = { ticks: { callback: (v) => fmt(v) } };
    parse(raw, index) { return Chart.LinearScale.prototype.parse.call(this, raw, index); }
    c() { return this.options.linthresh || 1; }
    fwd(v) { return Math.sign(v) * Math.log10(1 + Math.abs(v) / this.c()); }
    inv(u) { return Math.sign(u) * this.c() * (Math.pow(10, Math.abs(u)) - 1); }
    determineDataLimits() {
      const { min, max } = this.getMinMax(true);
      const c = this.c();
      this.min = -Math.max(Number.isFinite(min) ? -min : 0, c) * 1.6;
      this.max = Math.max(Number.isFinite(max) ? max : 0, c) * 1.6;
    }
    buildTicks() {
      const c = this.c(), out = [{ value: 0 }];
      for (let k = 0; k < 30; k++) {
        const d = c * Math.pow(10, k);
        if (d <= this.max) out.push({ value: d });
        if (-d >= this.min) out.unshift({ value: -d });
      }
      this.start = this.min;
      this.end = this.max;
      return out;
    }
    getLabelForValue(v) { return fmt(v); }
    configure() {
      super.configure();
      this._s = this.fwd(this.min);
      this._r = this.fwd(this.max) - this._s || 1;
    }
    getPixelForValue(v) {
      return v === null || v === undefined || isNaN(v) ? NaN : this.getPixelForDecimal((this.fwd(v) - this._s) / this._r);
    }
    getValueForPixel(p) { return this.inv(this._s + this.getDecimalForPixel(p) * this._r); }
  }
  if (typeof Chart !== "undefined") Chart.register(SymlogScale);
  const AXIS = { log: "logarithmic", symlog: "symlog", linear: "linear" };

  function points(xs, ys) {
    return xs.map((x, i) => ({ x: x, y: ys[i] }));
  }

  function datasets(panel, logY, bands) {
    const out = [], colours = kit.palette();
    panel.series.forEach((s, i) => {
      const shade = s.colour ?? i;  // (a figure's OLS and SVR lines of one σ_w share it)
      const color = colours[shade % colours.length];
      // the marker goes with the colour; the dash too, where it does not tell OLS's
      // flat line or a figure's SVR apart
      const look = kit.style(shade);
      const dash = s.flat ? [6, 4] : s.dash ? [3, 3] : shade === i ? look.borderDash : [];
      const meta = { series: i, estimator: s.estimator, gamma: s.gamma, line: s.line, mean: s.mean, std: s.std, count: s.count };
      const data = points(panel.x, s.mean);
      out.push({
        label: s.label, data: data, borderColor: color,
        backgroundColor: color, borderWidth: 2, pointRadius: 4, borderDash: dash, pointStyle: look.pointStyle,
        svrobs: Object.assign({ role: "mean" }, meta), spanGaps: false,
      });
      if (bands && !s.std.every((v) => v === null)) out.push(...kit.band(s.label, data, s.mean, s.std, color, i, logY));
    });
    return out;
  }

  /* Chart.js's own legend click (its legend is hidden: the page shows kit.legend's buttons). */
  function toggleSeries(e, item, legend) {
    const chart = legend.chart;
    const series = chart.data.datasets[item.datasetIndex].svrobs.series;
    kit.setSeries(chart, series, !chart.isDatasetVisible(item.datasetIndex));
    const button = chart.canvas.closest("figure").querySelector(`.legend button[data-series="${series}"]`);
    if (button) button.setAttribute("aria-pressed", String(chart.isDatasetVisible(item.datasetIndex)));
  }

  function makeChart(canvas, panel, data, opts) {
    const glossary = opts.glossary;
    const xField = data.x === "N" || data.preset ? "N" : data.x;
    const scales = {
      x: kit.axis(opts.logX ? "logarithmic" : "linear", kit.axisTitle(glossary, xField, data.x_label)),
      y: kit.axis(opts.yType, kit.axisTitle(glossary, data.metric), { linthresh: data.linthresh }),
    };
    const factor = opts.n0Factor;
    if (xField === "N" && factor > 1 && panel.x.length) {
      // N0 = (T0 − 1)·N on a second x axis at the top, the report's abscissa
      const lo = Math.min(...panel.x), hi = Math.max(...panel.x);
      const pad = 0;  // both axes span the data exactly, so their ticks line up
      scales.x.min = lo - pad;
      scales.x.max = hi + pad;
      scales.x2 = kit.axis(scales.x.type, `N0 = (T0 − 1)·N = ${factor}·N [samples]`, {
        position: "top", min: (lo - pad) * factor, max: (hi + pad) * factor, grid: { display: false },
      });
    }
    const chart = new Chart(canvas, {
      type: "line",
      data: { datasets: datasets(panel, opts.logY, opts.bands) },
      options: {
        animation: false, responsive: true, maintainAspectRatio: false, parsing: true,
        interaction: { mode: "nearest", axis: "x", intersect: false },
        scales: scales,
        plugins: {
          legend: {
            display: false,
            labels: { filter: (item, cd) => cd.datasets[item.datasetIndex].svrobs.role === "mean" },
            onClick: toggleSeries,
          },
          tooltip: {
            filter: (item) => item.dataset.svrobs.role === "mean",
            callbacks: {
              title: (items) => {
                if (!items.length) return "";
                const v = items[0].parsed.x;
                const n0 = xField === "N" && factor > 1 ? ` · N0 = ${fmt(v * factor)}` : "";
                return `${data.x_label} = ${fmt(v)}${n0}`;
              },
              label: (item) => {
                const m = item.dataset.svrobs, j = item.dataIndex;
                return `${item.dataset.label}: ${fmt(m.mean[j])} ± ${fmt(m.std[j])} (n = ${m.count[j]})`;
              },
            },
          },
        },
      },
    });
    kit.axisTooltips(canvas, chart, {
      x: kit.describe(glossary, xField),
      x2: kit.describe(glossary, "N0"),
      y: kit.describe(glossary, data.metric),
    });
    return chart;
  }

  function setOptions(select, values, current, labels, titles) {
    const keep = values.includes(current) ? current : values[0];
    select.replaceChildren(...values.map((v) => {
      const o = document.createElement("option");
      o.value = v;
      o.textContent = labels ? labels(v) : v;
      if (titles) o.title = titles(v);
      o.selected = v === keep;
      return o;
    }));
  }

  function controls(card) {
    const q = (sel) => card.querySelector(sel);
    return {
      preset: q("#chart-preset"), metric: q("#chart-metric"), x: q("#chart-x"), panel: q("#chart-panel"),
      logy: q("#chart-logy"), logx: q("#chart-logx"), bands: q("#chart-bands"),
    };
  }

  function draw(card, data) {
    if (!data) return;
    const c = controls(card), glossary = kit.glossaryOf(card);
    const box = card.querySelector("#charts");
    registry.charts.forEach((ch) => ch.chart.destroy());
    registry.charts = [];
    box.replaceChildren();
    const want = card.dataset.wantPanel !== undefined ? card.dataset.wantPanel : c.panel.value;
    delete card.dataset.wantPanel;
    const keys = data.panels.map((p) => p.key);
    const titles = Object.fromEntries(data.panels.map((p) => [p.key, p.title]));
    // a panel the user chose (or "all"); else all of up to 6 panels, or the first
    const pick = keys.includes(want) || (want === "" && card.dataset.panelChosen) ? want :
      (keys.length > 6 ? keys[0] : "");
    setOptions(c.panel, [""].concat(keys), pick, (k) => (k === "" ? `all (${keys.length})` : titles[k]));
    const logY = c.logy.checked && data.positive;
    const yType = data.preset ? AXIS[data.scale] : (logY ? "logarithmic" : "linear");
    const opts = {
      bands: c.bands.checked, yType: yType, logY: yType === "logarithmic", glossary: glossary,
      logX: c.logx.checked && data.panels.every((p) => p.x.every((v) => v > 0)),
      n0Factor: Number(card.dataset.n0Factor || 1),
    };
    data.panels.filter((p) => !c.panel.value || p.key === c.panel.value).forEach((panel) => {
      const metric = kit.label(glossary, data.metric);
      const { canvas } = window.svrobsUi.chartPanel(box, panel.title,
        `${metric} (${data.metric}) against ${data.x_label}, ${panel.title}`, { panel: panel.key });
      const chart = makeChart(canvas, panel, data, opts);
      kit.figureLegend(chart);
      registry.charts.push({ panel: panel.key, chart: chart });
    });
  }

  function presetMode(card) {
    const c = controls(card), preset = c.preset ? c.preset.value : "";
    [c.metric, c.x, c.logy].forEach((el) => {
      el.disabled = Boolean(preset);
      el.closest("label").classList.toggle("disabled", Boolean(preset));
    });
    return preset;
  }

  function describe(data) {
    const p = data.preset;
    const note = document.getElementById("chart-band-note");
    if (!p) {
      note.textContent = "(mean ± std over the repetitions, from the stored summaries)";
      return "";
    }
    note.textContent = `(the report's ${p.figure}: ${data.metric}, from the stored summaries)`;
    const band = p.band ? ` Band: ${p.band}; the figure's band is the 5–95 % of the records.` : "";
    return ` ${data.scale} y axis, as the figure.${band}`;
  }

  const KEYS = ["preset", "metric", "x", "panel", "logy", "logx", "bands"];

  /* The view in the page's URL: what differs from the defaults (the keys of the page's
   * other views kept). */
  function viewQuery(card) {
    const c = controls(card), q = new URLSearchParams(location.search);
    KEYS.forEach((k) => q.delete(k));
    if (c.preset && c.preset.value) q.set("preset", c.preset.value);
    else {
      if (c.metric.value && c.metric.value !== "rmse_A") q.set("metric", c.metric.value);
      if (c.x.value !== "N") q.set("x", c.x.value);
      if (card.dataset.logyTouched) q.set("logy", c.logy.checked ? "1" : "0");
    }
    if (card.dataset.panelChosen) q.set("panel", c.panel.value);
    if (card.dataset.logxTouched) q.set("logx", c.logx.checked ? "1" : "0");
    if (!c.bands.checked) q.set("bands", "0");
    const s = q.toString();
    return location.pathname + (s ? `?${s}` : "");
  }

  /* The charts' part of the URL's query. */
  function chartSearch() {
    const q = new URLSearchParams(location.search);
    return KEYS.map((k) => `${k}=${q.get(k)}`).join("&");
  }
  // the charts' query of the view shown: a back/forward to another fragment of the same
  // view (the skip link's #main) or to another choice of the page's other views fires
  // popstate too, and changes nothing here
  let shownSearch = chartSearch();

  function remember(card) {
    const url = viewQuery(card);
    if (url !== location.pathname + location.search) history.pushState({ svrobsChart: true }, "", url);
    shownSearch = chartSearch();
  }

  /* Set the controls from the URL (on load and on back/forward). */
  function restore(card) {
    const c = controls(card), q = new URLSearchParams(location.search);
    if (c.preset) c.preset.value = q.get("preset") || "";
    if (c.preset && c.preset.value !== (q.get("preset") || "")) c.preset.value = "";
    const metric = q.get("metric") || DEFAULT_METRIC;
    if (![...c.metric.options].some((o) => o.value === metric)) {
      const o = document.createElement("option");  // asked as it is: the server says if it is no field
      o.value = metric;
      o.textContent = metric;
      o.dataset.unknown = "yes";
      c.metric.appendChild(o);
    }
    c.metric.value = metric;
    c.x.value = q.get("x") || "N";
    if (!c.x.value) c.x.value = "N";
    delete card.dataset.logyTouched;
    delete card.dataset.logxTouched;
    delete card.dataset.panelChosen;
    if (q.has("logy")) { c.logy.checked = q.get("logy") === "1"; card.dataset.logyTouched = "yes"; }
    if (q.has("logx")) { c.logx.checked = q.get("logx") === "1"; card.dataset.logxTouched = "yes"; }
    else c.logx.checked = c.x.value !== "N" && !c.preset?.value;
    c.bands.checked = q.get("bands") !== "0";
    if (q.has("panel")) { card.dataset.wantPanel = q.get("panel"); card.dataset.panelChosen = "yes"; }
    else card.dataset.wantPanel = "";
  }

  let sequence = 0;
  let haveMetrics = false;  // the field list came with an answer (asked until it has)
  const DEFAULT_METRIC = "rmse_A";

  /* The reason of a refused request: the JSON body's detail, else the status. */
  async function reason(r) {
    let detail = "", field = "";
    try {
      const body = await r.json();
      if (body && typeof body.detail === "string") detail = body.detail;
      if (body && typeof body.field === "string") field = body.field;
    } catch (e) { /* not JSON: the status alone */ }
    return { detail, field };
  }

  /* A refused field or axis (a link with ?metric=nope): the default one instead, the
   * URL made to name it, and the field list asked again. */
  function fallBack(card, why) {
    const c = controls(card);
    const asked = why.field === "x" ? c.x.value : c.metric.value;
    c.metric.querySelectorAll("option[data-unknown]").forEach((o) => o.remove());
    if (why.field === "x") c.x.value = "N";
    else c.metric.value = [...c.metric.options].some((o) => o.value === DEFAULT_METRIC) ?
      DEFAULT_METRIC : (c.metric.options[0] || {}).value;
    card.dataset.fallback = `Could not show ${why.field} = “${asked}” (HTTP 422: ${why.detail}); ` +
      `showing ${why.field === "x" ? "N" : c.metric.value} instead.`;
    const url = viewQuery(card);
    history.replaceState(history.state, "", url);
    shownSearch = chartSearch();
    load(card, true);
  }

  async function load(card, withMetrics) {
    const c = controls(card);
    const status = card.querySelector("#chart-status");
    const box = card.querySelector("#charts");
    const glossary = kit.glossaryOf(card);
    const preset = presetMode(card);
    const query = preset ? `preset=${encodeURIComponent(preset)}` :
      `metric=${encodeURIComponent(c.metric.value)}&x=${encodeURIComponent(c.x.value)}`;
    const url = `${card.dataset.chartUrl}?${query}` + (withMetrics || !haveMetrics ? "&metrics=1" : "");
    const mine = ++sequence;
    registry.requests += 1;
    status.dataset.state = "loading";
    status.textContent = "Loading the chart data…";
    box.setAttribute("aria-busy", "true");
    card.dataset.state = "loading";
    let r, data, why = { detail: "", field: "" };
    try {
      r = await fetch(url, { credentials: "same-origin", headers: { Accept: "application/json" } });
      if (r.ok) data = await r.json(); else why = await reason(r);
    } catch (e) {
      r = { ok: false, status: "network error" };
    }
    if (mine !== sequence) {  // a newer request was sent meanwhile: its answer is the one shown
      registry.dropped += 1;
      return;
    }
    box.setAttribute("aria-busy", "false");
    card.dataset.state = "ready";
    status.dataset.state = "ready";
    if (!r.ok) {
      status.dataset.state = "error";
      status.textContent = `Could not load the chart data (HTTP ${r.status}${why.detail ? ": " + why.detail : ""}).`;
      registry.errors.push(r.status);
      const again = card.dataset.fallback;  // (the fallback itself refused: no second one)
      delete card.dataset.fallback;
      if (r.status === 422 && !preset && ["metric", "x"].includes(why.field) && !again) fallBack(card, why);
      return;
    }
    const fellBack = card.dataset.fallback || "";
    delete card.dataset.fallback;
    if (data.metrics) haveMetrics = true;
    const asked = new URLSearchParams(location.search).has("metric");
    if (data.metrics && data.metrics.length && !data.preset && !asked && !data.metrics.includes(data.metric)) {
      // the default field has no values in this job (rmse_A on measured data): the first that has
      setOptions(c.metric, data.metrics, data.metrics[0],
        (f) => `${kit.label(glossary, f)} · ${f}`, (f) => kit.describe(glossary, f));
      card.dataset.fallback = `${data.metric} has no values in this job; showing ${data.metrics[0]}.`;
      history.replaceState(history.state, "", viewQuery(card));
      shownSearch = chartSearch();
      return load(card, false);
    }
    if (data.metrics && data.metrics.length && !data.preset) {
      const shown = data.metrics.includes(data.metric) ? data.metrics : [data.metric].concat(data.metrics);
      setOptions(c.metric, shown, data.metric,
        (f) => `${kit.label(glossary, f)} · ${f}`, (f) => kit.describe(glossary, f));
    }
    if (data.metrics && c.preset) {  // presets of fields without data are hidden
      c.preset.querySelectorAll("option[data-field]").forEach((o) => {
        o.hidden = !data.metrics.includes(o.dataset.field);
      });
    }
    if (!data.preset && !card.dataset.logyTouched) c.logy.checked = data.positive;
    card.querySelector("#chart-field-help").textContent = kit.describe(glossary, data.metric);
    registry.data = data;
    if (!data.panels.length) {
      describe(data);
      status.textContent = data.preset ? "This figure series has no data in the job's summaries." :
        data.status === "succeeded" ? "No summaries stored." :
        "No summaries yet: a group appears when the cells of all its repetitions are done.";
    } else {
      const partial = data.status === "succeeded" ? "" : ` (job ${data.status}: the groups stored so far)`;
      status.textContent = `${data.groups} summary groups, ${data.panels.length} panel(s)${partial}.` +
        (describe(data) || (data.positive ? "" : " Some means are ≤ 0: linear y axis."));
    }
    if (fellBack) status.textContent = `${fellBack} ${status.textContent}`;
    draw(card, data);
    registry.loads += 1;
    card.dataset.loads = String(registry.loads);
  }

  function init() {
    const card = document.getElementById("charts-card");
    if (!card || typeof Chart === "undefined") return;
    const c = controls(card);
    card.querySelector("#chart-controls").addEventListener("submit", (e) => e.preventDefault());
    const fresh = () => {  // a new field or axis: log scales follow the data again
      delete card.dataset.logyTouched;
      delete card.dataset.logxTouched;
      delete card.dataset.panelChosen;
      c.panel.value = "";
      card.dataset.wantPanel = "";
      c.logx.checked = c.x.value !== "N" && !(c.preset && c.preset.value);
    };
    c.metric.addEventListener("change", () => { delete card.dataset.logyTouched; remember(card); load(card); });
    if (c.preset) c.preset.addEventListener("change", () => { fresh(); remember(card); load(card); });
    c.x.addEventListener("change", () => { fresh(); remember(card); load(card); });
    c.logy.addEventListener("change", () => { card.dataset.logyTouched = "yes"; remember(card); draw(card, registry.data); });
    c.logx.addEventListener("change", () => { card.dataset.logxTouched = "yes"; remember(card); draw(card, registry.data); });
    c.panel.addEventListener("change", () => { card.dataset.panelChosen = "yes"; remember(card); draw(card, registry.data); });
    c.bands.addEventListener("change", () => { remember(card); draw(card, registry.data); });
    [["#chart-panel-prev", -1], ["#chart-panel-next", 1]].forEach(([sel, step]) => {
      card.querySelector(sel).addEventListener("click", () => {  // one panel after another
        const n = c.panel.options.length - 1;  // (the first option is "all")
        if (n < 1) return;
        const i = c.panel.selectedIndex <= 0 ? (step > 0 ? 1 : n) : ((c.panel.selectedIndex - 1 + step + n) % n) + 1;
        c.panel.selectedIndex = i;
        card.dataset.panelChosen = "yes";
        remember(card);
        draw(card, registry.data);
      });
    });
    window.addEventListener("popstate", () => {
      if (chartSearch() === shownSearch) return;
      shownSearch = chartSearch();
      restore(card);
      load(card);
    });
    document.addEventListener("svrobs:theme", () => draw(card, registry.data));
    document.body.addEventListener("svrobs:job-finished", () => load(card, true));
    // while the job runs: reload when the progress card says more cells are done
    let cells = null;
    document.body.addEventListener("htmx:afterSwap", (e) => {
      const p = document.getElementById("job-progress");
      if (!p || e.detail.target.id !== "job-progress") return;
      if (cells !== null && p.dataset.cellsDone !== cells && p.dataset.status !== "succeeded") load(card, true);
      cells = p.dataset.cellsDone;
    });
    const p = document.getElementById("job-progress");
    if (p) cells = p.dataset.cellsDone;
    restore(card);
    load(card, true);
  }

  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", init);
  else init();
})();
