/* svrobs job page charts: Chart.js line charts of a summary field against N, σ_w or γ,
 * one panel per remaining grid coordinate, one line per estimator/γ with a mean ± std
 * band. The data come from /jobs/{id}/chart-data (the stored summaries). Every plotted
 * chart is kept in window.svrobsCharts so that tests can read what is drawn. */
(function () {
  "use strict";

  const PALETTE = ["#1f5fa8", "#c0392b", "#2e8b57", "#8e44ad", "#d68910", "#17a2b8",
    "#6c757d", "#e83e8c", "#5d4037", "#20c997"];
  const registry = { charts: [], data: null, loads: 0, errors: [] };
  window.svrobsCharts = registry;

  function alpha(hex, a) {
    const n = parseInt(hex.slice(1), 16);
    return `rgba(${(n >> 16) & 255}, ${(n >> 8) & 255}, ${n & 255}, ${a})`;
  }

  function fmt(v) {
    if (v === null || v === undefined) return "–";
    const a = Math.abs(v);
    return a !== 0 && (a < 1e-3 || a >= 1e5) ? v.toExponential(3) : Number(v.toPrecision(4)).toString();
  }

  function points(xs, ys) {
    return xs.map((x, i) => ({ x: x, y: ys[i] }));
  }

  function datasets(panel, logY, bands) {
    const out = [];
    panel.series.forEach((s, i) => {
      const color = PALETTE[i % PALETTE.length];
      const hi = s.mean.map((m, j) => (m === null || s.std[j] === null ? null : m + s.std[j]));
      const lo = s.mean.map((m, j) => {
        if (m === null || s.std[j] === null) return null;
        const v = m - s.std[j];
        return logY && v <= 0 ? null : v; // a log axis has no room for mean - std <= 0
      });
      const meta = { series: i, estimator: s.estimator, gamma: s.gamma, mean: s.mean, std: s.std, count: s.count };
      out.push({
        label: s.label, data: points(panel.x, s.mean), borderColor: color,
        backgroundColor: color, borderWidth: 2, pointRadius: 3, borderDash: s.flat ? [6, 4] : [],
        svrobs: Object.assign({ role: "mean" }, meta), spanGaps: false,
      });
      if (!bands) return;
      out.push({
        label: s.label + " + std", data: points(panel.x, hi), borderWidth: 0, pointRadius: 0,
        pointHitRadius: 0, fill: false, borderColor: "transparent", svrobs: { role: "band", series: i },
      });
      out.push({
        label: s.label + " − std", data: points(panel.x, lo), borderWidth: 0, pointRadius: 0,
        pointHitRadius: 0, fill: "-1", backgroundColor: alpha(color, 0.1),
        borderColor: "transparent", svrobs: { role: "band", series: i },
      });
    });
    return out;
  }

  function toggleSeries(e, item, legend) {
    const chart = legend.chart;
    const series = chart.data.datasets[item.datasetIndex].svrobs.series;
    const show = !chart.isDatasetVisible(item.datasetIndex);
    chart.data.datasets.forEach((d, k) => {
      if (d.svrobs.series === series) chart.setDatasetVisibility(k, show);
    });
    chart.update();
  }

  function makeChart(canvas, panel, data, opts) {
    return new Chart(canvas, {
      type: "line",
      data: { datasets: datasets(panel, opts.logY, opts.bands) },
      options: {
        animation: false, responsive: true, maintainAspectRatio: false, parsing: true,
        interaction: { mode: "nearest", axis: "x", intersect: false },
        scales: {
          x: { type: opts.logX ? "logarithmic" : "linear", title: { display: true, text: data.x_label } },
          y: { type: opts.logY ? "logarithmic" : "linear", title: { display: true, text: data.metric } },
        },
        plugins: {
          legend: {
            labels: { filter: (item, cd) => cd.datasets[item.datasetIndex].svrobs.role === "mean" },
            onClick: toggleSeries,
          },
          tooltip: {
            filter: (item) => item.dataset.svrobs.role === "mean",
            callbacks: {
              title: (items) => items.length ? `${data.x_label} = ${fmt(items[0].parsed.x)}` : "",
              label: (item) => {
                const m = item.dataset.svrobs, j = item.dataIndex;
                return `${item.dataset.label}: ${fmt(m.mean[j])} ± ${fmt(m.std[j])} (n = ${m.count[j]})`;
              },
            },
          },
        },
      },
    });
  }

  function setOptions(select, values, current, labels) {
    const keep = values.includes(current) ? current : values[0];
    select.replaceChildren(...values.map((v) => {
      const o = document.createElement("option");
      o.value = v;
      o.textContent = labels ? labels(v) : v;
      o.selected = v === keep;
      return o;
    }));
  }

  function draw(card, data) {
    const box = card.querySelector("#charts");
    registry.charts.forEach((c) => c.chart.destroy());
    registry.charts = [];
    box.replaceChildren();
    const panelSel = card.querySelector("#chart-panel");
    const want = panelSel.value;
    const keys = data.panels.map((p) => p.key);
    const titles = Object.fromEntries(data.panels.map((p) => [p.key, p.title]));
    setOptions(panelSel, [""].concat(keys), want || (keys.length > 6 ? keys[0] : ""),
      (k) => (k === "" ? `all (${keys.length})` : titles[k]));
    const opts = {
      bands: card.querySelector("#chart-bands").checked,
      logY: card.querySelector("#chart-logy").checked && data.positive,
      logX: card.querySelector("#chart-logx").checked && data.panels.every((p) => p.x.every((v) => v > 0)),
    };
    data.panels.filter((p) => !panelSel.value || p.key === panelSel.value).forEach((panel) => {
      const fig = document.createElement("figure");
      fig.className = "chart-panel";
      fig.dataset.panel = panel.key;
      const h = document.createElement("h3");
      h.textContent = panel.title;
      const wrap = document.createElement("div");
      wrap.className = "chart-box";
      const canvas = document.createElement("canvas");
      canvas.setAttribute("role", "img");
      canvas.setAttribute("aria-label", `${data.metric} against ${data.x_label}, ${panel.title}`);
      wrap.appendChild(canvas);
      fig.append(h, wrap);
      box.appendChild(fig);
      registry.charts.push({ panel: panel.key, chart: makeChart(canvas, panel, data, opts) });
    });
  }

  async function load(card, resetLog, withMetrics) {
    const metric = card.querySelector("#chart-metric");
    const x = card.querySelector("#chart-x");
    const status = card.querySelector("#chart-status");
    const url = `${card.dataset.chartUrl}?metric=${encodeURIComponent(metric.value)}` +
      `&x=${encodeURIComponent(x.value)}` + (withMetrics ? "&metrics=1" : "");
    const r = await fetch(url, { credentials: "same-origin", headers: { Accept: "application/json" } });
    if (!r.ok) {
      status.textContent = `Could not load the chart data (HTTP ${r.status}).`;
      registry.errors.push(r.status);
      return;
    }
    const data = await r.json();
    if (data.metrics && data.metrics.length) setOptions(metric, data.metrics, data.metric);
    if (resetLog) {
      card.querySelector("#chart-logy").checked = data.positive;
      card.querySelector("#chart-logx").checked = data.x !== "N";
    }
    registry.data = data;
    if (!data.panels.length) {
      status.textContent = data.status === "succeeded" ? "No summaries stored." :
        "No summaries yet: they appear as work units finish.";
    } else {
      const partial = data.status === "succeeded" ? "" : ` (job ${data.status}: the groups stored so far)`;
      status.textContent = `${data.groups} summary groups, ${data.panels.length} panel(s)${partial}.` +
        (data.positive ? "" : " Some means are ≤ 0: linear y axis.");
    }
    draw(card, data);
    registry.loads += 1;
    card.dataset.loads = String(registry.loads);
  }

  function init() {
    const card = document.getElementById("charts-card");
    if (!card || typeof Chart === "undefined") return;
    const form = card.querySelector("#chart-controls");
    form.addEventListener("submit", (e) => e.preventDefault());
    card.querySelector("#chart-metric").addEventListener("change", () => load(card, true));
    card.querySelector("#chart-x").addEventListener("change", () => {
      card.querySelector("#chart-panel").value = "";
      load(card, true);
    });
    ["#chart-panel", "#chart-logy", "#chart-logx", "#chart-bands"].forEach((sel) =>
      card.querySelector(sel).addEventListener("change", () => draw(card, registry.data)));
    document.body.addEventListener("svrobs:job-finished", () => load(card, false, true));
    load(card, true, true);
  }

  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", init);
  else init();
})();
