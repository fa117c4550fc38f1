/* The compare page's chart: the rows of GET /api/v1/compare (embedded in
 * #compare-card's data-compare) as one line per job and remaining group field, the
 * mean against the chosen x field. Points with a null mean are left out. */
(function () {
  "use strict";
  const card = document.getElementById("compare-card");
  if (!card || !window.Chart) return;
  const data = JSON.parse(card.dataset.compare);
  const rest = data.by.filter((b) => b !== data.x);
  const series = new Map();
  for (const r of data.rows) {
    if (r.mean === null || r[data.x] === null) continue;
    const label = [`job ${r.job_id}`].concat(rest.map((b) => `${b}=${r[b] === null ? "–" : r[b]}`)).join(" · ");
    if (!series.has(label)) series.set(label, { job: r.job_id, points: [], rows: [] });
    series.get(label).points.push({ x: r[data.x], y: r.mean });
    series.get(label).rows.push(r);
  }
  const palette = ["#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf"];
  const datasets = Array.from(series, ([label, s], i) => {
    const order = s.points.map((p, k) => k).sort((a, b) => s.points[a].x - s.points[b].x);
    return {
      label,
      data: order.map((k) => s.points[k]),
      svrobs: { job: s.job, rows: order.map((k) => s.rows[k]) },
      borderColor: palette[i % palette.length],
      backgroundColor: palette[i % palette.length],
      borderDash: s.job === data.jobs[0] ? [] : [6, 3],
      tension: 0,
    };
  });
  const positive = datasets.every((d) => d.data.every((p) => p.y > 0));
  const chart = new window.Chart(document.getElementById("compare-chart"), {
    type: "line",
    data: { datasets },
    options: {
      animation: false,
      parsing: false,
      scales: {
        x: { type: "linear", title: { display: true, text: data.x } },
        y: { type: positive ? "logarithmic" : "linear", title: { display: true, text: data.metric } },
      },
      plugins: {
        tooltip: {
          callbacks: {
            label: (item) => {
              const r = item.dataset.svrobs.rows[item.dataIndex];
              return `${item.dataset.label}: ${r.mean.toPrecision(4)} ± ${r.std.toPrecision(3)} (n = ${r.count})`;
            },
          },
        },
      },
    },
  });
  window.svrobsCompare = { chart, data };
  card.dataset.ready = "yes";
})();
