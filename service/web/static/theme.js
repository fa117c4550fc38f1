/* The colour theme, set before the page is drawn (no flash): the one chosen with the
 * header's toggle (kept in localStorage), else the system's (prefers-color-scheme,
 * handled by the stylesheet alone). */
(function () {
  "use strict";
  const root = document.documentElement;
  root.classList.add("js");
  try {
    const saved = localStorage.getItem("svrobs-theme");
    if (saved === "light" || saved === "dark") root.dataset.theme = saved;
  } catch (e) { /* storage refused: follow the system */ }
})();
