// Projects page: upload (drag-and-drop), new from a template, download, build with live output and
// clickable compiler errors, 20-sim facts, message fields, run a build on the bench, open it in the
// editor. Messages go where there is room: the page's own row above both columns (an upload's
// refusal names paths that never fit the 320 px list column), an action's refusal next to the
// button that was clicked ("run 4 is still active" beside that build's Run).
"use strict";
(function () {
  const P = { projects: [], current: null, detail: null, shownBuild: null, logs: {}, templates: [], rowMsg: {}, rules: null };
  window.xrfProjects = P;  // test hook
  const el = (tag, attrs, ...kids) => {
    const e = document.createElement(tag);
    for (const [k, v] of Object.entries(attrs || {})) {
      if (k === "class") e.className = v; else if (k === "text") e.textContent = v;
      else if (k.startsWith("on")) e.addEventListener(k.slice(2), v); else e.setAttribute(k, v);
    }
    for (const k of kids) if (k != null) e.append(k);
    return e;
  };
  const q = (id) => document.getElementById(id);
  const fmtErr = (e) => { try { const d = JSON.parse(e.message); return d.error || e.message; } catch (_) { return e.message; } };

  async function uploadFile(file, pid) {
    const form = new FormData();
    form.append("file", file, file.name);
    const url = pid ? `/api/projects/${pid}/source` : "/api/projects";
    status(`Checking ${file.name}…`);
    const { ok, data, res } = await xrfLib.send(pid ? "PUT" : "POST", url, form);
    if (!ok) {
      const d = data.detail;
      const text = d && typeof d === "object" ? (d.error || JSON.stringify(d)) : (d || res.statusText);
      status(text, true);
      throw new Error(text);
    }
    status(`${file.name}: ${data.files} files, ${(data.bytes / 1024).toFixed(1)} KB` + (data.skipped.length ? ` (left out ${data.skipped.join(", ")})` : "")
      + (data.package ? `; a workspace: its controller package ${data.package}/ is built, the project is named ${data.project.name}` : "")
      + " — ready to build");
    await loadProjects();
    await select(data.project.id);
    return data;
  }

  function status(text, bad) {
    const s = q("proj-status");
    s.textContent = text;
    s.className = "proj-status" + (bad ? " bad" : "");
  }

  // What an upload may be and hold, from the server's check (projects/archive.py rules()).
  const mb = (n) => `${Math.round(n / (1 << 20))} MB`;
  async function loadRules() {
    const r = P.rules = await xrf.api("GET", "/api/project-upload-rules");
    const box = q("proj-rules");
    box.textContent = "";
    box.append(el("div", { text: `One archive (${r.formats.join(", ")}), at most ${mb(r.max_upload)}` +
      ` (${mb(r.max_total)} unpacked, ${r.max_files} files), holding one of:` }));
    const ul = el("ul");
    for (const l of r.layouts) ul.append(el("li", { text: l }));
    box.append(ul, el("div", { text: `Left out when unpacking: ${r.left_out.join(" ")}` }));
    for (const id of ["proj-file", "proj-update-file"]) q(id).setAttribute("accept", r.formats.join(","));
  }

  async function loadProjects() {
    P.projects = await xrf.api("GET", "/api/projects");
    const ul = q("proj-list");
    ul.textContent = "";
    if (!P.projects.length) ul.append(el("li", { class: "muted", text: "No projects yet: upload one or start from a template." }));
    for (const p of P.projects) {
      ul.append(el("li", { "data-id": p.id, class: p.id === P.current ? "current" : "", onclick: () => select(p.id) },
        el("span", { class: "pname", text: p.name }), el("span", { class: "muted small", text: ` #${p.id} · ${p.origin}` })));
    }
  }

  async function select(pid) {
    if (P.current !== pid) {
      // Another project: nothing of the previous one's build may stay on screen (issue 19: project
      // A showed project B's compile error and source).
      P.shownBuild = null;
      P.rowMsg = {};
      actionMsg("");
      q("proj-build-title").textContent = "Build output";
      q("proj-build-title").className = "";
      q("proj-diags").textContent = "";
      q("proj-log").textContent = "";
      q("proj-source").textContent = "";
      q("proj-source").classList.add("hidden");
    }
    P.current = pid;
    document.querySelectorAll("#proj-list li").forEach((li) => li.classList.toggle("current", Number(li.dataset.id) === pid));
    const d = await xrf.api("GET", `/api/projects/${pid}`);
    if (P.current !== pid) return;  // another project was picked meanwhile
    P.detail = d;
    q("proj-detail").classList.remove("hidden");
    q("proj-name").textContent = `${d.name} (#${d.id})`;
    q("proj-download").href = `/api/projects/${pid}/download`;
    // A workspace: which of its packages is built (the build log says it too, but nobody reads it first).
    q("proj-package").textContent = d.package
      ? `A ROS 2 workspace: builds its controller package ${d.package.name} (${d.package.path}/)` : "";
    q("proj-package").classList.toggle("hidden", !d.package);
    renderTwentySim(d.twenty_sim);
    renderMessages(d.messages);
    renderBuilds(d.builds);
    if (d.builds.length && P.shownBuild == null) showBuild(d.builds[0].id);
  }

  function renderTwentySim(t) {
    const box = q("proj-20sim");
    box.textContent = "";
    if (!t) { box.append(el("div", { class: "muted", text: "No 20-sim controller/ folder." })); return; }
    const dl = el("dl", { class: "facts" });
    const add = (k, v, id) => dl.append(el("dt", { text: k }), el("dd", { text: v == null || v === "" ? "–" : String(v), id }));
    add("submodel", t.submodel, "ts-submodel");
    add("step size", t.time_step_size != null ? `${t.time_step_size} s` : null, "ts-step");
    add("cycle frequency", t.frequency_hz != null ? `${t.frequency_hz} Hz` : null, "ts-freq");
    add("integration method", t.integration_method, "ts-method");
    add("inputs", t.inputs.join(", "), "ts-inputs");
    add("outputs", t.outputs.join(", "), "ts-outputs");
    box.append(dl);
    for (const p of t.problems || []) box.append(el("div", { class: "bad", text: p }));
  }

  function renderMessages(m) {
    const box = q("proj-msgs");
    box.textContent = "";
    for (const name of ["Ros2Xeno", "Xeno2Ros"]) {
      const f = m[name];
      const text = Array.isArray(f) ? (f.map((x) => `${x.type}${x.count ? `[${x.count}]` : ""} ${x.name}`).join(", ") || "(no fields)") : `error: ${f.error}`;
      box.append(el("div", { class: "msgline" }, el("b", { text: name + ": " }), el("span", { id: `msg-${name}`, text })));
    }
  }

  function renderBuilds(builds) {
    const tb = q("proj-builds");
    tb.textContent = "";
    for (const b of builds) {
      const run = b.runnable ? el("button", { class: "small", "data-run": b.id, text: "Run", onclick: (e) => { e.stopPropagation(); runBuild(b.id); } }) : null;
      const st = b.status === "queued" && b.position > 0 ? `queued (#${b.position})` : b.status;
      const msg = P.rowMsg[b.id];
      tb.append(el("tr", { "data-build": b.id, class: (b.id === P.shownBuild ? "current " : "") + "st-" + b.status, onclick: () => showBuild(b.id) },
        el("td", { text: b.id }), el("td", { class: "bstatus", text: st }), el("td", { class: "bresult", text: b.result }),
        el("td", { text: b.duration != null ? b.duration.toFixed(1) + " s" : "" }), el("td", { class: "mono small", text: b.source_hash }),
        el("td", { class: "brun" }, run, msg ? el("span", { class: "action-msg" + (msg.bad ? " bad" : ""), role: "status", text: msg.text }) : null)));
    }
  }

  async function refreshBuilds() {
    if (P.current == null) return;
    const builds = await xrf.api("GET", `/api/projects/${P.current}/builds`);
    if (P.detail) P.detail.builds = builds;
    renderBuilds(builds);
    return builds;
  }

  async function showBuild(bid) {
    P.shownBuild = bid;
    const pid = P.current;
    document.querySelectorAll("#proj-builds tr").forEach((tr) => tr.classList.toggle("current", Number(tr.dataset.build) === bid));
    const b = await xrf.api("GET", `/api/projects/${pid}/builds/${bid}`);
    if (P.current !== pid || P.shownBuild !== bid) return;  // answers for a project no longer shown
    q("proj-build-title").textContent = `Build #${b.id}: ${b.status}` + (b.result ? ` — ${b.result}` : "");
    q("proj-build-title").className = "st-" + b.status;
    if (b.status === "ok" || b.status === "failed") {
      const res = await fetch(`/api/projects/${pid}/builds/${bid}/log`);
      P.logs[bid] = (await res.text()).split("\n");
      if (P.current !== pid || P.shownBuild !== bid) return;
    }
    q("proj-log").textContent = (P.logs[bid] || []).join("\n");
    q("proj-log").scrollTop = 1e9;
    renderDiagnostics((b.details && b.details.diagnostics) || []);
    if (b.details && b.details.twenty_sim_tokens) renderTwentySim(b.details.twenty_sim_tokens);
  }

  function renderDiagnostics(diags) {
    const ul = q("proj-diags");
    ul.textContent = "";
    for (const d of diags.filter((x) => x.kind === "error" || x.kind === "warning").slice(0, 50)) {
      const loc = d.file ? `${d.file}:${d.line}${d.col ? ":" + d.col : ""}` : "";
      const li = el("li", { class: "diag " + d.kind + (d.in_project ? " clickable" : ""), "data-file": d.file, "data-line": d.line || "" },
        el("span", { class: "loc", text: loc }), el("span", { text: ` ${d.kind}: ${d.message}` }));
      if (d.in_project) li.addEventListener("click", () => showSource(d.file, d.line));
      ul.append(li);
    }
  }

  async function showSource(path, line) {
    const box = q("proj-source");
    const pid = P.current;
    try {
      const ex = await xrf.api("GET", `/api/projects/${pid}/source?path=${encodeURIComponent(path)}` + (line ? `&line=${line}&context=6` : ""));
      if (P.current !== pid) return;
      box.textContent = "";
      box.append(el("div", { class: "src-title", text: ex.path }));
      const pre = el("pre", { class: "src" });
      ex.lines.forEach((t, i) => {
        const n = ex.first + i;
        pre.append(el("div", { class: "srcline" + (n === ex.highlight ? " hl" : ""), "data-line": n },
          el("span", { class: "ln", text: String(n).padStart(4) + "  " }), el("span", { text: t })));
      });
      box.append(pre);
      box.classList.remove("hidden");
    } catch (e) { box.textContent = fmtErr(e); box.classList.remove("hidden"); }
  }

  // The answer to a click in the project's header, beside its buttons.
  function actionMsg(text, bad) {
    const s = q("proj-action-msg");
    s.textContent = text;
    s.className = "action-msg" + (bad ? " bad" : "");
  }

  async function build() {
    if (P.current == null) return;
    try {
      const b = await xrf.api("POST", `/api/projects/${P.current}/builds`);
      P.logs[b.id] = P.logs[b.id] || [];
      actionMsg(b.reused ? `Unchanged source: build #${b.id} is reused` : `Build #${b.id} queued`);
      await refreshBuilds();
      showBuild(b.id);
    } catch (e) { actionMsg(fmtErr(e), true); }
  }

  // A run's answer goes in its build's row, beside the Run button clicked (kept across the row's
  // re-renders until the next click).
  async function runBuild(bid) {
    const say = (text, bad) => {
      P.rowMsg = { [bid]: { text, bad } };
      renderBuilds((P.detail && P.detail.builds) || []);
    };
    say(`starting on the bench…`);
    try {
      const r = await xrf.api("POST", `/api/projects/${P.current}/builds/${bid}/run`, {});
      say(`run #${r.run.id} started`);
      location.hash = "#bench";
    } catch (e) { say(fmtErr(e), true); }
  }

  // The Editor page on this project (its current version): the editor opens the project it is
  // asked for when it is next shown (frontend/pages/editor.js, E.want).
  function openInEditor(pid) {
    const E = window.xrfEditor;
    if (E) E.want = pid;
    location.hash = "#editor";
  }

  async function fromTemplate() {
    try {
      const p = await xrf.api("POST", "/api/projects/from-template", { template: q("proj-template").value, name: q("proj-new-name").value });
      status(`Project ${p.name} created from the ${q("proj-template").value} template`);
      await loadProjects();
      await select(p.id);
    } catch (e) { status(fmtErr(e), true); }
  }

  function onBuildMessage(m) {
    if (m.build_id == null) return;
    if (m.line != null) {
      (P.logs[m.build_id] = P.logs[m.build_id] || []).push(m.line);
      if (m.build_id === P.shownBuild) {
        const pre = q("proj-log");
        pre.append(m.line + "\n");
        pre.scrollTop = 1e9;
      }
    }
    if (m.status && m.project_id === P.current) {
      if (m.status === "ok" || m.status === "failed") actionMsg(`Build #${m.build_id}: ${m.status}` + (m.result ? ` — ${m.result}` : ""), m.status === "failed");
      else if (m.status === "building") actionMsg(`Build #${m.build_id} building…`);
      refreshBuilds().then(() => { if (m.build_id === P.shownBuild && (m.status === "ok" || m.status === "failed")) showBuild(m.build_id); }).catch(() => {});
    }
  }

  function dropZone(zone, getPid) {
    zone.addEventListener("dragover", (e) => { e.preventDefault(); zone.classList.add("over"); });
    zone.addEventListener("dragleave", () => zone.classList.remove("over"));
    zone.addEventListener("drop", (e) => {
      e.preventDefault();
      zone.classList.remove("over");
      const files = e.dataTransfer && e.dataTransfer.files;
      if (!files || files.length !== 1) { status("Drop one .zip or .tar.gz file (a folder: use `xrf upload FOLDER`)", true); return; }
      uploadFile(files[0], getPid()).catch(() => {});
    });
  }

  function init(root) {
    root.classList.add("projects-page");
    root.innerHTML = `
      <div id="proj-status" class="proj-status" role="status"></div>
      <section class="panel" id="proj-side">
        <h2>Projects</h2>
        <div id="proj-drop" class="dropzone" tabindex="0">
          Drop a project (<b>.zip</b> / <b>.tar.gz</b>) here<br><span class="muted small">or</span>
          <label class="filebtn">choose a file<input type="file" id="proj-file" hidden></label>
          <div id="proj-rules" class="proj-rules muted small"></div>
        </div>
        <div class="row newrow">
          <select id="proj-template"><option value="base">base template</option><option value="20sim">20-sim template</option></select>
          <input id="proj-new-name" placeholder="name" maxlength="64">
          <button id="proj-new">New project</button>
        </div>
        <div class="muted small">Edit locally: <a id="proj-tpl-download" href="/api/project-templates/base/download">download the template (zip)</a></div>
        <ul id="proj-list" class="proj-list"></ul>
      </section>
      <section class="panel hidden" id="proj-detail">
        <h2><span id="proj-name"></span>
          <button id="proj-build">Build</button>
          <button id="proj-edit" class="secondary small">Open in editor</button>
          <a id="proj-download" class="button secondary small" href="#">Download (zip)</a>
          <label class="filebtn secondary small">new version…<input type="file" id="proj-update-file" hidden></label>
          <button id="proj-delete" class="secondary small">Delete</button>
          <span id="proj-action-msg" class="action-msg" role="status"></span>
        </h2>
        <div id="proj-package" class="proj-package hidden"></div>
        <div class="proj-cols">
          <div><h3>20-sim</h3><div id="proj-20sim"></div></div>
          <div><h3>Messages</h3><div id="proj-msgs"></div></div>
        </div>
        <h3>Builds</h3>
        <table class="runs"><thead><tr><th>#</th><th>status</th><th>result</th><th>time</th><th>source</th><th></th></tr></thead><tbody id="proj-builds"></tbody></table>
        <h3 id="proj-build-title">Build output</h3>
        <ul id="proj-diags" class="diags"></ul>
        <div id="proj-source" class="source hidden"></div>
        <pre id="proj-log" class="console buildlog"></pre>
      </section>`;
    q("proj-file").addEventListener("change", (e) => { if (e.target.files[0]) uploadFile(e.target.files[0], null).catch(() => {}); e.target.value = ""; });
    q("proj-update-file").addEventListener("change", (e) => { if (e.target.files[0]) uploadFile(e.target.files[0], P.current).catch(() => {}); e.target.value = ""; });
    q("proj-new").addEventListener("click", fromTemplate);
    q("proj-template").addEventListener("change", () => {
      const v = q("proj-template").value;
      q("proj-tpl-download").href = `/api/project-templates/${v}/download`;
      q("proj-tpl-download").parentElement.classList.toggle("hidden", v.startsWith("assignment:")); // no zip of those
    });
    // assignments the lab room published (docs/educators/room.md): a fresh copy from here
    xrf.api("GET", "/api/project-templates").then((ts) => {
      for (const t of ts) if (t.assignment) q("proj-template").append(el("option", { value: t.name, text: "assignment: " + t.title }));
    }).catch(() => {});
    q("proj-build").addEventListener("click", build);
    q("proj-edit").addEventListener("click", () => openInEditor(P.current));
    loadRules().catch((e) => status(fmtErr(e), true));
    q("proj-delete").addEventListener("click", async () => {
      if (!confirm("Delete this project and its builds?")) return;
      try { await xrf.api("DELETE", `/api/projects/${P.current}`); } catch (e) { actionMsg(fmtErr(e), true); return; }
      P.current = null; q("proj-detail").classList.add("hidden"); loadProjects();
    });
    dropZone(q("proj-drop"), () => null);
    dropZone(q("proj-detail"), () => P.current);
    xrf.on("build", onBuildMessage);
  }

  function show() { loadProjects().then(() => { if (P.current != null) select(P.current); }).catch((e) => status(fmtErr(e), true)); }

  P.upload = uploadFile; P.select = select; P.build = build; P.showSource = showSource;
  xrf.addPage({ id: "projects", title: "Projects", order: 10, perm: "projects", init, show });
})();
