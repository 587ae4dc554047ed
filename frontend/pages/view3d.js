// 3D view page: the appliance's viser scene (xrflab.viz), live numbers, reset odometry and replay
// of a finished run. The scene is served by viser on an internal port (127.0.0.1 only) and opened
// through the appliance's /viser/ proxy (same origin, behind the login; GET /api/viz gives the
// path), in a TAB OF ITS OWN (noopener: a renderer process of its own), never in an iframe of
// this page: a same-origin iframe shares this page's main thread, and drawing or tearing down its
// WebGL scene with a software GPU (a lab PC without a GPU driver, headless chromium) froze the
// dashboard for 5-8 s when leaving this page (issue 31 bug 7), as the embedded rerun viewer did
// (issue 19). The scene's tab gets Esc-stops-the-run from frontend/rerun-tab.js (server/http/viser.py).
"use strict";
(function () {
  const STATE_HZ = 4;  // numbers under the view; the scene itself updates at 30 Hz inside viser
  let timer = null, info = null, el0 = null, seeking = false, holdMessage = 0;

  const deg = (r) => (r * 180 / Math.PI).toFixed(1) + "°";

  function html(el) {
    el.innerHTML = `
      <section class="panel wide" id="panel-view3d">
        <h2>3D view <span class="muted small" id="v3d-mode">…</span></h2>
        <div class="rejected hidden" id="v3d-message" role="status"></div>
        <div class="row">
          <span id="v3d-values" class="values">–</span>
          <button id="v3d-reset" class="secondary" title="RELbot: put the robot back at the origin, heading +x">Reset odometry</button>
        </div>
        <div class="row">
          <button id="v3d-open" title="The scene opens in a tab of its own, so drawing it never blocks this page">Open the 3D scene</button>
          <a id="v3d-link" target="_blank" rel="noopener" href="/viser/">/viser/</a>
          <span class="muted small">in a tab of its own (Esc there stops the run, as here); the numbers below follow the same scene</span>
        </div>
        <div class="row">
          <label for="v3d-runs">Replay run</label>
          <select id="v3d-runs"><option value="">–</option></select>
          <button id="v3d-replay" class="secondary">Replay</button>
          <input type="range" id="v3d-slider" min="0" max="1" step="0.01" value="0" disabled style="flex:1">
          <span id="v3d-time" class="muted">–</span>
          <button id="v3d-live" class="secondary">Live</button>
        </div>
      </section>`;
  }

  async function loadInfo(el) {
    const $ = (id) => el.querySelector("#" + id);
    info = await xrf.api("GET", "/api/viz");
    $("v3d-open").disabled = !info.available || !info.url;
    if (!info.available || !info.url) {
      $("v3d-message").textContent = info.error || "The 3D view is not available on this appliance.";
      $("v3d-message").classList.remove("hidden");
      return;
    }
    $("v3d-link").setAttribute("href", new URL(info.url, location.href).href);
  }

  async function loadRuns(el) {
    const sel = el.querySelector("#v3d-runs");
    const recs = await xrf.api("GET", "/api/viz/recordings");
    const keep = sel.value;
    sel.innerHTML = '<option value="">–</option>' + recs.filter((r) => !r.active)
      .map((r) => `<option value="${r.run_id}">run ${r.run_id}</option>`).join("");
    if ([...sel.options].some((o) => o.value === keep)) sel.value = keep;
  }

  async function poll(el) {
    const $ = (id) => el.querySelector("#" + id);
    let s;
    try { s = await xrf.api("GET", "/api/viz/state"); } catch (e) { return; }
    xrf.view3d = s;  // test hook
    $("v3d-mode").textContent = s.mode === "replay" ? `replay of run ${s.run_id}`
      : s.mode === "live" ? `live: run ${s.run_id}${s.active ? "" : " (ended)"}` : "no run yet";
    const msg = $("v3d-message");
    if (Date.now() > holdMessage) {  // a refusal stays readable for a while
      msg.textContent = s.message || "";
      msg.classList.toggle("hidden", !s.message);
    }
    let v = "–";
    if (s.joints) {
      v = `pan ${deg(s.joints.pan)} · tilt ${deg(s.joints.tilt)}`;
      if (s.ghost) v += ` · setpoint (green) ${Object.entries(s.ghost).map(([k, x]) => k + " " + deg(x)).join(", ")}`;
    } else if (s.arm) {  // the youBot: the arm's joints, then its base's odometry
      v = s.arm.map((a, k) => `J${k + 1} ${deg(a)}`).join(" · ") +
        ` · base x ${s.pose.x.toFixed(3)} m, y ${s.pose.y.toFixed(3)} m, θ ${deg(s.pose.theta)}`;
    } else if (s.pose) {
      v = `x ${s.pose.x.toFixed(3)} m · y ${s.pose.y.toFixed(3)} m · θ ${deg(s.pose.theta)}`;
    } else if (s.axes) {  // the cell: homed on its switches from the live pins (a replay has none)
      v = `table ${deg(s.axes[0])} · press ${(1000 * s.axes[1]).toFixed(1)} mm · feeder ${(1000 * s.axes[2]).toFixed(1)} mm`;
      if (s.homed) v += s.homed.every((h) => h) ? " · homed" : " · not homed";
    }
    $("v3d-values").textContent = v;
    $("v3d-reset").disabled = s.kind !== "differential_drive" || s.mode === "replay";
    const slider = $("v3d-slider");
    slider.disabled = s.mode !== "replay";
    if (s.mode === "replay") {
      slider.max = Math.max(s.duration, 0.01);
      if (!seeking) slider.value = s.t;
      $("v3d-time").textContent = `${(+s.t).toFixed(2)} / ${s.duration.toFixed(2)} s`;
    } else {
      $("v3d-time").textContent = "–";
    }
  }

  function wire(el) {
    const $ = (id) => el.querySelector("#" + id);
    // Only a click opens the scene's tab (a page switch never does); noopener: the browser gives
    // it a process of its own (also when the link is opened with the middle button).
    $("v3d-open").addEventListener("click", () => window.open($("v3d-link").href, "_blank", "noopener"));
    $("v3d-reset").addEventListener("click", () => xrf.api("POST", "/api/viz/reset-odometry").catch(() => {}));
    // A refusal is said on the page (not an alert, not nothing): replay and live switch the scene
    // every viewer sees, so they need the bench, which its holder now keeps after a run (server/security/lease.py).
    const refused = (e) => {
      const msg = $("v3d-message");
      msg.textContent = (e.status === 403 ? "Replay and live need the bench: " : "") + (e.message || e);
      msg.classList.remove("hidden");
      holdMessage = Date.now() + 8000;
    };
    $("v3d-replay").addEventListener("click", async () => {
      const id = $("v3d-runs").value;
      if (id) await xrf.api("POST", "/api/viz/replay", { run_id: +id }).then(() => poll(el)).catch(refused);
    });
    $("v3d-live").addEventListener("click", () => xrf.api("POST", "/api/viz/live").then(() => poll(el)).catch(refused));
    let pending = null;
    $("v3d-slider").addEventListener("input", (ev) => {
      seeking = true;
      const t = +ev.target.value;
      if (pending) { pending.t = t; return; }
      pending = { t };
      setTimeout(async () => {  // at most ~10 seeks per second while dragging
        const p = pending; pending = null;
        await xrf.api("POST", "/api/viz/replay/seek", { t: p.t }).catch(() => {});
        seeking = false;
      }, 100);
    });
    xrf.on("run", () => { if (el0 && !el0.classList.contains("hidden")) loadRuns(el0).catch(() => {}); });
  }

  xrf.addPage({
    id: "view3d",
    title: "3D view",
    order: 20,
    init(el) { el0 = el; html(el); wire(el); },
    show(el) {
      loadInfo(el).catch((e) => { el.querySelector("#v3d-message").textContent = "3D view: " + e; });
      loadRuns(el).catch(() => {});
      clearInterval(timer);
      timer = setInterval(() => {
        if (el.classList.contains("hidden")) { clearInterval(timer); timer = null; return; }
        poll(el);
      }, 1000 / STATE_HZ);
      poll(el);
    },
  });
})();
