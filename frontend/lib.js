// What every page of the appliance and the room needs, written once: HTML escaping, the CSRF
// header and one fetch helper. A plain script (the pages load plain scripts, no bundler and
// nothing from the internet), loaded before each page's own script: index.html, login.html,
// room.html, and the rerun viewer's page (server/http/rerun.py adds it before rerun-tab.js).
// tests/lint/test_written_once.py fails on a second copy of any of these in frontend/.
"use strict";

const xrfLib = (function () {
  const ENTITIES = { "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" };

  // Text made safe for innerHTML, in element content and in quoted attributes alike (hence the
  // quotes too). null and undefined are shown as nothing, not as "null".
  function esc(s) {
    return String(s ?? "").replace(/[&<>"']/g, (c) => ENTITIES[c]);
  }

  // The session cookie is HttpOnly; the CSRF token is in the readable xrf_csrf cookie and goes back
  // in X-CSRF-Token on every state-changing request (docs/developers/security.md). No cookie: no header.
  function csrfHeaders() {
    const m = document.cookie.match(/(?:^|;\s*)xrf_csrf=([^;]+)/);
    return m ? { "X-CSRF-Token": decodeURIComponent(m[1]) } : {};
  }

  // One request to this origin with the session cookie. Anything but GET/HEAD carries the CSRF
  // header. `body`: a string, Blob/File or FormData is sent as it is (the caller names its type in
  // `headers` if it needs one); any other value is sent as JSON. The answer never throws on an
  // HTTP error: {ok, status, data, res}, `data` the JSON body ({} for none or not JSON); callers
  // word their own errors from data.detail.
  async function send(method, path, body, headers) {
    const h = Object.assign(method === "GET" || method === "HEAD" ? {} : csrfHeaders(), headers || {});
    let payload = body;
    if (body !== undefined && !(typeof body === "string" || body instanceof Blob || body instanceof FormData)) {
      payload = JSON.stringify(body);
      if (!Object.keys(h).some((k) => k.toLowerCase() === "content-type")) h["Content-Type"] = "application/json";
    }
    const res = await fetch(path, { method, headers: h, body: payload, credentials: "same-origin" });
    const data = res.status === 204 ? {} : await res.json().catch(() => ({}));
    return { ok: res.ok, status: res.status, data, res };
  }

  return { esc, csrfHeaders, send };
})();
window.xrfLib = xrfLib;
