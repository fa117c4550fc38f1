/* A dataset job's validation card (the job page): GET /api/v1/jobs/{id}/validation
 * (the session's cookie), a table of each model's fit and test p-values per channel,
 * and for the chosen model and held-out rollout one chart per channel of the measured
 * values with the one-step predictions and the open-loop simulation, and one chart per
 * channel of the residual autocorrelation r_1..r_h with its ±band, in the theme's
 * colours, each with a keyboard legend (window.svrobsChartKit). The model and rollout
 * chosen are in the page's URL (?model=…&rollout=…). What is drawn is kept in
 * window.svrobsValidation for the tests. */
(function () {
  "use strict";

  const registry = { data: null, predictions: [], autocorrelation: [], loads: 0 };
  window.svrobsValidation = registry;
  const kit = window.svrobsChartKit;
  const ui = window.svrobsUi;
  const SERIES = { measured: 0, predicted: 1, simulated: 2, band: 3 };

  /* A series' colour in the current theme: the measured values in the theme's text
   * colour (dark on light, light on dark), the band in its muted one, the others of
   * its palette. */
  function colour(name) {
    if (name === "band") return kit.themeColours().fg;
    if (name === "measured") {
      return getComputedStyle(document.documentElement).getPropertyValue("--fg").trim() || "#1d232b";
    }
    return kit.palette()[name === "predicted" ? 0 : 1];
  }

  function fmt(v, digits) {
    if (v === null || v === undefined) return "–";
    return Number(v).toFixed(digits);
  }

  function pval(v) {
    if (v === null || v === undefined) return "–";
    const a = Math.abs(v);
    return a !== 0 && a < 1e-3 ? v.toExponential(1) : v.toFixed(3);
  }

  function label(m) {
    return m.gamma === null ? m.estimator : `${m.estimator} γ=${m.gamma}`;
  }

  function cell(tr, text, cls) {
    const td = document.createElement("td");
    td.textContent = text;
    if (cls) td.className = cls;
    tr.appendChild(td);
  }

  function table(el, data) {
    const channels = data.plots.channels;
    const head = ["model"].concat(...channels.map((c) => [`${c} one-step fit %`, `${c} simulation fit %`, `${c} Ljung-Box p`]));
    head.push("cross-correlation p (min)");
    const thead = document.createElement("thead");
    const hr = document.createElement("tr");
    head.forEach((h, i) => {
      const th = document.createElement("th");
      th.textContent = h;
      if (i) th.className = "num";
      hr.appendChild(th);
    });
    thead.appendChild(hr);
    const tbody = document.createElement("tbody");
    data.models.forEach((m) => {
      const v = m.validation;
      const tr = document.createElement("tr");
      tr.dataset.model = label(m);
      cell(tr, label(m));
      channels.forEach((_, j) => {
        cell(tr, v ? fmt(v.one_step_fit[j], 1) : "–", "num");
        cell(tr, v ? fmt(v.simulation_fit_pooled[j], 1) : "–", "num");
        const p = v ? v.ljung_box_p[j] : null;
        cell(tr, pval(p), "num" + (p !== null && p < 0.01 ? " p-low" : ""));
      });
      const cross = v ? v.cross_p.flat().filter((p) => p !== null) : [];
      cell(tr, cross.length ? pval(Math.min(...cross)) : "–", "num");
      tbody.appendChild(tr);
    });
    el.replaceChildren(thead, tbody);
  }

  /* A chart of ``config`` in a new figure of ``box``, its legend of buttons under it. */
  function chartIn(box, title, config) {
    const { canvas } = ui.chartPanel(box, title, title, { channel: title });
    config.options.plugins = { legend: { display: false } };
    const chart = new Chart(canvas, config);
    kit.figureLegend(chart);
    return chart;
  }

  /* A line of the series ``name``, in its colour and dash (listed in the legend unless
   * svrobs says otherwise). */
  function line(name, points, extra) {
    return Object.assign({ label: name, data: points, borderColor: colour(name), backgroundColor: colour(name),
      borderWidth: 1.5, pointRadius: 0, borderDash: kit.style(SERIES[name]).borderDash,
      svrobs: { role: name, series: SERIES[name], legend: true } }, extra || {});
  }

  function draw(card) {
    const data = registry.data;
    registry.predictions.forEach((c) => c.chart.destroy());
    registry.autocorrelation.forEach((c) => c.chart.destroy());
    registry.predictions = [];
    registry.autocorrelation = [];
    const pbox = card.querySelector("#prediction-charts");
    const abox = card.querySelector("#autocorrelation-charts");
    pbox.replaceChildren();
    abox.replaceChildren();
    const m = data.models[Number(card.querySelector("#val-model").value) || 0];
    const v = m && m.validation;
    if (!v) return;
    const r = Number(card.querySelector("#val-rollout").value) || 0;
    const dt = data.plots.sample_time;
    const at = (k) => (dt ? k * dt : k);
    const xLabel = dt ? "time (s)" : "step k";
    const measured = data.plots.measured[r] || [];
    data.plots.channels.forEach((ch, j) => {
      const series = {
        measured: measured.map((row, k) => ({ x: at(k), y: row[j] })),
        predicted: (v.predicted[r] || []).map((row, k) => ({ x: at(k + 1), y: row[j] })),
        simulated: (v.simulated[r] || []).map((row, k) => ({ x: at(k), y: row[j] })),
      };
      const chart = chartIn(pbox, `${ch}: held-out rollout ${data.plots.rollouts[r]}`, {
        type: "line",
        data: { datasets: [line("measured", series.measured, { borderWidth: 2 }),
          line("predicted", series.predicted), line("simulated", series.simulated)] },
        options: { animation: false, responsive: true, maintainAspectRatio: false,
          interaction: { mode: "nearest", axis: "x", intersect: false },
          scales: { x: kit.axis("linear", xLabel), y: kit.axis("linear", ch) } },
      });
      const points = {};
      Object.keys(series).forEach((k) => { points[k] = series[k].map((p) => [p.x, p.y]); });
      registry.predictions.push({ channel: ch, rollout: data.plots.rollouts[r], model: label(m), chart, points });
      const lags = v.autocorrelation[j].map((_, i) => i + 1);
      const band = v.band;
      const bar = colour("predicted");
      const ac = chartIn(abox, `${ch}: residual autocorrelation (Ljung-Box p = ${pval(v.ljung_box_p[j])})`, {
        type: "bar",
        data: { datasets: [
          { type: "bar", label: "r_k", data: lags.map((k, i) => ({ x: k, y: v.autocorrelation[j][i] })),
            backgroundColor: bar, borderColor: bar, svrobs: { role: "r", series: 0, legend: true } },
          line("band", lags.map((k) => ({ x: k, y: band })), { type: "line", label: "+99 % band",
            svrobs: { role: "band", series: SERIES.band, legend: "±99 % band" } }),
          line("band", lags.map((k) => ({ x: k, y: -band })), { type: "line", label: "−99 % band",
            svrobs: { role: "band", series: SERIES.band } }),
        ] },
        options: { animation: false, responsive: true, maintainAspectRatio: false,
          scales: { x: lagAxis(lags.length), y: kit.axis("linear", "r_k") } },
      });
      registry.autocorrelation.push({ channel: ch, model: label(m), chart: ac, r: v.autocorrelation[j], band });
    });
  }

  function lagAxis(h) {
    const a = kit.axis("linear", "lag k", { min: 0, max: h + 1 });
    a.ticks.stepSize = 1;
    return a;
  }

  /* The options of ``select``: value its index, text its label, data-key its key in
   * the URL. */
  function options(select, labels, keys) {
    select.replaceChildren(...labels.map((text, i) => {
      const o = document.createElement("option");
      o.value = String(i);
      o.textContent = text;
      o.dataset.key = keys[i];
      return o;
    }));
  }

  const CHOICES = { model: "#val-model", rollout: "#val-rollout" };

  /* The choices in the page's URL (the first of each list, the default, left out). */
  function remember(card) {
    const values = {};
    Object.entries(CHOICES).forEach(([key, sel]) => {
      const s = card.querySelector(sel);
      values[key] = s.selectedIndex > 0 ? s.selectedOptions[0].dataset.key : null;
    });
    ui.setQuery(values);
  }

  /* The choices of the URL, where the lists have them (else the first); true when one
   * changed. */
  function restore(card) {
    let changed = false;
    Object.entries(CHOICES).forEach(([key, sel]) => {
      const s = card.querySelector(sel), want = ui.queryValue(key);
      const i = Math.max([...s.options].findIndex((o) => o.dataset.key === want), 0);
      changed = changed || s.selectedIndex !== i;
      s.selectedIndex = i;
    });
    return changed;
  }

  async function init() {
    const card = document.getElementById("validation-card");
    if (!card || typeof Chart === "undefined") return;
    const note = card.querySelector("#validation-note");
    card.querySelector("#validation-controls").addEventListener("submit", (e) => e.preventDefault());
    const r = await fetch(card.dataset.validationUrl, { credentials: "same-origin", headers: { Accept: "application/json" } });
    if (!r.ok) {
      note.textContent = `Could not load the validation (HTTP ${r.status}).`;
      return;
    }
    const data = await r.json();
    registry.data = data;
    options(card.querySelector("#val-model"), data.models.map(label), data.models.map(label));
    options(card.querySelector("#val-rollout"), data.plots.rollouts.map((k) => `rollout ${k}`), data.plots.rollouts.map(String));
    table(card.querySelector("#validation-table"), data);
    restore(card);
    Object.values(CHOICES).forEach((sel) => card.querySelector(sel).addEventListener("change", () => {
      remember(card);
      draw(card);
    }));
    window.addEventListener("popstate", () => { if (restore(card)) draw(card); });
    const ex = data.excitation;
    card.querySelector("#validation-excitation").textContent = ex
      ? `Excitation of the ${ex.N0} training transitions: λ_min = ${ex.lambda_min === null ? "none" : Number(ex.lambda_min).toPrecision(3)}, condition number ${ex.cond === null ? "∞" : Number(ex.cond).toPrecision(3)}.`
      : "";
    const notes = card.querySelector("#validation-notes");
    const all = data.notes.concat(ex ? ex.notes : [], ...data.models.map((m) => (m.validation ? m.validation.notes : [])));
    notes.replaceChildren(...[...new Set(all)].map((t) => { const li = document.createElement("li"); li.textContent = t; return li; }));
    const held = data.plots.of;
    const steps = data.plots.cut ? `, each to its step ${data.plots.steps}` : "";
    note.textContent = held ? `(N = ${data.N}; ${held} held-out rollouts, the first ${data.plots.rollouts.length} plotted${steps})` : "(no held-out rollouts: holdout = 0)";
    draw(card);
    document.addEventListener("svrobs:theme", () => draw(card));  // the theme's colours
    registry.loads += 1;
    card.dataset.loads = String(registry.loads);
  }

  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", init);
  else init();
})();
