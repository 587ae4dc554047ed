// ROS 2 page: the bridge the appliance runs with every loop run (XenoCmd, XenoState, Ros2Xeno,
// Xeno2Ros). Everybody sees its status; educators switch it on/off. API: appliance/xrflab/server/
// server/http/ros.py; live updates: the `ros` WebSocket message. Docs: docs/ros2/bridge.md.
"use strict";

(function () {
  const $ = (id) => document.getElementById(id);
  const esc = xrf.esc;  // frontend/lib.js

  const HTML = `<div class="page-body ros">
    <section class="panel" id="ros-card">
      <h2>ROS 2 bridge <span class="spacer"></span>
        <label class="small" id="ros-toggle-label"><input type="checkbox" id="ros-toggle"> run with every loop run</label></h2>
      <p class="muted small">Course ROS 2 nodes talk to the running controller through the topics below. Commands
        (XenoCmd) obey the bench lease of the bridge's user; stop and pause always go through.</p>
      <dl class="facts" id="ros-facts"><dt>…</dt><dd></dd></dl>
      <p class="small bad" id="ros-msg"></p>
    </section>
  </div>`;

  let last = null;

  function render(s) {
    last = s;
    if (!$("ros-facts")) return;
    const isEdu = xrf.may("educator");
    const t = $("ros-toggle");
    t.checked = !!s.enabled;
    t.disabled = !isEdu;
    $("ros-toggle-label").title = isEdu ? "" : "only educators switch the bridge";
    const rows = [
      ["status", s.state + (s.enabled ? "" : " (switched off)")],
      ["pid", s.pid ?? "–"],
      ["run", s.run_id != null ? "#" + s.run_id : "–"],
      ["acts for", s.user || (s.configured_user ? s.configured_user : "the user who starts the run")],
      ["topics", (s.topics || []).join(", ")],
      ["restarts", s.restarts],
      ["scheduling", s.scheduling],
      ["last error", s.last_error || "–"],
      ["output", s.output || "–"],
    ];
    $("ros-facts").innerHTML = rows.map(([k, v]) => `<dt>${esc(k)}</dt><dd data-fact="${esc(k)}" class="${k === "status" ? "ros-" + esc(s.state) : ""}">${esc(v)}</dd>`).join("");
  }

  async function load() {
    try { render(await xrf.api("GET", "/api/ros")); $("ros-msg").textContent = ""; }
    catch (e) { $("ros-msg").textContent = e.message; }
  }

  xrf.on("ros", (m) => render(m));

  xrf.addPage({
    id: "ros", title: "ROS 2", order: 75,
    init(el) {
      el.innerHTML = HTML;
      $("ros-toggle").addEventListener("change", async (ev) => {
        const want = ev.target.checked;
        ev.target.disabled = true;
        try { render(await xrf.api("POST", "/api/ros", { enabled: want })); $("ros-msg").textContent = ""; }
        catch (e) { $("ros-msg").textContent = e.message; ev.target.checked = !want; }
        finally { ev.target.disabled = !xrf.may("educator"); }
      });
      if (last) render(last);
      load();
    },
    show() { load(); },
  });
})();
