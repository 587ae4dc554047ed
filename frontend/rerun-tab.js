// Ours, added to the rerun viewer's page (/rerun/, routes_rerun.neutralise_index). The Runs page
// opens the viewer in a tab of its own (noopener: a renderer process of its own), because a viewer
// embedded in the dashboard froze the dashboard's main thread for minutes on a software GPU and
// its WebSocket closed (issue 19 item 9, docs/logging/appliance.md). In its own tab the
// dashboard's key handler is not there, so this page keeps the promise "Esc stops from anywhere"
// itself (issue 19 item 1), with the dashboard's rule, over HTTP with the session cookie and the
// CSRF header: RUN or PAUSED -> the `stop` command; any other state of a live run -> end the run.
// It also follows the live stream to the next run, as the embedded viewer did, and offers the
// run's replay from its start: the live stream keeps only a short window and sends it newest
// first, so a viewer opened mid-run starts at the live edge (issue 31 bug 6, logs/rerun_servers.py
// LiveProxy); the whole run so far is its log, opened as .rrd in another viewer tab.
// The 3D view's tab (viser's page, server/http/viser.py) loads this script too, for Esc.
"use strict";
(function () {
  const FOLLOW_MS = 3000;
  let busy = false, noteTimer = null;

  // The rerun viewer's tab (not viser's): console.debug does nothing here. When the first plot is
  // drawn, the viewer's shader compiler (naga, logging at debug level in rerun's web build, with
  // no switch) writes ~9000 console.debug lines; each is a message to DevTools when a debugger
  // is attached and a message to the browser process in any case. Measured in chromium on the
  // CPU-only VM: it froze the tab 5-8 s on its first data, muted 2-3 s (issue 31 bug 6,
  // bench/appliance/rerun_lag.py). Runs before re_viewer.js (server/http/rerun.py puts this
  // script first), whose bindings look console.debug up at each call. The viewer's info,
  // warnings and errors still reach the console; the original is kept for whoever debugs.
  const rerunPage = location.pathname.startsWith("/rerun/");
  const consoleDebug = console.debug;
  let debugMuted = 0;
  if (rerunPage) console.debug = () => { debugMuted += 1; };

  async function post(path, body) {
    const { data, res } = await xrfLib.send("POST", path, body || {});  // frontend/lib.js, loaded before this
    const detail = typeof data.detail === "string" ? data.detail : data.detail ? JSON.stringify(data.detail) : res.statusText;
    return { ok: res.ok, status: res.status, data, detail };
  }

  // A short note over the viewer: the canvas covers the whole page, so it floats above it.
  function note(text, bad) {
    let n = document.getElementById("xrf-stop-note");
    if (!n) {
      n = document.createElement("div");
      n.id = "xrf-stop-note";
      n.setAttribute("role", "status");
      Object.assign(n.style, { position: "fixed", top: "12px", left: "50%", transform: "translateX(-50%)",
        zIndex: "2147483647", padding: "8px 16px", borderRadius: "6px", font: "600 15px system-ui, sans-serif",
        color: "#fff", boxShadow: "0 2px 8px rgba(0,0,0,.4)", pointerEvents: "none" });
      document.body.appendChild(n);
    }
    n.textContent = text;
    n.dataset.kind = bad ? "refused" : "sent";
    n.style.background = bad ? "#b91c1c" : "#15803d";
    n.style.display = "block";
    clearTimeout(noteTimer);
    noteTimer = setTimeout(() => { n.style.display = "none"; }, bad ? 10000 : 6000);
  }

  async function stop() {
    if (busy) return;  // a held key repeats: one stop at a time
    busy = true;
    note("Esc: sending stop…");  // at once: the viewer may keep this thread busy until the answer is handled
    try {
      const r = await post("/api/runs/current/command", { cmd: "stop" });
      if (r.status === 401) { note("Not logged in: log in to the dashboard again, then stop from there.", true); return; }
      if (!r.ok) { note("Stop refused: " + r.detail, true); return; }
      if (r.data.accepted) { note("Stop sent (Esc): the controller is stopping."); return; }
      // Not in RUN or PAUSED: the loop refuses `stop`, and the rule ends the run instead.
      note("Ending the run (Esc): it is in " + (r.data.state_name || "another state") + "…");
      const end = await post("/api/runs/current/stop");
      if (end.ok) note("Run ended (Esc): it was in " + (r.data.state_name || "another state") + ".");
      else note("Could not end the run: " + end.detail, true);
    } catch (e) {
      note("Stop not sent: the appliance does not answer (" + e.message + "). Use the STOP button of the bench.", true);
    } finally {
      busy = false;
    }
  }

  // Capture phase on the window: before the viewer's canvas (a wasm app) can take the key.
  window.addEventListener("keydown", (ev) => {
    if (ev.key !== "Escape") return;  // only Esc: other keys are the viewer's
    ev.preventDefault();
    if (!ev.repeat) stop();
  }, true);

  // The live stream (?url=rerun+http(s)://<host>/proxy) is the latest run's: when a new run starts,
  // the previous run's stream ends, and this tab reloads onto the new one.
  const url = new URLSearchParams(location.search).get("url") || "";
  const live = /^rerun\+https?:\/\/[^/]+\/proxy$/.test(url);
  // "Replay from start": a link in a corner (the viewer's canvas covers the page), to the live
  // run's first log file as .rrd (converted up to now: a run still logging gives what it has).
  async function offerReplay(run) {
    let a = document.getElementById("xrf-replay");
    try {
      const r = await fetch(`/api/logs/runs/${run}`, { credentials: "same-origin" });
      const files = r.ok ? (await r.json()).files : [];
      if (!files.length) { if (a) a.remove(); return; }
      const path = `/api/logs/runs/${run}/files/${files[0].name.split("/").map(encodeURIComponent).join("/")}?fmt=rrd`;
      if (!a) {
        a = document.createElement("a");
        a.id = "xrf-replay";
        a.target = "_blank";
        a.rel = "noopener";
        Object.assign(a.style, { position: "fixed", right: "12px", bottom: "40px", zIndex: "2147483647",
          padding: "4px 10px", borderRadius: "6px", font: "13px system-ui, sans-serif", color: "#fff",
          background: "rgba(30,64,175,.85)", textDecoration: "none" });
        document.body.appendChild(a);
      }
      a.textContent = `Replay run ${run} from its start`;
      a.title = "This live view shows the last seconds; the whole run so far is its log, opened here as .rrd in a new tab";
      a.href = "/rerun/?url=" + encodeURIComponent(location.origin + path);
    } catch (e) { /* the appliance restarts: the next poll tries again */ }
  }

  if (live) {
    let shown, offered;
    const follow = async () => {
      try {
        const r = await fetch("/api/logs/rerun", { credentials: "same-origin" });
        if (r.ok) {
          const info = await r.json();
          if (shown === undefined) shown = info.live_run;
          else if (info.live_run != null && info.live_run !== shown) { location.reload(); return; }
          if (info.live_run != null) document.title = `rerun · live run ${info.live_run}` + (info.live_running ? "" : " (ended)");
          if (info.live_run != null && offered !== info.live_run) { offered = info.live_run; offerReplay(info.live_run); }
        }
      } catch (e) { /* the appliance restarts: try again */ }
      setTimeout(follow, FOLLOW_MS);
    };
    follow();
  } else {
    const m = url.match(/\/api\/logs\/runs\/(\d+)\//);
    if (m) document.title = `rerun · run ${m[1]}`;
  }
  // test hook; debugMuted(): console.debug lines muted so far (see above)
  window.xrfRerunTab = { stop, live, consoleDebug, debugMuted: () => debugMuted };
})();
