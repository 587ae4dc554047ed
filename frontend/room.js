// The room page: one tile per bench, fed by /api/room/ws; alarms first, then offline benches.
// Everything it loads comes from the room itself (nothing from the internet).
"use strict";

(function () {
  const $ = (id) => document.getElementById(id);
  const benches = new Map();
  window.xrfRoom = { benches, connected: false };

  async function post(path, body) {
    const { ok, data, res } = await xrfLib.send("POST", path, body || {});  // frontend/lib.js
    if (!ok) throw new Error(typeof data.detail === "string" ? data.detail : res.statusText);
    return data;
  }

  function note(text) { $("room-note").textContent = text; }

  function rank(b) { return (b.online && b.alarms && b.alarms.length) ? 0 : !b.online ? 1 : 2; }

  function el(tag, cls, text) {
    const e = document.createElement(tag);
    if (cls) e.className = cls;
    if (text !== undefined) e.textContent = text;
    return e;
  }

  function tile(b) {
    const t = el("div", "tile");
    t.dataset.bench = b.name;
    const state = b.online ? (b.state || "?") : "OFFLINE";
    t.classList.add("state-" + String(b.state || "").toLowerCase().replace(/\s+/g, "-"));
    if (!b.online) t.classList.add("offline");
    if (b.online && b.alarms && b.alarms.length) t.classList.add("has-alarm");
    const head = el("div", "head");
    head.append(el("span", "name", b.name), el("span", "state", state));
    t.append(head);
    t.append(el("div", "line holder", b.holder ? "held by " + b.holder : (b.run_owner ? "run of " + b.run_owner : "free")));
    const alarm = b.alarms && b.alarms.length ? b.alarms[b.alarms.length - 1] : null;
    t.append(el("div", "line alarm", alarm ? alarm.kind + ": " + alarm.message : ""));
    const facts = [];
    if (b.cycle_rate != null) facts.push(Math.round(b.cycle_rate) + " Hz");
    if (b.misses) facts.push(b.misses + " missed");
    if (b.cpu_temp_c != null) facts.push(b.cpu_temp_c + " °C");
    if (b.throttled) facts.push("throttled");
    if (b.disk_free_mb != null) facts.push((b.disk_free_mb / 1024).toFixed(1) + " GB free");
    t.append(el("div", "line facts", facts.join(" · ")));
    const sc = b.selfcheck;
    t.append(el("div", "line selfcheck", sc ? "self-check: " + (sc.verdict || "?") : ""));
    if (b.problem) t.append(el("div", "line problem", b.problem));
    const btns = el("div", "btns");
    const stop = el("button", "stop", "Stop");
    stop.addEventListener("click", () => post("/api/room/stop", { bench: b.name }).then(() => note("stop sent to " + b.name), (e) => note(e.message)));
    const open = el("button", "open", "Open");
    open.disabled = !b.online || b.enrolment !== "ok";
    open.addEventListener("click", async () => {
      try { const r = await post("/api/room/benches/" + encodeURIComponent(b.name) + "/sso"); window.open(r.url, "_blank", "noopener"); }
      catch (e) { note(e.message); }
    });
    btns.append(stop, open);
    t.append(btns);
    return t;
  }

  function render() {
    const list = [...benches.values()].sort((a, b) => rank(a) - rank(b) || a.name.localeCompare(b.name));
    $("room-grid").replaceChildren(...list.map(tile));
    const online = list.filter((b) => b.online).length;
    $("room-counts").textContent = `${online} of ${list.length} benches online`;
    enrolledCount = list.length;
  }

  let pending = false;
  function schedule() { if (!pending) { pending = true; requestAnimationFrame(() => { pending = false; render(); }); } }

  function connect() {
    const ws = new WebSocket((location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/api/room/ws");
    ws.onmessage = (ev) => {
      const m = JSON.parse(ev.data);
      if (m.type === "snapshot") {
        benches.clear();
        for (const b of m.benches) benches.set(b.name, b);
        window.xrfRoom.connected = m.connected;
        $("room-broker").textContent = m.connected ? "broker connected" : "broker unreachable";
        $("room-broker").classList.toggle("bad", !m.connected);
      } else if (m.type === "bench") {
        benches.set(m.bench.name, m.bench);
      } else if (m.type === "grades") {
        if (grading.aid === m.assignment) loadGrades();  // a bench sent a newer table
        return;
      }
      schedule();
    };
    ws.onclose = () => { $("room-broker").textContent = "room unreachable"; $("room-broker").classList.add("bad"); setTimeout(connect, 1000); };
  }

  $("room-stop-all").addEventListener("click", () =>
    post("/api/room/stop", {}).then((r) => note("stop sent to " + r.benches.length + " benches"), (e) => note(e.message)));
  $("room-msg-form").addEventListener("submit", (ev) => {
    ev.preventDefault();
    const text = $("room-msg").value.trim();
    if (text) post("/api/room/message", { text }).then(() => { note("message sent"); $("room-msg").value = ""; }, (e) => note(e.message));
  });
  $("room-selfcheck").addEventListener("click", () =>
    post("/api/room/selfcheck", {}).then((r) => note("self-check asked of " + (r.benches.join(", ") || "no bench") + (r.busy && r.busy.length ? " (running, skipped: " + r.busy.join(", ") + ")" : "")), (e) => note(e.message)));
  $("room-join").addEventListener("click", () =>
    post("/api/room/join-codes", {}).then((r) => { $("room-join-code").textContent = r.code; note("on the bench: xrf room join " + location.origin + " " + r.code + " --name NAME"); }, (e) => note(e.message)));

  // ---- assignments: publish to every bench, collect every run as one archive ----
  let enrolledCount = 0;
  const collecting = new Map(); // assignment id -> the collection being followed

  async function loadAssignments() {
    const res = await fetch("/api/room/assignments");
    if (!res.ok) return;
    const list = await res.json();
    const items = list.slice().reverse().map((a) => {
      const li = el("li");
      li.dataset.assignment = a.id;
      li.append(el("span", "aname", a.name), el("span", "muted holders", a.benches.length + " of " + enrolledCount + " benches"));
      const collect = el("button", "collect", "Collect runs");
      collect.addEventListener("click", () => startCollect(a));
      li.append(collect);
      const gradesBtn = el("button", "grades", "Grades");
      gradesBtn.addEventListener("click", () => openGrades(a));
      li.append(gradesBtn);
      const c = collecting.get(a.id);
      if (c && c.done) {
        const link = el("a", "download", "Download (" + Object.values(c.benches).filter((s) => s === "collected").length + " collected, "
          + Object.values(c.benches).filter((s) => s !== "collected").length + " missing)");
        link.href = c.archive;
        link.setAttribute("download", "");
        li.append(link);
      } else if (c) {
        li.append(el("span", "muted", "collecting…"));
      }
      return li;
    });
    $("room-assign-list").replaceChildren(...items);
  }

  async function startCollect(a) {
    try {
      let c = await post("/api/room/assignments/" + encodeURIComponent(a.id) + "/collect", { formats: ["csv"] });
      collecting.set(a.id, c);
      loadAssignments();
      while (!c.done) {
        await new Promise((r) => setTimeout(r, 1000));
        const res = await fetch("/api/room/collections/" + c.id);
        if (!res.ok) throw new Error("the collection is gone");
        c = await res.json();
        collecting.set(a.id, c);
      }
      note("runs of " + a.name + " collected");
      loadAssignments();
    } catch (e) { note(e.message); }
  }

  // ---- grades: one table per assignment across every bench (each bench grades its own students) ----
  const grading = { aid: null, name: "", loading: false, again: false };
  const esc = xrfLib.esc;  // frontend/lib.js
  // a link only to a bench's own web address (from its enrolment, given by the room)
  const safeUrl = (u) => (/^https?:\/\//.test(u || "") ? u : "");

  async function openGrades(a) {
    grading.aid = a.id; grading.name = a.name;
    $("room-grades").hidden = false;
    $("room-grades-title").textContent = "Grades: " + a.name;
    $("room-grades-csv").href = "/api/room/assignments/" + encodeURIComponent(a.id) + "/grades.csv";
    $("room-grades-table").textContent = "asking the benches…";
    await askGrades(false);
  }

  async function askGrades(rerun) {
    try {
      const r = await post("/api/room/assignments/" + encodeURIComponent(grading.aid) + "/grades", { rerun });
      note((rerun ? "re-run asked of " : "tables asked of ") + (r.benches.join(", ") || "no bench online")
        + (r.offline.length ? " (offline: " + r.offline.join(", ") + ")" : ""));
    } catch (e) { note(e.message); }
    await loadGrades();
  }

  async function loadGrades() {
    if (!grading.aid) return;
    if (grading.loading) { grading.again = true; return; }
    grading.loading = true;
    try {
      const res = await fetch("/api/room/assignments/" + encodeURIComponent(grading.aid) + "/grades");
      const t = await res.json();
      if (!res.ok) { $("room-grades-table").textContent = typeof t.detail === "string" ? t.detail : res.statusText; return; }
      renderGrades(t);
    } finally {
      grading.loading = false;
      if (grading.again) { grading.again = false; loadGrades(); }
    }
  }

  function renderGrades(t) {
    const checks = t.checks || [];
    const rows = t.rows.map((r) => {
      const cells = checks.map((c) => {
        const x = (r.checks || {})[c.id];
        return x ? `<td class="${x.passed ? "pass" : "fail"}" title="${esc(x.value != null ? "measured " + x.value : "")}">${esc(x.earned)}</td>` : `<td class="muted">—</td>`;
      }).join("");
      const status = r.status === "completed" ? "" : ` <span class="bad" title="${esc(r.reason)}">${esc(r.status)}</span>`;
      const plots = safeUrl(r.plots), log = safeUrl(r.log);
      return `<tr data-bench="${esc(r.bench)}" data-owner="${esc(r.owner)}"><td>${esc(r.owner)}</td><td>${esc(r.bench)}</td><td>${esc(r.name)}</td>
        <td class="mono">${esc(r.build || "—")}</td>${cells}<td class="total"><b>${esc(r.earned)}</b> / ${esc(r.points)}${status}${r.job && r.job !== "done" ? " (" + esc(r.job) + ")" : ""}</td>
        <td>${plots ? `<a href="${esc(plots)}" target="_blank" rel="noopener">plots</a>` : ""} ${log ? `<a href="${esc(log)}" target="_blank" rel="noopener">log</a>` : ""}</td></tr>`;
    }).join("");
    $("room-grades-table").innerHTML = `<table><thead><tr><th>student</th><th>bench</th><th>project</th><th>build</th>
      ${checks.map((c) => `<th title="${esc(c.kind)}">${esc(c.id)}<br><span class="muted small">${esc(c.points)} pt</span></th>`).join("")}
      <th>total</th><th></th></tr></thead><tbody>${rows || `<tr><td colspan="${checks.length + 6}" class="muted">No graded project yet${t.scenario ? "" : " (this assignment has no scenario in the room: choose one above)"}.</td></tr>`}</tbody></table>`;
    const benchLines = Object.entries(t.benches).map(([name, b]) => {
      const p = b.progress;
      const what = b.error ? `<span class="bad">${esc(b.error)}</span>` : !b.online ? "offline" : p ? `${esc(b.rows)} rows${p.total ? `, ${esc(p.done)}/${esc(p.total)} graded` : ""}${b.left_out ? `, ${esc(b.left_out)} left out` : ""}${b.same_checks === false ? ", <span class=\"bad\">other checks</span>" : ""}` : b.asked ? "waiting" : "not asked";
      return `<span data-bench="${esc(name)}">${esc(name)}: ${what}</span>`;
    });
    $("room-grades-benches").innerHTML = benchLines.join(" · ");
    const p = t.progress;
    $("room-grades-progress").innerHTML = p.total ? `<progress max="${esc(p.total)}" value="${esc(p.done)}"></progress> ${esc(p.done)} / ${esc(p.total)} graded across the room${p.running ? ", " + esc(p.running) + " running" : ""}` : "";
  }

  $("room-grades-rerun").addEventListener("click", () => askGrades(true));
  $("room-grades-refresh").addEventListener("click", () => askGrades(false));
  $("room-grades-close").addEventListener("click", () => { grading.aid = null; $("room-grades").hidden = true; });
  $("room-grades-scenario").addEventListener("change", async () => {
    const file = $("room-grades-scenario").files[0];
    if (!file || !grading.aid) return;
    const r = await xrfLib.send("PUT", "/api/room/assignments/" + encodeURIComponent(grading.aid) + "/scenario", await file.text(), { "Content-Type": "text/plain" });
    const d = r.data && r.data.detail;
    note(r.ok ? "scenario " + r.data.name + " kept: " + r.data.checks.length + " checks; it goes to every bench with the next re-run"
      : "scenario refused: " + (d && d.error ? (d.line ? "line " + d.line + ": " : "") + d.error : (typeof d === "string" ? d : r.res.statusText)));
    $("room-grades-scenario").value = "";
  });

  $("room-assign-template").addEventListener("change", () => {
    $("room-assign-file").hidden = $("room-assign-template").value !== "upload";
  });
  $("room-assign-form").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    const name = $("room-assign-name").value.trim();
    const template = $("room-assign-template").value;
    try {
      let a;
      if (template === "upload") {
        const file = $("room-assign-file").files[0];
        if (!file) throw new Error("choose an archive first");
        const up = await xrfLib.send("POST", "/api/room/assignments/upload?name=" + encodeURIComponent(name), file);
        a = up.data;
        if (!up.ok) throw new Error(typeof a.detail === "string" ? a.detail : up.res.statusText);
      } else {
        a = await post("/api/room/assignments", { name, template });
      }
      note("assignment " + a.name + " published to every bench");
      $("room-assign-name").value = "";
      loadAssignments();
    } catch (e) { note(e.message); }
  });

  fetch("/api/me").then((r) => (r.ok ? r.json() : null)).then((me) => {
    if (!me) { location.replace("/login"); return; }
    if (!me.perms.includes("educator")) { note("the room is for educators"); return; }
    connect();
    loadAssignments();
    setInterval(loadAssignments, 3000); // which benches have each assignment
  });
})();
