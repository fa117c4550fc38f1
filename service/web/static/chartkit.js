/* What the charts share (window.svrobsChartKit): colours of the current theme, a
 * dash pattern and point style per series (a second channel besides colour), number
 * format, the record glossary's axis titles and tooltips, a legend of buttons (Tab to a
 * line, Enter or Space hides or shows it, with its band; each swatch drawn with the
 * line's colour, dash and marker), and the data table under a chart of a figure
 * (window.svrobsUi.chartPanel), filled from its datasets whenever they change. A
 * dataset's svrobs.series groups a line with its band; svrobs.role is "mean" for the
 * line (or svrobs.legend lists it). */
(function () {
  "use strict";

  const PALETTE = ["#1f5fa8", "#c0392b", "#2e8b57", "#8e44ad", "#d68910", "#17a2b8",
    "#6c757d", "#e83e8c", "#5d4037", "#20c997"];
  const DARK_PALETTE = ["#7db4f5", "#ff8a80", "#7fd49a", "#c39bf0", "#f0b860", "#5fd3e6",
    "#b8c2cc", "#f68fc0", "#c8a27c", "#5fe0b8"];

  // solid, dashed, dotted, dash-dot, dash-dot-dot; and markers told apart by shape
  const DASHES = [[], [8, 4], [2, 3], [12, 3, 2, 3], [12, 3, 2, 3, 2, 3]];
  const POINTS = ["circle", "rect", "triangle", "rectRot", "crossRot", "star", "cross"];
  const TABLE_ROWS = 500;  // rows of a chart's data table; the rest are left out

  /* The ``i``-th series' dash pattern and point style (35 pairs before they repeat). */
  function style(i) {
    return { borderDash: DASHES[i % DASHES.length], pointStyle: POINTS[i % POINTS.length] };
  }

  function palette() {
    return window.svrobsTheme && window.svrobsTheme() === "dark" ? DARK_PALETTE : PALETTE;
  }

  function alpha(hex, a) {
    const n = parseInt(hex.slice(1), 16);
    return `rgba(${(n >> 16) & 255}, ${(n >> 8) & 255}, ${n & 255}, ${a})`;
  }

  /* ``v`` to ``digits`` significant digits (4 unless told). */
  function fmt(v, digits) {
    if (v === null || v === undefined) return "–";
    const d = digits || 4, a = Math.abs(v);
    return a !== 0 && (a < 1e-3 || a >= 1e5) ? v.toExponential(d - 1) : Number(v.toPrecision(d)).toString();
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
      b.append(swatch(chart, d), document.createTextNode(typeof d.svrobs.legend === "string" ? d.svrobs.legend : d.label));
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

  const SVG = "http://www.w3.org/2000/svg";

  function svg(tag, attrs) {
    const el = document.createElementNS(SVG, tag);
    Object.entries(attrs).forEach(([k, v]) => el.setAttribute(k, String(v)));
    return el;
  }

  /* The outline of a Chart.js point style of radius r at (x, y), as an SVG element. */
  function marker(pointStyle, x, y, r) {
    const at = (pts) => pts.map(([dx, dy]) => `${x + dx * r},${y + dy * r}`).join(" ");
    const lines = (pts) => pts.map(([a, b, c, e]) => `M${x + a * r} ${y + b * r}L${x + c * r} ${y + e * r}`).join("");
    const PLUS = [[-1, 0, 1, 0], [0, -1, 0, 1]], TIMES = [[-0.7, -0.7, 0.7, 0.7], [-0.7, 0.7, 0.7, -0.7]];
    switch (pointStyle) {
      case "rect": return svg("rect", { x: x - 0.8 * r, y: y - 0.8 * r, width: 1.6 * r, height: 1.6 * r });
      case "triangle": return svg("polygon", { points: at([[0, -1.1], [1, 0.7], [-1, 0.7]]) });
      case "rectRot": return svg("polygon", { points: at([[0, -1.1], [1.1, 0], [0, 1.1], [-1.1, 0]]) });
      case "cross": return svg("path", { d: lines(PLUS) });
      case "crossRot": return svg("path", { d: lines(TIMES) });
      case "star": return svg("path", { d: lines(PLUS.concat(TIMES)) });
      default: return svg("circle", { cx: x, cy: y, r: r });
    }
  }

  /* A legend entry's swatch: a bar's block; else the dataset's line (its colour and
   * dash) unless it draws none (a scatter), with its marker where it draws points;
   * data-dash and data-point say which. */
  function swatch(chart, d) {
    const colour = d.borderColor || d.backgroundColor;
    const el = svg("svg", { class: "swatch", width: 30, height: 14, viewBox: "0 0 30 14", "aria-hidden": "true", focusable: "false" });
    const kind = d.type || chart.config.type;
    if (kind === "bar") {
      el.appendChild(svg("rect", { x: 9, y: 1, width: 12, height: 12, fill: colour }));
      return el;
    }
    const dash = (d.borderDash || []).join(" ");
    const lined = d.showLine !== false && kind !== "scatter";
    if (lined) {
      el.appendChild(svg("line", { x1: 1, y1: 7, x2: 29, y2: 7, stroke: colour, "stroke-width": 2.5, "stroke-dasharray": dash || "none" }));
      el.dataset.dash = dash;
    }
    const radius = d.pointRadius === undefined ? 3 : d.pointRadius;
    if (radius > 0 || !lined) {
      const point = d.pointStyle || "circle";
      const m = marker(point, 15, 7, 4.5);
      const open = point === "cross" || point === "crossRot" || point === "star";
      m.setAttribute("fill", open ? "none" : colour);
      m.setAttribute("stroke", colour);
      m.setAttribute("stroke-width", open ? 1.8 : 1);
      el.appendChild(m);
      el.dataset.point = point;
    }
    return el;
  }

  /* The legend of a chart of a figure (ui.chartPanel): under the chart, above its data
   * table. */
  function figureLegend(chart) {
    chart.canvas.closest(".chart-box").after(legend(chart));
  }

  /* A chart's plotted numbers as rows: the x values ascending, then for each dataset its
   * y at that x (null where it has none); a dataset with several points at one x (a
   * scatter) gives that x as many rows. */
  function tableRows(datasets) {
    const byX = datasets.map((d) => {
      const m = new Map();
      (d.data || []).forEach((p) => {
        if (!p || p.x === null || p.x === undefined) return;
        if (!m.has(p.x)) m.set(p.x, []);
        m.get(p.x).push(p.y);
      });
      return m;
    });
    const xs = [...new Set(byX.flatMap((m) => [...m.keys()]))].sort((a, b) => a - b);
    return xs.flatMap((x) => {
      const n = Math.max(...byX.map((m) => (m.get(x) || []).length));
      return Array.from({ length: n }, (_, k) => [x].concat(byX.map((m) => {
        const y = (m.get(x) || [])[k];
        return y === undefined ? null : y;
      })));
    });
  }

  /* The page's data exports (links marked data-export), as new links for a note. */
  function exportLinks() {
    return [...document.querySelectorAll("a[data-export]")].map((a) => {
      const link = document.createElement("a");
      link.setAttribute("href", a.getAttribute("href"));
      link.textContent = a.textContent.trim();
      if (a.hasAttribute("download")) link.setAttribute("download", "");
      return link;
    });
  }

  /* Fill the data table of ``chart``'s figure (details.chart-data of ui.chartPanel):
   * its caption, the x axis and one column per dataset, the numbers as plotted (6
   * significant digits), at most TABLE_ROWS rows with a note of those left out. Built
   * again only when the numbers or labels differ from those shown. */
  function fillTable(chart) {
    const fig = chart.canvas.closest("figure");
    const box = fig && fig.querySelector("details.chart-data");
    if (!box) return;
    const sets = chart.data.datasets;
    const xTitle = ((chart.options.scales.x || {}).title || {}).text || "x";
    const head = [xTitle].concat(sets.map((d) => d.label));
    const rows = tableRows(sets);
    const key = JSON.stringify([head, rows]);
    if (box.dataset.key === key) return;
    box.dataset.key = key;
    const table = box.querySelector("table");
    const caption = document.createElement("caption");
    caption.textContent = `Data of the chart: ${chart.canvas.getAttribute("aria-label")}`;
    const tr = document.createElement("tr");
    head.forEach((h) => {
      const th = document.createElement("th");
      th.scope = "col";
      th.textContent = h;
      tr.appendChild(th);
    });
    const thead = document.createElement("thead");
    thead.appendChild(tr);
    const tbody = document.createElement("tbody");
    rows.slice(0, TABLE_ROWS).forEach((row) => {
      const r = tbody.insertRow();
      const th = document.createElement("th");
      th.scope = "row";
      th.textContent = fmt(row[0], 6);
      r.appendChild(th);
      row.slice(1).forEach((y) => {
        const td = r.insertCell();
        td.className = "num";
        td.textContent = fmt(y, 6);
      });
    });
    table.replaceChildren(caption, thead, tbody);
    const note = box.querySelector(".chart-data-note");
    const left = rows.length - TABLE_ROWS;
    note.hidden = left <= 0;
    if (left <= 0) { note.replaceChildren(); return; }
    const links = exportLinks();
    note.replaceChildren(`The first ${TABLE_ROWS} of ${rows.length.toLocaleString("en")} rows; ` +
      `${left.toLocaleString("en")} left out` + (links.length ? "; see the page's exports: " : "."));
    links.forEach((a, i) => note.append(i ? ", " : "", a));
    if (links.length) note.append(".");
  }

  if (typeof Chart !== "undefined") Chart.register({ id: "svrobsDataTable", afterUpdate: fillTable });

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
    palette, style, alpha, fmt, coord, themeColours, axis, glossaryOf, label, axisTitle, describe,
    axisTooltips, setSeries, legend, figureLegend, band,
  };
})();
