/* The colour theme, set before the page is drawn (no flash): data-theme is the choice
 * of the header's toggle (kept in localStorage; none: auto), data-scheme what is
 * shown: that choice, else the system's (prefers-color-scheme), followed live. */
(function () {
  "use strict";
  const root = document.documentElement;
  root.classList.add("js");
  try {
    const saved = localStorage.getItem("svrobs-theme");
    if (saved === "light" || saved === "dark") root.dataset.theme = saved;
  } catch (e) { /* storage refused: follow the system */ }
  const system = window.matchMedia ? window.matchMedia("(prefers-color-scheme: dark)") : null;
  function scheme() {
    root.dataset.scheme = root.dataset.theme || (system && system.matches ? "dark" : "light");
  }
  scheme();
  if (system) system.addEventListener("change", scheme);
  window.svrobsScheme = scheme;
})();
