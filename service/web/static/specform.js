/* The spec form of /jobs/new: the JSON view and the fields kept in sync both ways
 * (the rules of service/web/spec_form.py: lists of numbers, start/stop/step, the
 * options of a bounds method only with it, empty optional fields null; a dataset chosen
 * makes it a job on measured data: the fields of that kind of job only). Editing the
 * fields rewrites the JSON and sets "Submit: the fields"; editing valid JSON fills
 * the fields and sets "Submit: the JSON". A preset fills the form when its "Fill the
 * form" button is pressed: choosing one in the list (arrow keys included) changes
 * nothing else, so nothing typed is lost (WCAG 3.2.2, On Input). */
(function () {
  "use strict";
  const form = document.getElementById("submit-form");
  if (!form) return;
  const textarea = document.getElementById("spec");
  const status = document.getElementById("spec-json-status");
  const INT = /^[+-]?\d+$/;

  const blocks = () => [...form.querySelectorAll(".spec-field[data-kind]")];
  const named = (name) => form.querySelectorAll(`[name="${CSS.escape(name)}"]`);
  const one = (name) => named(name)[0];

  /* An integer beyond 2^53 (a seed may be up to 2^63 - 1) as its digits: a JS number
   * would round it. parse() and stringify() carry it through the JSON view as is. */
  class BigIntText {
    constructor(digits) { this.digits = digits; }
    toString() { return this.digits; }
  }
  const MARK = "\u0001";
  function parse(text) {
    // the reviver's third argument holds the number's source text (Chromium 114+)
    return JSON.parse(text, (k, v, ctx) =>
      typeof v === "number" && !Number.isSafeInteger(v) && ctx && INT.test(ctx.source || "")
        ? new BigIntText(ctx.source) : v);
  }
  function stringify(value, indent) {
    const json = JSON.stringify(value, (k, v) => (v instanceof BigIntText ? MARK + v.digits + MARK : v), indent);
    return json.replace(/"\\u0001(-?\d+)\\u0001"/g, "$1");
  }

  function number(token, integer) {
    if (INT.test(token)) {
      const v = parseInt(token, 10);
      return Number.isSafeInteger(v) ? v : new BigIntText(token.replace(/^\+/, ""));
    }
    const v = Number(token);
    return integer || token === "" || !Number.isFinite(v) ? token : v;
  }

  function tokens(text) { return text.trim().split(/[,\s;]+/).filter(Boolean); }

  /* "dataset" when a dataset is chosen (a job on measured data), else "simulated". */
  function job() { const d = one("f.dataset"); return d && d.value ? "dataset" : "simulated"; }
  function applies(b) { return !b.dataset.job || b.dataset.job === job(); }
  function method() {
    return (one("f.bounds_method") || {}).value || (job() === "dataset" ? "self-normalized" : "paper");
  }

  function put(spec, name, value) {
    if (name.startsWith("sls.")) (spec.sls = spec.sls || {})[name.slice(4)] = value;
    else spec[name] = value;
  }

  function gridValue(name, kind) {
    const mode = form.querySelector(`[name="m.${name}"]:checked`);
    if (mode && mode.value === "range") {
      const p = {};
      for (const part of ["start", "stop", "step"]) {
        const t = one(`r.${name}.${part}`).value.trim() || (part === "step" ? "1" : "");
        if (!t) return undefined;
        p[part] = number(t, kind === "grid");
      }
      if (kind === "grid") return p;
      if (![p.start, p.stop, p.step].every((v) => typeof v === "number") || p.step <= 0 || p.stop < p.start) return undefined;
      const n = Math.floor((p.stop - p.start) / p.step + 1e-9) + 1;
      return Array.from({ length: Math.min(n, 100000) }, (_, i) => Number((p.start + i * p.step).toPrecision(12)));
    }
    const text = one(`f.${name}`).value;
    return text.trim() ? tokens(text).map((t) => number(t, kind === "grid")) : undefined;
  }

  /* The spec the fields describe. */
  function fieldsToSpec() {
    const spec = {}, m = method();
    for (const b of blocks()) {
      const name = b.dataset.field, kind = b.dataset.kind, key = b.dataset.key;
      if (!applies(b) || (b.dataset.onlyWith && b.dataset.onlyWith !== m)) continue;
      let value;
      if (kind === "json") {
        const t = one(`f.${key}`).value.trim();
        try { value = t ? parse(t) : null; } catch (e) { value = t; /* the server says so */ }
      } else if (kind === "systems") {
        value = [...named("f.systems")].filter((c) => c.checked).map((c) => c.value);
        const custom = one("f.systems_custom").value.trim();
        if (custom) { try { value = value.concat(parse(custom)); } catch (e) { /* the server says so */ } }
        if (!value.length) value = undefined;
      } else if (kind === "numbers" || kind === "grid") {
        value = gridValue(name, kind);
      } else if (kind === "choices") {
        value = [...named(`f.${name}`)].filter((c) => c.checked).map((c) => c.value);
      } else if (kind === "bool") {
        value = one(`f.${name}`).checked;
      } else {
        const t = one(`f.${key}`).value.trim();
        if (!t) { if (b.dataset.optional) put(spec, name, null); continue; }
        value = kind === "choice" || (kind === "level" && t === "estimate") ? t : number(t, kind === "int" || kind === "dataset");
      }
      if (value !== undefined) put(spec, name, value);
    }
    return spec;
  }

  function text(v) { return v === null || v === undefined ? "" : String(v); }

  /* Fill the fields from a spec (a field it lacks keeps its value); a spec with
   * "dataset" chooses that dataset (an option is added for an id not listed). */
  function specToFields(spec) {
    const ds = one("f.dataset");
    if (ds) {
      const id = spec.dataset === undefined || spec.dataset === null ? "" : String(spec.dataset);
      if (id && ![...ds.options].some((o) => o.value === id)) ds.add(new Option(id, id));
      ds.value = id;
      const bm = one("f.bounds_method");
      if (id && bm && spec.bounds_method === undefined) bm.value = "self-normalized";
    }
    for (const b of blocks()) {
      const name = b.dataset.field, kind = b.dataset.kind, key = b.dataset.key;
      if (kind === "dataset" || !applies(b)) continue;
      const v = name.startsWith("sls.") ? (spec.sls || {})[name.slice(4)] : spec[name];
      if (v === undefined) continue;
      if (kind === "json") {
        one(`f.${key}`).value = v === null ? "" : stringify(v);
      } else if (kind === "systems") {
        const list = Array.isArray(v) ? v : [];
        named("f.systems").forEach((c) => { c.checked = list.includes(c.value); });
        const custom = list.filter((s) => typeof s !== "string");
        one("f.systems_custom").value = custom.length ? stringify(custom) : "";
        document.getElementById("systems-custom-note").textContent =
          custom.length ? `+ ${custom.length} custom system(s) of the JSON view` : "";
      } else if (kind === "numbers" || kind === "grid") {
        const range = v && typeof v === "object" && !Array.isArray(v);
        form.querySelector(`[name="m.${name}"][value="${range ? "range" : "list"}"]`).checked = true;
        if (range) ["start", "stop", "step"].forEach((p) => { one(`r.${name}.${p}`).value = text(v[p]); });
        else one(`f.${name}`).value = Array.isArray(v) ? v.join(", ") : text(v);
      } else if (kind === "choices") {
        const list = Array.isArray(v) ? v : [];
        named(`f.${name}`).forEach((c) => { c.checked = list.includes(c.value); });
      } else if (kind === "bool") {
        one(`f.${name}`).checked = v === true;
      } else {
        one(`f.${key}`).value = text(v);
      }
    }
    modes();
  }

  /* Show what applies: the fields of the kind of job, list or range inputs, the
   * options of the chosen bounds method. */
  function modes() {
    const m = method();
    for (const b of blocks()) {
      b.hidden = !applies(b) || (!!b.dataset.onlyWith && b.dataset.onlyWith !== m);
      const mode = b.querySelector("[name^='m.']:checked");
      if (mode) {
        b.querySelector(".grid-list").hidden = mode.value === "range";
        b.querySelector(".grid-range").hidden = mode.value !== "range";
      }
    }
  }

  function source(which) {
    const r = form.querySelector(`[name=source][value=${which}]`);
    if (r) r.checked = true;
  }

  function fromFields() {
    textarea.value = stringify(fieldsToSpec(), 2);
    status.textContent = "The JSON follows the fields.";
    source("form");
  }

  form.addEventListener("input", (e) => {
    if (e.target === textarea) {
      let spec;
      try { spec = parse(textarea.value); } catch (err) {
        status.textContent = `Not valid JSON yet (${err.message}); the fields keep their values.`;
        source("json");
        return;
      }
      if (!spec || typeof spec !== "object" || Array.isArray(spec)) {
        status.textContent = "The spec must be a JSON object.";
        return;
      }
      specToFields(spec);
      status.textContent = "The fields follow the JSON.";
      source("json");
    } else if (e.target.closest(".spec-field[data-kind]")) {
      fromFields();
    }
  });
  form.addEventListener("change", (e) => {
    if (e.target.name === "f.dataset" && job() === "dataset") {
      const bm = one("f.bounds_method");  // the one bounds method sound on measured data
      if (bm) bm.value = "self-normalized";
    }
    if (e.target.closest(".spec-field[data-kind]")) { modes(); fromFields(); }
  });
  document.getElementById("spec_file").addEventListener("change", () => source("json"));
  modes();
  if (!textarea.value.trim()) fromFields();
  window.svrobsSpecForm = { fieldsToSpec, specToFields };
})();
