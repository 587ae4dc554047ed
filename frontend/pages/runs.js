// Runs page: every run with who/when/build/duration/cycles/misses and its logging figures (records
// written, a "lost: N" badge that is normally 0, the note when logging stopped), each log file
// downloadable as the raw file, CSV, MAT, Parquet and rerun .rrd, and the rerun web viewer
// (served by the appliance under /rerun/) showing the live run (through the appliance's login, from
// any address) or a finished run's .rrd. The viewer (a 43 MB wasm, 14 MB compressed) is loaded only
// when asked for ("Live plots", "Open in rerun"): not to download a CSV. It opens in a tab of its
// own (noopener: its own renderer process), never in this page: embedded, its drawing froze the
// dashboard's main thread for minutes on a software GPU, and with it the WebSocket and Esc
// (issue 19 item 9). Esc in the viewer's tab still stops the run (frontend/rerun-tab.js).
// Which log files a run has is known only from its own record (/api/logs/runs/{id}: the listing
// does not walk 200 run folders every 2 s), so each row has a "log files" button that opens them
// below, as a click on the row does, and the heading says so: the formats are not shown as if they
// were links (issue 31).
"use strict";
(function () {
  const REFRESH_MS = 2000;
  const FORMATS = [["raw", "raw"], ["csv", "CSV"], ["mat", "MAT"], ["parquet", "Parquet"], ["rrd", ".rrd"]];
  let el0 = null, timer = null, selected = null, rerun = null;

  const esc = xrf.esc;  // frontend/lib.js
  const when = (t) => new Date(t * 1000).toLocaleString();
  const dur = (s) => s == null ? "–" : s < 60 ? s.toFixed(1) + " s" : s < 3600 ? `${Math.floor(s / 60)} min ${Math.round(s % 60)} s` : `${(s / 3600).toFixed(1)} h`;
  const num = (n) => (n == null ? "–" : Number(n).toLocaleString("en-US"));

  function html(el) {
    el.innerHTML = `
      <section class="panel wide" id="panel-runs">
        <h2>Runs <span class="muted small" id="runs-hint">click a run (or its <b>log files</b>) for its downloads:
          raw, CSV, MAT, Parquet, rerun .rrd</span></h2>
        <div class="runs-scroll">
          <table class="runs runs-table" id="runs-table">
            <thead><tr><th>#</th><th>who</th><th>when</th><th>build</th><th>duration</th><th>status</th>
              <th>cycles</th><th>misses</th><th>records</th><th>lost</th><th>logs</th></tr></thead>
            <tbody id="runs-list"></tbody>
          </table>
        </div>
      </section>
      <section class="panel wide hidden" id="panel-run-logs">
        <h2>Run <span id="rl-title"></span></h2>
        <div class="rejected hidden" id="rl-note" role="status"></div>
        <div class="hidden" id="rl-safe" role="status"></div>
        <div id="rl-files"></div>
      </section>
      <section class="panel wide" id="panel-rerun">
        <h2>Plots (rerun) <span class="muted small" id="rr-what">not loaded</span>
          <button id="rr-live" class="secondary small">Live plots</button></h2>
        <div class="rejected hidden" id="rr-message" role="status"></div>
        <div class="muted small" id="rr-hint">The rerun viewer opens in a tab of its own when you ask for it:
          <b>Live plots</b> for the running run, <b>Open in rerun</b> on a log file. <b>Esc</b> in that tab
          stops the run, as here.</div>
        <div class="small hidden" id="rr-opened">Opened in a new tab: <a id="rr-link" target="_blank"
          rel="noopener">open it again</a> (if the browser blocked the new tab, this link opens it).</div>
      </section>`;
    el.querySelector("#rr-live").addEventListener("click", () => openLive(el));
  }

  function lostBadge(n) {
    const b = document.createElement("span");
    b.className = "lost-badge" + (n > 0 ? " bad" : "");
    b.textContent = `lost: ${num(n)}`;
    b.title = n > 0 ? "records the loop could not hand over (ring full) or that could not be written" : "no record lost";
    return b;
  }

  // The viewer's code in the browser's cache while a live run is listed (issue 31 bug 6, session 11):
  // "Live plots" is likely soon, and a first opening fetched the viewer's 14 MB of compressed wasm
  // (43 MB) and its script then, before anything else could happen: seconds over a lab's Wi-Fi.
  // Read to the end and dropped here (the HTTP cache keeps them, cached a day by the appliance),
  // once per dashboard; not compiled here: chromium keeps compiled wasm only for a module that has
  // run (the viewer's first opening), and compiling 43 MB for nothing costs a 2-core machine seconds
  // of CPU. Nothing is fetched while no run is live: a dashboard that never watches one stays light.
  const VIEWER_CODE = ["/rerun/re_viewer_bg.wasm", "/rerun/re_viewer.js"];
  let warmed = false, warmAsked = null;
  async function warmViewer() {
    if (warmed) return;
    warmed = true;
    for (const path of VIEWER_CODE) {
      try {
        // Already in the cache (the viewer was opened before: the usual case): nothing to do. Read
        // again, the 43 MB cost the dashboard's renderer CPU just when the viewer's tab may start.
        const cached = await fetch(path, { credentials: "same-origin", mode: "same-origin", cache: "only-if-cached" })
          .catch(() => null);
        if (cached && cached.ok) { cached.body.cancel(); continue; }
        const res = await fetch(path, { credentials: "same-origin" });
        const reader = res.body.getReader();
        while (!(await reader.read()).done) { /* into the cache, not into memory */ }
      } catch (e) { /* the viewer's opening fetches it then */ }
    }
  }

  async function loadList(el) {
    let runs;
    try { runs = await xrf.api("GET", "/api/logs/runs?limit=200"); } catch (e) { return; }
    xrf.runsList = runs;  // test hook
    // A live run listed: is it one this user may watch live (and is live streaming on)? Asked once
    // per run: then the viewer's code is put in the HTTP cache (warmViewer).
    const live = runs.find((r) => r.live);
    if (live && !warmed && warmAsked !== live.id) {
      warmAsked = live.id;
      rerunInfo(el).then((info) => { if (info.live_running && info.live_allowed) warmViewer(); });
    }
    const body = el.querySelector("#runs-list");
    // Rows are updated in place, never rebuilt: a table rebuilt every 2 s swallowed clicks (the
    // row under the mouse was replaced between press and release: issue 19).
    const old = new Map([...body.children].map((tr) => [tr.id, tr]));
    runs.forEach((r, k) => {
      const id = "runs-row-" + r.id;
      const tr = old.get(id) || document.createElement("tr");
      old.delete(id);
      tr.id = id;
      const className = (r.id === selected ? "selected " : "") + (r.live ? "live" : "");
      if (tr.className !== className) tr.className = className;
      const status = r.status + xrf.endReason(r) + (r.live ? " · live" : "");
      const cells = [r.id, r.owner || "–", when(r.started), r.build, dur(r.duration_s), status,
        num(r.cycles), num(r.misses), num(r.log_records)];
      while (tr.children.length < cells.length + 2) tr.appendChild(document.createElement("td"));
      cells.forEach((c, i) => {
        const td = tr.children[i];
        if (td.textContent !== String(c)) td.textContent = c;
        const cls = i === 5 && r.crashed ? "crashed" : i === 7 && r.misses > 0 ? "warn-text" : "";
        if (td.className !== cls) td.className = cls;
      });
      const key = `${r.log_lost}|${r.log_note || ""}`;
      const td = tr.children[cells.length];
      if (td.dataset.key !== key) {
        td.dataset.key = key;
        td.textContent = "";
        td.appendChild(lostBadge(r.log_lost));
        if (r.log_note) {
          const w = document.createElement("span");
          w.className = "log-note"; w.textContent = "⚠"; w.title = r.log_note;
          td.appendChild(w);
        }
      }
      const logs = tr.children[cells.length + 1];
      if (!logs.firstChild) {
        // A real button (not text that looks like links): it opens the run's files below, where
        // each format is a download link (the same routes and permissions as everywhere).
        const b = document.createElement("button");
        b.className = "secondary small open-logs";
        b.textContent = "log files ▾";
        b.title = "show this run's log files, each downloadable as raw, CSV, MAT, Parquet or rerun .rrd";
        b.addEventListener("click", (ev) => { ev.stopPropagation(); select(el, r.id, true); });
        logs.appendChild(b);
      }
      tr.title = r.log_note || r.message;
      if (!tr.dataset.wired) { tr.dataset.wired = "1"; tr.addEventListener("click", () => select(el, r.id)); }
      if (body.children[k] !== tr) body.insertBefore(tr, body.children[k] || null);
    });
    for (const tr of old.values()) tr.remove();
  }

  function safeOutcome(o) {
    const who = o.by === "xrf-watch"
      ? "The appliance died during this run. Its safety watcher (xrf-watch)"
      : `The controller failed (${o.reason}). The safety watcher`;
    let t = `${who} ${o.loop_killed ? "killed the loop and " : ""}made the outputs safe ${o.safe_ms.toFixed(2)} ms after`;
    if (o.phase !== "none") {
      t += `; it held the arm (largest joint drop ${o.drop_deg.toFixed(2)}°)`;
      t += o.rest_s !== null ? ` and lowered it onto its rest stops: at rest ${o.rest_s.toFixed(1)} s after` : `, not at rest when last recorded`;
      t += ` (final phase: ${o.phase})`;
    }
    return t + ".";
  }

  async function select(el, id, reveal) {
    selected = id;
    el.querySelectorAll("#runs-list tr").forEach((tr) => tr.classList.toggle("selected", tr.id === "runs-row-" + id));
    let d;
    try { d = await xrf.api("GET", `/api/logs/runs/${id}`); } catch (e) { return; }
    if (selected !== id) return;
    xrf.runLogs = d;  // test hook
    const $ = (i) => el.querySelector("#" + i);
    $("panel-run-logs").classList.remove("hidden");
    const r = d.run;
    $("rl-title").textContent = `#${r.id} · ${r.build} · ${r.status}${r.live ? " (live)" : ""}`;
    $("rl-note").textContent = r.log_note ? "Logging stopped: " + r.log_note : "";
    $("rl-note").classList.toggle("hidden", !r.log_note);
    // What a safety watcher did for a `hold` run: the appliance's own when the loop failed, the
    // run's xrf-watch while the appliance was gone (its record, read at the restart).
    const o = r.safe_outcome;
    $("rl-safe").textContent = o ? safeOutcome(o) : "";
    $("rl-safe").classList.toggle("hidden", !o);
    const box = $("rl-files");
    box.textContent = "";
    if (!d.files.length) {
      box.innerHTML = '<div class="muted">This run has no log file (its controller did not start a logger).</div>';
    }
    for (const f of d.files) {
      const div = document.createElement("div");
      div.className = "log-file";
      const base = `/api/logs/runs/${r.id}/files/${f.name.split("/").map(encodeURIComponent).join("/")}`;
      const links = FORMATS.map(([fmt, label]) =>
        `<a class="dl" data-fmt="${fmt}" href="${base}?fmt=${fmt}" download>${label}</a>`).join(" ");
      const vars = f.variables.map((v) => `${esc(v.name)} <span class="muted">${esc(v.type)}</span>`).join(", ");
      div.innerHTML = `
        <div class="row"><strong>${esc(f.name)}</strong>
          <span class="muted">${num(f.size)} bytes · ${num(f.records)} records · ${f.kind}</span>
          <span class="badge-slot"></span>
          <span class="downloads">${links}</span>
          <button class="secondary small open-rrd">Open in rerun</button></div>
        <div class="small vars">${vars}</div>
        ${f.error ? `<div class="rejected">${esc(f.error)}</div>` : ""}
        ${f.skipped.length ? `<div class="skipped"><strong>The decoder skipped ${num(f.skipped_bytes)} bytes:</strong><ul>${f.skipped.map((s) => `<li>${esc(s)}</li>`).join("")}</ul></div>` : ""}`;
      div.querySelector(".badge-slot").appendChild(lostBadge(f.lost));
      div.querySelector(".open-rrd").addEventListener("click", () => openRrd(el, r.id, f.name));
      box.appendChild(div);
    }
    if (d.timing) {
      const t = document.createElement("div");
      t.className = "small";
      t.innerHTML = `<a href="/api/logs/runs/${r.id}/timing" download>framework timing per second (JSON lines)</a>`;
      box.appendChild(t);
    }
    if (reveal) $("panel-run-logs").scrollIntoView({ block: "nearest" });
  }

  async function rerunInfo(el) {
    try { rerun = await xrf.api("GET", "/api/logs/rerun"); } catch (e) { rerun = { available: false, error: e.message }; }
    const msg = el.querySelector("#rr-message");
    msg.textContent = rerun.available ? "" : "The rerun viewer is not available: " + (rerun.error || "?");
    msg.classList.toggle("hidden", !!rerun.available);
    return rerun;
  }

  // live: the run whose live stream the last opened viewer showed (null: a finished run's .rrd or
  // nothing). The viewer's tab follows the next run by itself (rerun-tab.js); this page's text too.
  let liveShown = null;
  // What the user asked for last, counted: an answer to an older request (the 2 s poll following
  // the live stream, a slow "Live plots") never overrides a newer click such as "Open in rerun"
  // (issue 19: a finished run's plots flipped back to the live stream).
  let asked = 0;

  // A tab of its own, without an opener: the browser gives it a renderer process of its own, so
  // however long the viewer's wasm blocks its thread, this page keeps reading its WebSocket.
  function show(el, url, what) {
    const src = "/rerun/?url=" + encodeURIComponent(url);
    window.open(src, "_blank", "noopener");
    el.querySelector("#rr-link").setAttribute("href", src);
    el.querySelector("#rr-opened").classList.remove("hidden");
    el.querySelector("#rr-what").textContent = what;
  }

  // The live stream comes through the appliance's own origin (its gRPC-web read proxy, behind the
  // login), from the Pi itself and from the LAN alike; only the run's owner and educators see it.
  async function openLive(el) {
    const ask = ++asked;
    const info = await rerunInfo(el);
    if (ask !== asked || !info.available) return;
    const msg = el.querySelector("#rr-message");
    if (!info.live_url) {
      liveShown = null;
      msg.textContent = "No live plots: " + (info.live_reason || "nothing is streaming")
        + ". A finished run of yours opens with 'Open in rerun' on its log (.rrd).";
      msg.classList.remove("hidden");
      return;
    }
    liveShown = info.live_run;
    show(el, info.live_url, `live: run ${info.live_run}` + (info.live_running ? "" : " (ended)"));
  }

  // A new run replaces the live stream: the viewer's tab follows it (rerun-tab.js), and so does
  // what this page says it shows. Never a new tab: only a click opens one.
  async function followLive(el) {
    if (liveShown === null) return;
    const ask = asked;
    let info;
    try { info = await xrf.api("GET", "/api/logs/rerun"); } catch (e) { return; }
    if (ask !== asked || liveShown === null || !info.live_url) return;  // the user opened something else meanwhile
    liveShown = info.live_run;
    el.querySelector("#rr-what").textContent = `live: run ${info.live_run}` + (info.live_running ? "" : " (ended)");
  }

  // rerun's viewer fetches a recording without our cookie and opens only a path ending in .rrd:
  // it gets a link of its own to this one log (server/http/logs.py viewer_link, valid for an hour).
  async function openRrd(el, id, name) {
    const ask = ++asked;
    liveShown = null;
    const info = await rerunInfo(el);
    if (ask !== asked || !info.available) return;
    const segs = name.split("/").map(encodeURIComponent).join("/");
    let link;
    try { link = await xrf.api("GET", `/api/logs/runs/${id}/viewer-link/${segs}`); } catch (e) { return; }
    if (ask !== asked) return;
    show(el, location.origin + link.path, `run ${id} (.rrd)`);
  }

  xrf.addPage({
    id: "runs",
    title: "Runs",
    order: 20,
    init(el) {
      el0 = el;
      html(el);
      xrf.on("run", () => { if (!el.classList.contains("hidden")) { loadList(el); if (selected) select(el, selected); } });
      xrf.on("alarm", (m) => { if (m.kind === "log" && !el.classList.contains("hidden")) loadList(el); });
    },
    show(el) {
      loadList(el);
      // Where the viewer is (nothing streams before a viewer opens).
      rerunInfo(el);
      if (selected) select(el, selected);
      clearInterval(timer);
      timer = setInterval(() => {
        if (el.classList.contains("hidden")) { clearInterval(timer); timer = null; return; }
        loadList(el);
        followLive(el);
      }, REFRESH_MS);
    },
  });
})();
