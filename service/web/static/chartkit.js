/* What the job page's and the compare page's charts share (window.svrobsChartKit):
 * colours of the current theme, number format, the record glossary's axis titles and
 * tooltips, and a legend of buttons (Tab to a line, Enter or Space hides or shows it,
 * with its band). A dataset's svrobs.series groups a line with its band;
 * svrobs.role is "mean" for the line (or svrobs.legend lists it). */
(function () {
  "use strict";

  const PALETTE = ["#1f5fa8", "#c0392b", "#2e8b57", "#8e44ad", "#d68910", "#17a2b8",
    "#6c757d", "#e83e8c", "#5d4037", "#20c997"];
  const DARK_PALETTE = ["#7db4f5", "#ff8a80", "#7fd49a", "#c39bf0", "#f0b860", "#5fd3e6",
    "#b8c2cc", "#f68fc0", "#c8a27c", "#5fe0b8"];

  function palette() {
    return window.svrobsTheme && window.svrobsTheme() === "dark" ? DARK_PALETTE : PALETTE;
  }

  function alpha(hex, a) {
    const n = parseInt(hex.slice(1), 16);
    return `rgba(${(n >> 16) & 255}, ${(n >> 8) & 255}, ${n & 255}, ${a})`;
  }

  function fmt(v) {
    if (v === null || v === undefined) return "–";
    const a = Math.abs(v);
    return a !== 0 && (a < 1e-3 || a >= 1e5) ? v.toExponential(3) : Number(v.toPrecision(4)).toString();
  }

  /* A grid coordinate's text: the σ_w key -1 of a dataset job that estimates σ_w is
   * "estimate" (service/web/fields.py coordinate), any other value its number. */
  function coord(field, v) { return field === "sigma_w" && v === -1 ? "estimate" : fmt(v); }

  function themeColours() {
    const css = getComputedStyle(document.documentElement);
    return { fg: css.getPropertyValue("--muted").trim() || "#56606b", line: css.getPropertyValue("--line").trim() || "#d9dee4" };
  }

  /* An axis of the theme's colours titled ``text``. */
  function axis(type, text, extra) {
    const c = themeColours();
    return Object.assign({
      type: type, title: { display: true, text: text, color: c.fg },
      ticks: { color: c.fg }, grid: { color: c.line },
    }, extra || {});
  }

  function glossaryOf(el) {
    return JSON.parse(el.dataset.glossary || "{}");
  }

  function label(glossary, f) {
    return (glossary[f] && glossary[f].label) || f;
  }

  function axisTitle(glossary, f, fallback) {
    const g = glossary[f];
    if (!g) return fallback || f;
    return g.unit && g.unit !== "true/false" ? `${g.label} [${g.unit}]` : g.label;
  }

  function describe(glossary, f) {
    const g = glossary[f];
    if (!g) return f;
    return `${f}: ${g.description}` + (g.unit ? ` [${g.unit}]` : "");
  }

  /* The axis titles' tooltips: the canvas's title is the field's description while the
   * pointer is over an axis (texts: {x, y, x2}). */
  function axisTooltips(canvas, chart, texts) {
    canvas.addEventListener("mousemove", (e) => {
      const r = canvas.getBoundingClientRect(), x = e.clientX - r.left, y = e.clientY - r.top;
      const a = chart.chartArea;
      let t = "";
      if (a && x < a.left) t = texts.y;
      else if (a && y > a.bottom) t = texts.x;
      else if (a && y < a.top && texts.x2) t = texts.x2;
      if (canvas.title !== t) canvas.title = t || "";
    });
  }

  /* A line with its band: hidden or shown together. */
  function setSeries(chart, series, show) {
    chart.data.datasets.forEach((d, k) => {
      if (d.svrobs.series === series) chart.setDatasetVisibility(k, show);
    });
    chart.update();
  }

  /* The legend as a list of buttons (aria-pressed: shown), for the lines of ``chart``:
   * each dataset of role "mean" or with svrobs.legend (true, or the text to show in
   * place of its label). */
  function legend(chart) {
    const ul = document.createElement("ul");
    ul.className = "legend";
    ul.setAttribute("aria-label", "lines (press to hide or show)");
    chart.data.datasets.forEach((d, k) => {
      if (d.svrobs.role !== "mean" && !d.svrobs.legend) return;
      const li = document.createElement("li");
      const b = document.createElement("button");
      b.type = "button";
      b.dataset.series = String(d.svrobs.series);
      b.setAttribute("aria-pressed", String(chart.isDatasetVisible(k)));
      const sw = document.createElement("span");
      sw.className = "swatch" + (d.borderDash && d.borderDash.length ? " dash" : "");
      sw.style.borderTopColor = d.borderColor;
      sw.setAttribute("aria-hidden", "true");
      b.append(sw, document.createTextNode(typeof d.svrobs.legend === "string" ? d.svrobs.legend : d.label));
      b.addEventListener("click", () => {
        const show = b.getAttribute("aria-pressed") !== "true";
        setSeries(chart, d.svrobs.series, show);
        b.setAttribute("aria-pressed", String(show));
      });
      li.appendChild(b);
      ul.appendChild(li);
    });
    return ul;
  }

  /* The two band datasets (mean + std, then mean − std filled to it) of a line. */
  function band(label, data, mean, std, color, series, logY) {
    const hi = data.map((p, j) => ({ x: p.x, y: mean[j] === null || std[j] === null ? null : mean[j] + std[j] }));
    const lo = data.map((p, j) => {
      if (mean[j] === null || std[j] === null) return { x: p.x, y: null };
      const v = mean[j] - std[j];
      return { x: p.x, y: logY && v <= 0 ? null : v };  // a log axis has no room for mean − std ≤ 0
    });
    return [
      { label: label + " + std", data: hi, borderWidth: 0, pointRadius: 0, pointHitRadius: 0, fill: false,
        borderColor: "transparent", svrobs: { role: "band", series: series } },
      { label: label + " − std", data: lo, borderWidth: 0, pointRadius: 0, pointHitRadius: 0, fill: "-1",
        backgroundColor: alpha(color, 0.12), borderColor: "transparent", svrobs: { role: "band", series: series } },
    ];
  }

  window.svrobsChartKit = {
    palette, alpha, fmt, coord, themeColours, axis, glossaryOf, label, axisTitle, describe,
    axisTooltips, setSeries, legend, band,
  };
})();
