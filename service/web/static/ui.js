/* Behaviour every page shares: the header's menu button (narrow screens), the theme
 * toggle (auto -> dark -> light, remembered in localStorage), copy buttons
 * ([data-copy] copies the value of the element it names) and confirmations
 * (form[data-confirm] asks before it is sent); a form's error list takes the focus and
 * its links lead into their fields; a view's choices in the query string
 * (window.svrobsUi.setQuery); boxes that scroll take the focus; a part
 * htmx replaces keeps the focus, and one it could not update says why; the figure of a
 * chart (window.svrobsUi.chartPanel). */
(function () {
  "use strict";
  const root = document.documentElement;
  const THEMES = ["auto", "dark", "light"];

  function theme() { return root.dataset.theme || "auto"; }

  function effectiveTheme() {
    return root.dataset.scheme || "light";
  }
  window.svrobsTheme = effectiveTheme;

  function showTheme(button) {
    button.textContent = `Theme: ${theme()}`;
    button.setAttribute("aria-label", `Colour theme: ${theme()} (${effectiveTheme()}); change`);
  }

  function setTheme(t, button) {
    if (t === "auto") delete root.dataset.theme; else root.dataset.theme = t;
    try {
      if (t === "auto") localStorage.removeItem("svrobs-theme"); else localStorage.setItem("svrobs-theme", t);
    } catch (e) { /* not remembered */ }
    if (window.svrobsScheme) window.svrobsScheme();
    showTheme(button);
    document.dispatchEvent(new CustomEvent("svrobs:theme", { detail: effectiveTheme() }));
  }

  function initMenu() {
    const bar = document.querySelector("header.bar");
    const toggle = document.getElementById("menu-toggle");
    if (!bar || !toggle) return;
    toggle.addEventListener("click", () => {
      const open = !bar.classList.contains("open");
      bar.classList.toggle("open", open);
      toggle.setAttribute("aria-expanded", String(open));
    });
    document.addEventListener("keydown", (e) => {
      if (e.key === "Escape" && bar.classList.contains("open")) {
        bar.classList.remove("open");
        toggle.setAttribute("aria-expanded", "false");
        toggle.focus();
      }
    });
  }

  function initTheme() {
    const button = document.getElementById("theme-toggle");
    if (!button) return;
    showTheme(button);
    button.addEventListener("click", () => {
      setTheme(THEMES[(THEMES.indexOf(theme()) + 1) % THEMES.length], button);
    });
    if (window.matchMedia) {
      window.matchMedia("(prefers-color-scheme: dark)").addEventListener("change", () => {
        if (window.svrobsScheme) window.svrobsScheme();
        showTheme(button);
        document.dispatchEvent(new CustomEvent("svrobs:theme", { detail: effectiveTheme() }));
      });
    }
  }

  function initCopy(scope) {
    scope.querySelectorAll("[data-copy]").forEach((button) => {
      if (button.dataset.copyReady) return;
      button.dataset.copyReady = "yes";
      button.addEventListener("click", async () => {
        const source = document.getElementById(button.dataset.copy);
        const status = button.parentElement.querySelector(".copy-status");
        const text = source.value || source.textContent;
        let ok = false;
        try {
          await navigator.clipboard.writeText(text);
          ok = true;
        } catch (e) {
          source.select && source.select();
          ok = document.execCommand && document.execCommand("copy");
        }
        if (status) status.textContent = ok ? "Copied." : "Select the text and copy it.";
      });
    });
  }

  function initConfirm() {
    document.addEventListener("submit", (e) => {
      const form = e.target;
      if (form.dataset && form.dataset.confirm && !window.confirm(form.dataset.confirm)) {
        e.preventDefault();
        e.stopImmediatePropagation();
      }
    }, true);
  }

  /* A box that scrolls (a wide table, a long spec) can be scrolled with the keyboard. */
  function focusableScrollers(scope) {
    scope.querySelectorAll(".table-wrap, .scroll-x, pre.json").forEach((el) => {
      if (!el.hasAttribute("tabindex")) el.setAttribute("tabindex", "0");
    });
  }

  // the data tables open, by their chart's name: a chart drawn again keeps its table open
  const openTables = new Set();

  /* A chart's figure, appended to box: a heading, a canvas (role img, aria-label
   * label) in a .chart-box, and a "Data table" (details.chart-data, open when the
   * chart's table was) that the chart kit fills with the plotted numbers; data goes
   * into the figure's dataset. -> {fig, canvas} */
  function chartPanel(box, title, label, data) {
    const fig = document.createElement("figure");
    fig.className = "chart-panel";
    Object.assign(fig.dataset, data || {});
    const h = document.createElement("h3");
    h.textContent = title;
    const wrap = document.createElement("div");
    wrap.className = "chart-box";
    const canvas = document.createElement("canvas");
    canvas.setAttribute("role", "img");
    canvas.setAttribute("aria-label", label);
    wrap.appendChild(canvas);
    const details = document.createElement("details");
    details.className = "chart-data";
    const summary = document.createElement("summary");
    summary.textContent = "Data table";
    const scroller = document.createElement("div");
    scroller.className = "table-wrap";
    scroller.tabIndex = 0;
    scroller.appendChild(document.createElement("table")).className = "data";
    const note = document.createElement("p");
    note.className = "chart-note chart-data-note";
    note.hidden = true;
    details.append(summary, scroller, note);
    details.open = openTables.has(label);
    details.addEventListener("toggle", () => {
      if (details.open) openTables.add(label); else openTables.delete(label);
    });
    fig.append(h, wrap, details);
    box.appendChild(fig);
    return { fig: fig, canvas: canvas };
  }

  /* A view's choices in the page's query string, as the job chart keeps its own: each
   * key of ``values`` set to its value, or left out when null (its default). A change
   * is a step of the history; the other keys of the query are kept. */
  function setQuery(values) {
    const q = new URLSearchParams(location.search);
    Object.entries(values).forEach(([k, v]) => {
      if (v === null || v === undefined) q.delete(k); else q.set(k, String(v));
    });
    const s = q.toString();
    if (s !== new URLSearchParams(location.search).toString()) {
      history.pushState({ svrobsView: true }, "", location.pathname + (s ? `?${s}` : ""));
    }
  }

  /* The value of ``key`` in the page's query string (null when absent). */
  function queryValue(key) { return new URLSearchParams(location.search).get(key); }

  window.svrobsUi = { chartPanel, setQuery, queryValue };

  /* A region htmx replaces (the polled runs table and job status, the results grid)
   * keeps the keyboard focus: htmx focuses the element of the same id in the new
   * content; where there is none (the last page has no "next"), the region itself. */
  let focusIn = null;
  function keepFocus(e) {
    const active = document.activeElement, target = e.detail.target;
    focusIn = e.detail.shouldSwap && target && target.id && active && active !== document.body &&
      target.contains(active) ? target.id : null;
  }
  function restoreFocus() {
    const id = focusIn, active = document.activeElement;
    focusIn = null;
    if (!id || (active && active !== document.body && active.isConnected)) return;
    const region = document.getElementById(id);
    if (!region) return;
    if (!region.hasAttribute("tabindex")) region.setAttribute("tabindex", "-1");
    region.focus({ preventScroll: true });
  }

  /* A region htmx could not update (the server refused, or did not answer: the database
   * down, the network gone) keeps what it showed and says why, until an update comes. */
  function reasonOf(xhr) {
    const again = "Try again in a moment, or reload the page.";
    if (!xhr || !xhr.status) return `the server did not answer. ${again}`;
    let detail = "";
    const type = xhr.getResponseHeader("content-type") || "";
    try {
      if (type.includes("json")) detail = JSON.parse(xhr.responseText).detail;
      else if (type.includes("html")) {  // the error page's message
        const page = new DOMParser().parseFromString(xhr.responseText, "text/html");
        const message = page.querySelector(".error-message");
        detail = message ? message.textContent.trim() : "";
      }
    } catch (err) { /* the status alone */ }
    return typeof detail === "string" && detail ? `HTTP ${xhr.status}: ${detail}` : `HTTP ${xhr.status}. ${again}`;
  }
  function showFailure(e) {
    const target = e.detail.target;
    if (!target || !target.id) return;
    const id = `${target.id}-failed`;
    let note = document.getElementById(id);
    if (!note) {
      note = document.createElement("p");
      note.id = id;
      note.className = "error-message update-failed";
      note.setAttribute("role", "alert");
      const loading = target.querySelector("[data-loading]");  // (a card still saying "Loading…")
      if (loading) loading.replaceWith(note); else target.before(note);
    }
    const text = `Could not update this part of the page: ${reasonOf(e.detail.xhr)}`;
    if (note.textContent !== text) note.textContent = text;  // (said once, not at every poll)
  }
  function clearFailure(e) {
    const target = e.detail.target;
    const note = target && target.id && document.getElementById(`${target.id}-failed`);
    if (note && !target.contains(note)) note.remove();
  }

  /* A form's error list (#form-errors: the spec form, the schedule forms) takes the
   * focus when the page loads; a link of the list moves the focus into its field (a
   * fragment link would only scroll to the field's box): the control marked invalid,
   * else the first shown. */
  function initErrorSummary() {
    const summary = document.getElementById("form-errors");
    if (!summary) return;
    summary.focus();
    summary.addEventListener("click", (e) => {
      const a = e.target.closest("a[href^='#']");
      const box = a && document.getElementById(a.getAttribute("href").slice(1));
      if (!box) return;
      const shown = (c) => c.getClientRects().length > 0;
      const controls = box.matches("input, select, textarea") ? [box]
        : [...box.querySelectorAll("input:not([type=hidden]), select, textarea")].filter(shown);
      const control = controls.find((c) => c.getAttribute("aria-invalid") === "true") || controls[0];
      if (!control) return;
      e.preventDefault();
      control.focus();
      control.scrollIntoView({ block: "center" });
    });
  }

  function init() {
    focusableScrollers(document);
    initErrorSummary();
    initMenu();
    initTheme();
    initCopy(document);
    initConfirm();
    document.body.addEventListener("htmx:beforeSwap", keepFocus);
    document.body.addEventListener("htmx:afterSwap", (e) => {
      restoreFocus();
      clearFailure(e);
      initCopy(e.detail.target);
      focusableScrollers(document);
    });
    document.body.addEventListener("htmx:responseError", showFailure);
    document.body.addEventListener("htmx:sendError", showFailure);
  }

  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", init);
  else init();
})();
