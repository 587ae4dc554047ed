// The login page: password login, then (for a one-time password) the forced password change,
// then back to where the user was going (a path on this appliance only).
"use strict";

(function () {
  const $ = (id) => document.getElementById(id);

  function next() {
    const n = new URLSearchParams(location.search).get("next") || "/";
    // Only a local path: never an open redirect to another site ("//evil", "/\evil", "https:").
    return /^\/(?![\/\\])/.test(n) ? n : "/";
  }

  async function post(path, body) {
    const { ok, data, res } = await xrfLib.send("POST", path, body);  // frontend/lib.js
    if (!ok) {
      const d = data.detail;
      throw new Error(typeof d === "string" ? d : Array.isArray(d) ? d.map((e) => e.msg).join("; ") : res.statusText);
    }
    return data;
  }

  function showChange(current) {
    $("login-form").classList.add("hidden");
    $("change-form").classList.remove("hidden");
    if (current) { $("change-current").value = current; $("change-new").focus(); } else $("change-current").focus();
  }

  $("login-form").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    $("login-error").textContent = "";
    $("login-submit").disabled = true;
    try {
      const me = await post("/api/auth/login", { username: $("login-user").value.trim(), password: $("login-pass").value });
      if (me.must_change) showChange($("login-pass").value);
      else location.replace(next());
    } catch (e) {
      $("login-error").textContent = e.message;
    } finally {
      $("login-submit").disabled = false;
    }
  });

  $("change-form").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    $("change-error").textContent = "";
    if ($("change-new").value !== $("change-again").value) { $("change-error").textContent = "the two new passwords differ"; return; }
    $("change-submit").disabled = true;
    try {
      await post("/api/auth/password", { current: $("change-current").value, new: $("change-new").value });
      location.replace(next());
    } catch (e) {
      $("change-error").textContent = e.message;
    } finally {
      $("change-submit").disabled = false;
    }
  });

  // Already logged in (e.g. sent here because the password must change): say what is needed.
  fetch("/api/me").then((r) => (r.ok ? r.json() : null)).then((me) => {
    if (!me) return;
    if (me.must_change) showChange("");
    else location.replace(next());
  }).catch(() => {});
})();
