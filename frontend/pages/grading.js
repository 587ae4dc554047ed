// Grading (issue 32, docs/educators/grading.md): the student's "Check my project" panel on the
// Editor page and the educator's "Grades" page (one table per assignment). The results come from
// server/http/grading.py; the plots are drawn here as SVG (nothing is fetched from outside).
// Docs: docs/students/checking.md, docs/educators/grading.md.
"use strict";
(function () {
  const SVG = "http://www.w3.org/2000/svg";
  const POLL_MS = 500;
  const q = (id) => document.getElementById(id);
  const sleep = (ms) => new Promise((r) => setTimeout(r, ms));  // between polls of a job
  const detail = (r) => {
    const d = r.data && r.data.detail;
    if (!d) return `HTTP ${r.status}`;
    if (typeof d === "string") return d;
    return d.line ? `${d.file || "scenario"}:${d.line}: ${d.error}` : (d.error || JSON.stringify(d));
  };
  const fmt = (v) => (v == null ? "—" : typeof v === "number" ? (Math.abs(v) >= 100 || v === 0 ? String(+v.toPrecision(4)) : v.toPrecision(3)) : String(v));

  // ---- one check's plot: the signal over loop time, its window shaded, its bounds drawn ---------

  function svg(tag, attrs) {
    const e = document.createElementNS(SVG, tag);
    for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
    return e;
  }

  function plot(p, passed) {
    const W = 360, H = 150, L = 44, R = 8, T = 8, B = 22;
    const s = svg("svg", { viewBox: `0 0 ${W} ${H}`, class: "gr-plot", role: "img", "aria-label": `plot of ${p.signal}` });
    const t = p.t || [], y = p.y || [];
    const ys = y.concat((p.bounds || []).filter((b) => b.y != null).map((b) => b.y));
    const ts = t.concat((p.bounds || []).filter((b) => b.t != null).map((b) => b.t));
    if (!t.length) { const e = svg("text", { x: W / 2, y: H / 2, "text-anchor": "middle" }); e.textContent = "no samples"; s.append(e); return s; }
    let y0 = Math.min(...ys), y1 = Math.max(...ys);
    if (y1 - y0 < 1e-12) { y0 -= 1; y1 += 1; }
    const pad = (y1 - y0) * 0.08; y0 -= pad; y1 += pad;
    const t0 = Math.min(...ts), t1 = Math.max(...ts) > t0 ? Math.max(...ts) : t0 + 1;
    const X = (v) => L + (v - t0) / (t1 - t0) * (W - L - R);
    const Y = (v) => T + (y1 - v) / (y1 - y0) * (H - T - B);
    s.append(svg("rect", { x: L, y: T, width: W - L - R, height: H - T - B, class: "gr-frame" }));
    if (p.window) s.append(svg("rect", { x: X(p.window[0]), y: T, width: Math.max(0, X(p.window[1]) - X(p.window[0])), height: H - T - B, class: "gr-window" }));
    for (const b of p.bounds || []) {
      const line = b.y != null ? svg("line", { x1: L, x2: W - R, y1: Y(b.y), y2: Y(b.y), class: "gr-bound" })
        : svg("line", { x1: X(b.t), x2: X(b.t), y1: T, y2: H - B, class: "gr-bound" });
      const title = svg("title", {}); title.textContent = b.label || ""; line.append(title);
      s.append(line);
      const lab = svg("text", b.y != null ? { x: W - R - 2, y: Y(b.y) - 2, "text-anchor": "end", class: "gr-blabel" } : { x: X(b.t) + 2, y: T + 10, class: "gr-blabel" });
      lab.textContent = b.label || ""; s.append(lab);
    }
    s.append(svg("polyline", { points: t.map((v, i) => `${X(v).toFixed(1)},${Y(y[i]).toFixed(1)}`).join(" "), class: "gr-line " + (passed ? "pass" : "fail") }));
    for (const [v, yy, anchor] of [[y1 - pad, T + 9, "end"], [y0 + pad, H - B, "end"]]) {
      const e = svg("text", { x: L - 3, y: yy, "text-anchor": anchor, class: "gr-axis" }); e.textContent = fmt(v); s.append(e);
    }
    for (const [v, anchor] of [[t0, "start"], [t1, "end"]]) {
      const e = svg("text", { x: X(v), y: H - 6, "text-anchor": anchor, class: "gr-axis" }); e.textContent = fmt(v) + " s"; s.append(e);
    }
    return s;
  }

  // ---- a whole result: total, status, one row per check with its plot -----------------------------

  function renderResult(box, res) {
    box.textContent = "";
    if (!res) { box.innerHTML = `<p class="muted">Not checked yet.</p>`; return; }
    const ok = res.status === "completed";
    const head = document.createElement("p");
    head.className = "gr-total";
    head.innerHTML = `<b>${xrf.esc(res.earned)} / ${xrf.esc(res.points)}</b> points · ${xrf.esc(res.scenario)}`
      + (ok ? "" : ` · <span class="bad">${xrf.esc(res.status)}: ${xrf.esc(res.reason)}</span>`)
      + (res.virtual_time ? ` · <span class="muted">simulated time</span>` : "")
      + (res.build ? ` · <span class="muted">build ${xrf.esc(res.build.id != null ? res.build.id : res.build)}</span>` : "");
    box.append(head);
    const list = document.createElement("ul");
    list.className = "gr-checks";
    for (const c of res.checks || []) {
      const li = document.createElement("li");
      li.className = "gr-check " + (c.passed ? "pass" : "fail");
      li.dataset.check = c.id;
      li.innerHTML = `<div class="gr-row"><span class="gr-mark">${c.passed ? "PASS" : "FAIL"}</span>
        <b>${xrf.esc(c.id)}</b> <span class="muted">${xrf.esc(c.kind)}</span>
        <span class="gr-pts">${xrf.esc(c.earned)} / ${xrf.esc(c.points)}</span></div>
        <div class="small">${c.value != null ? "measured " + xrf.esc(fmt(c.value)) + " · " : ""}${xrf.esc(c.limit || "")}</div>
        ${c.passed ? "" : `<div class="small bad">${xrf.esc(c.reason || "")}${c.message ? " — " + xrf.esc(c.message) : ""}</div>`}`;
      if (c.plot) li.append(plot(c.plot, c.passed));
      list.append(li);
    }
    box.append(list);
    if (!ok && res.output_tail) {
      const pre = document.createElement("pre");
      pre.className = "gr-tail";
      pre.textContent = Array.isArray(res.output_tail) ? res.output_tail.join("\n") : String(res.output_tail);
      box.append(pre);
    }
  }

  // ---- the student's panel on the Editor page ---------------------------------------------------

  const S = { pid: null, busy: false };
  window.xrfGrading = { S, plot, renderResult };  // test hook and the Grades page's renderer

  function panel() {
    let p = q("gr-panel");
    if (p) return p;
    const main = q("ed-main");
    if (!main) return null;
    p = document.createElement("div");
    p.id = "gr-panel";
    p.className = "gr-panel hidden";
    p.innerHTML = `<h3>Check my project <span class="muted small" id="gr-scenario"></span></h3>
      <div class="row"><button id="gr-check" title="run the assignment's checks on the newest build, on a simulated robot">Check my project</button>
      <span id="gr-msg" class="small" role="status"></span></div>
      <div id="gr-result" class="gr-result"></div>`;
    main.insertBefore(p, q("ed-cm"));
    q("gr-check").addEventListener("click", () => check().catch((e) => say(e.message, "bad")));
    return p;
  }

  function say(text, kind) { const m = q("gr-msg"); if (m) { m.textContent = text; m.className = "small " + (kind || ""); } }

  async function follow(pid) {
    for (;;) {
      const r = await xrfLib.send("GET", `/api/projects/${pid}/grade`);
      if (S.pid !== pid) return;
      if (!r.ok) { say(detail(r), "bad"); return; }
      const j = r.data.job || {};
      const done = !j.status || j.status === "done";  // queued, running, done (grading/queue.py)
      if (done && r.data.result) { renderResult(q("gr-result"), r.data.result); say(""); return; }
      say(`checking… ${j.status || ""}`);
      await sleep(POLL_MS);
    }
  }

  async function check() {
    const pid = S.pid;
    if (pid == null || S.busy) return;
    S.busy = true; q("gr-check").disabled = true;
    try {
      const r = await xrfLib.send("POST", `/api/projects/${pid}/grade`);
      if (r.status === 429) {
        const after = r.res.headers.get("Retry-After");
        say(`Checked a moment ago: again in ${after || "a few"} s.`, "bad");
        return;
      }
      if (!r.ok) { say(detail(r), "bad"); return; }
      say("checking…");
      await follow(pid);
    } finally { S.busy = false; q("gr-check").disabled = false; }
  }

  async function showFor(pid) {
    S.pid = pid;
    const p = panel();
    if (!p) return;
    p.classList.add("hidden");
    q("gr-result").textContent = ""; say("");
    const project = await xrfLib.send("GET", `/api/projects/${pid}`);
    const origin = project.ok ? String(project.data.origin || "") : "";
    if (!origin.startsWith("assignment:") || S.pid !== pid) return;
    const sc = await xrfLib.send("GET", `/api/assignments/${encodeURIComponent(origin.slice(11))}/scenario`);
    if (!sc.ok || S.pid !== pid) return;  // an assignment without a scenario: nothing to check
    q("gr-scenario").textContent = `${sc.data.name} · ${sc.data.points} points`;
    p.classList.remove("hidden");
    const last = await xrfLib.send("GET", `/api/projects/${pid}/grade`);
    if (S.pid === pid && last.ok && last.data.result) renderResult(q("gr-result"), last.data.result);
  }

  document.addEventListener("xrf-editor-project", (ev) => showFor(ev.detail).catch(() => {}));

  // ---- the educator's Grades page -------------------------------------------------------------

  const G = { aid: null, table: null, polling: false };

  async function loadAssignments() {
    const sel = q("gr-assignment");
    const ts = await xrf.api("GET", "/api/project-templates");
    const keep = sel.value;
    sel.textContent = "";
    for (const t of ts.filter((t) => t.assignment)) {
      const o = document.createElement("option");
      o.value = t.name.slice("assignment:".length); o.textContent = t.title;
      sel.append(o);
    }
    if (keep && [...sel.options].some((o) => o.value === keep)) sel.value = keep;
    if (!sel.options.length) q("gr-table").innerHTML = `<p class="muted">No assignment published yet (Room page).</p>`;
  }

  function renderTable(t) {
    G.table = t;
    const box = q("gr-table");
    const checks = t.checks || [];
    const rows = (t.rows || []).map((r) => {
      const cells = checks.map((c) => {
        const x = (r.checks || {})[c.id];
        if (!x) return `<td class="muted">—</td>`;
        return `<td class="${x.passed ? "pass" : "fail"}" title="${xrf.esc(x.value != null ? "measured " + fmt(x.value) : "")}">${xrf.esc(x.earned)}</td>`;
      }).join("");
      const status = r.status === "completed" ? "" : `<span class="bad" title="${xrf.esc(r.reason)}">${xrf.esc(r.status || "not graded")}</span>`;
      return `<tr data-project="${xrf.esc(r.project)}"><td>${xrf.esc(r.owner)}</td><td>${xrf.esc(r.name)}</td>
        <td class="mono">${xrf.esc(r.build != null ? (r.build.id != null ? r.build.id : r.build) : "—")}</td>${cells}
        <td><b>${xrf.esc(r.earned != null ? r.earned : "—")}</b> / ${xrf.esc(r.points != null ? r.points : "")} ${status}</td>
        <td><button class="secondary small gr-open" data-project="${xrf.esc(r.project)}">plots &amp; log</button></td></tr>`;
    }).join("");
    box.innerHTML = `<table class="gr-table"><thead><tr><th>student</th><th>project</th><th>build</th>
      ${checks.map((c) => `<th title="${xrf.esc(c.kind)}">${xrf.esc(c.id)}<br><span class="muted small">${xrf.esc(c.points)} pt</span></th>`).join("")}
      <th>total</th><th></th></tr></thead><tbody>${rows || `<tr><td colspan="${checks.length + 5}" class="muted">No student project of this assignment yet.</td></tr>`}</tbody></table>`;
    for (const b of box.querySelectorAll(".gr-open")) b.addEventListener("click", () => openRow(b.dataset.project));
    showProgress(t.progress);
  }

  function showProgress(p) {
    const e = q("gr-progress");
    if (!p || !p.total) { e.textContent = ""; return false; }
    const done = p.done != null ? p.done : (p.total - (p.queued || 0) - (p.running || 0));
    e.innerHTML = `<progress max="${xrf.esc(p.total)}" value="${xrf.esc(done)}"></progress> ${xrf.esc(done)} / ${xrf.esc(p.total)} graded${p.running ? `, ${xrf.esc(p.running)} running` : ""}`;
    return done < p.total;
  }

  async function loadTable() {
    if (!G.aid) return;
    const r = await xrfLib.send("GET", `/api/assignments/${encodeURIComponent(G.aid)}/grades`);
    if (!r.ok) { q("gr-table").innerHTML = `<p class="bad">${xrf.esc(detail(r))}</p>`; return; }
    renderTable(r.data);
    q("gr-csv").href = `/api/assignments/${encodeURIComponent(G.aid)}/grades.csv`;
    return r.data;
  }

  async function pollWhileRunning() {
    if (G.polling) return;
    G.polling = true;
    try {
      for (;;) {
        const t = await loadTable();
        if (!t || !showProgress(t.progress)) break;
        await sleep(POLL_MS);
      }
    } finally { G.polling = false; }
  }

  async function rerun() {
    const r = await xrfLib.send("POST", `/api/assignments/${encodeURIComponent(G.aid)}/grades/rerun`);
    if (!r.ok) { q("gr-progress").textContent = detail(r); return; }
    showProgress(r.data.progress);
    await pollWhileRunning();
  }

  async function openRow(pid) {
    const d = q("gr-detail");
    const r = await xrfLib.send("GET", `/api/projects/${encodeURIComponent(pid)}/grade`);
    d.innerHTML = `<h3>Project ${xrf.esc(pid)} <button class="secondary small" id="gr-detail-close">close</button></h3><div id="gr-detail-body"></div>`;
    q("gr-detail-close").addEventListener("click", () => { d.textContent = ""; });
    if (!r.ok) { q("gr-detail-body").textContent = detail(r); return; }
    renderResult(q("gr-detail-body"), r.data.result);
    const res = r.data.result;
    if (res && res.log) {
      const a = document.createElement("a");
      a.href = typeof res.log === "string" ? res.log : (res.log.url || "#");
      a.textContent = "the run's log"; a.className = "small";
      q("gr-detail-body").append(a);
    }
  }

  xrf.addPage({
    id: "grades", title: "Grades", order: 62, perm: "educator",
    init(root) {
      root.innerHTML = `<section class="panel">
        <h2>Grades <span class="spacer"></span>
          <select id="gr-assignment" aria-label="assignment"></select>
          <button id="gr-rerun" title="grade every project of this assignment on its latest build (queued)">Re-run all</button>
          <a id="gr-csv" class="button secondary small" download>CSV</a></h2>
        <div id="gr-progress" class="small" role="status"></div>
        <div id="gr-table" class="gr-tablebox"></div>
        <div id="gr-detail" class="gr-result"></div></section>`;
      q("gr-assignment").addEventListener("change", () => { G.aid = q("gr-assignment").value; loadTable(); });
      q("gr-rerun").addEventListener("click", () => rerun().catch((e) => { q("gr-progress").textContent = e.message; }));
    },
    async show() {
      await loadAssignments();
      G.aid = q("gr-assignment").value || null;
      await pollWhileRunning();
    },
  });
})();
