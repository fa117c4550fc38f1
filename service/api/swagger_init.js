/* /docs: Swagger UI under the web session. A browser signed in to the dashboard tries
 * the API out without pasting a key: reads send the session cookie, writes also the
 * session's CSRF token (X-CSRF-Token, from /session), which the API takes in place
 * of a key; the Authorize button still takes one (it wins when given). */
(async function () {
  "use strict";
  let session = null;
  try {
    const r = await fetch("/session", { credentials: "same-origin", headers: { Accept: "application/json" } });
    if (r.ok) session = await r.json();
  } catch (e) { /* no session: the key, as before */ }
  const signedIn = Boolean(session && session.signed_in && session.csrf);
  if (signedIn) {
    const note = document.getElementById("docs-session");
    note.textContent = `Signed in to the dashboard as ${session.email || "a service key"}: ` +
      "Try it out works without a key (Authorize only to act as another key).";
    note.hidden = false;
  }
  window.ui = SwaggerUIBundle({
    url: document.body.dataset.openapi,
    dom_id: "#swagger-ui",
    layout: "BaseLayout",
    deepLinking: true,
    showExtensions: true,
    showCommonExtensions: true,
    validatorUrl: null,
    persistAuthorization: true,
    presets: [SwaggerUIBundle.presets.apis, SwaggerUIBundle.SwaggerUIStandalonePreset],
    requestInterceptor: (req) => {
      const headers = req.headers || {};
      if (signedIn && !headers.Authorization) headers["X-CSRF-Token"] = session.csrf;
      req.headers = headers;
      req.credentials = "same-origin";
      return req;
    },
  });
})();
