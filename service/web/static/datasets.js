/* svrobs datasets pages. The upload form sends its file with XMLHttpRequest so that a
 * progress bar follows the bytes sent (xhr.upload's progress events), the CSRF token in
 * the X-CSRF-Token header; a refused file's error is shown beside its field. The
 * dataset page plots its first rollouts, one Chart.js chart per channel (states,
 * then inputs), one line per rollout (a colour and dash pattern each), from
 * /datasets/{id}/plot-data, in the theme's colours with a keyboard legend (window.svrobsChartKit), drawn again when the theme
 * changes. What is drawn is kept in window.svrobsDataset so that tests can read it. */
(function () {
  "use strict";

  const registry = { charts: [], upload: { progress: [] }, loads: 0 };
  window.svrobsDataset = registry;

  function bytes(n) {
    if (n < 2 ** 10) return `${n} B`;
    if (n < 2 ** 20) return `${(n / 2 ** 10).toFixed(1)} KB`;
    return `${(n / 2 ** 20).toFixed(1)} MB`;
  }

  function clearErrors(form) {
    form.querySelectorAll(".field-error").forEach((p) => { p.hidden = true; p.textContent = ""; });
    form.querySelectorAll(".invalid").forEach((el) => {
      el.classList.remove("invalid");
      el.removeAttribute("aria-invalid");
    });
  }

  function showError(form, field, message) {
    const slot = (field && form.querySelector(`#err-${CSS.escape(field)}`)) || form.querySelector("#err-form");
    slot.textContent = field ? `${field}: ${message}` : message;
    slot.hidden = false;
    const input = field && form.querySelector(`[name="${CSS.escape(field)}"]`);
    if (input) {
      input.classList.add("invalid");
      input.setAttribute("aria-invalid", "true");
      input.focus();
    }
  }

  function setupUpload(form) {
    const bar = form.querySelector("#upload-progress");
    const status = form.querySelector("#upload-status");
    const button = form.querySelector("#upload-button");
    form.addEventListener("submit", (e) => {
      e.preventDefault();
      clearErrors(form);
      const data = new FormData(form);
      for (const [key, value] of [...data.entries()]) {
        if (typeof value === "string" && value.trim() === "") data.delete(key);  // not given
      }
      const xhr = new XMLHttpRequest();
      xhr.open("POST", form.action);
      xhr.setRequestHeader("X-CSRF-Token", form.dataset.csrf);
      xhr.setRequestHeader("Accept", "application/json");
      xhr.responseType = "json";
      registry.upload = { progress: [], status: null };
      bar.hidden = false;
      bar.value = 0;
      button.disabled = true;
      status.textContent = "Uploading…";
      xhr.upload.addEventListener("progress", (ev) => {
        if (!ev.lengthComputable) return;
        bar.value = (100 * ev.loaded) / ev.total;
        registry.upload.progress.push([ev.loaded, ev.total]);
        status.textContent = `${Math.floor(bar.value)} % of ${bytes(ev.total)} sent`;
      });
      xhr.upload.addEventListener("load", () => {
        bar.value = 100;
        status.textContent = "Sent; checking and storing the file…";
      });
      xhr.addEventListener("load", () => {
        const body = xhr.response || {};
        registry.upload.status = xhr.status;
        if (xhr.status === 201) {
          status.textContent = "Stored.";
          window.location.assign(body.url);
          return;
        }
        button.disabled = false;
        bar.hidden = true;
        status.textContent = "";
        showError(form, body.field, body.detail || `The upload failed (HTTP ${xhr.status}).`);
      });
      xhr.addEventListener("error", () => {
        button.disabled = false;
        bar.hidden = true;
        status.textContent = "";
        showError(form, null, "The upload failed: the server could not be reached.");
      });
      xhr.send(data);
    });
  }

  function chartFor(box, title, lines, xLabel) {
    const kit = window.svrobsChartKit, palette = kit.palette();
    const { canvas } = window.svrobsUi.chartPanel(
      box, title, `${title} against ${xLabel}, ${lines.length} rollouts`, { channel: title });
    const chart = new Chart(canvas, {
      type: "line",
      data: {
        datasets: lines.map((ln, i) => ({
          label: `rollout ${ln.rollout}`, data: ln.points, borderColor: palette[i % palette.length],
          backgroundColor: palette[i % palette.length], borderWidth: 1.5, pointRadius: 0, borderDash: kit.style(i).borderDash,
          stepped: ln.stepped ? "before" : false, svrobs: { rollout: ln.rollout, series: i, legend: true },
        })),
      },
      options: {
        animation: false, responsive: true, maintainAspectRatio: false,
        interaction: { mode: "nearest", axis: "x", intersect: false },
        scales: { x: kit.axis("linear", xLabel), y: kit.axis("linear", title) },
        plugins: { legend: { display: false } },
      },
    });
    kit.figureLegend(chart);
    return chart;
  }

  /* One chart per channel of the plot data, in place of those drawn before. */
  function drawPlot(card, data) {
    const dt = data.sample_time;
    const xLabel = dt ? "time (s)" : "step k";
    const at = (k) => (dt ? k * dt : k);
    const box = card.querySelector("#rollout-charts");
    registry.charts.forEach((c) => c.chart.destroy());
    box.replaceChildren();
    registry.charts = [];
    const channels = data.state_names.map((name, j) => ({ name, kind: "state", j, of: data.X }))
      .concat(data.input_names.map((name, j) => ({ name, kind: "input", j, of: data.U })));
    channels.forEach((ch) => {
      const lines = ch.of.map((rows, i) => ({
        rollout: i, stepped: ch.kind === "input",
        points: rows.map((row, k) => ({ x: at(k), y: row[ch.j] })),
      }));
      const chart = chartFor(box, `${ch.name} (${ch.kind})`, lines, xLabel);
      registry.charts.push({ channel: ch.name, kind: ch.kind, chart: chart,
        lines: lines.map((l) => ({ rollout: l.rollout, points: l.points.map((p) => [p.x, p.y]) })) });
    });
    return xLabel;
  }

  async function loadPlot(card) {
    const note = card.querySelector("#plot-note");
    const r = await fetch(card.dataset.plotUrl, { credentials: "same-origin", headers: { Accept: "application/json" } });
    if (!r.ok) {
      note.textContent = `Could not load the rollouts (HTTP ${r.status}).`;
      return;
    }
    const data = await r.json();
    const xLabel = drawPlot(card, data);
    const cut = data.cut ? `, each cut to its first ${data.steps.toLocaleString("en")} steps` : "";
    note.textContent = `(the first ${data.shown} of ${data.rollouts} rollouts${cut}, each channel against ${xLabel})`;
    document.addEventListener("svrobs:theme", () => drawPlot(card, data));  // the theme's colours
    registry.loads += 1;
    card.dataset.loads = String(registry.loads);
  }

  function init() {
    const form = document.getElementById("upload-form");
    if (form) setupUpload(form);
    const plot = document.getElementById("dataset-plot");
    if (plot && typeof Chart !== "undefined") loadPlot(plot);
  }

  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", init);
  else init();
})();
