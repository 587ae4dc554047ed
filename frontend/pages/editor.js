// Editor page: a project's files in CodeMirror (Debian's libjs-codemirror, served by the appliance:
// nothing is fetched from outside), save = the project's next source version, built at once, the
// compiler's errors as markers at their lines, "Build & run" that runs exactly the build of the
// saved source, and the version history with diffs (against the template too).
// API: server/http/editor.py. Docs: docs/students/editor.md.
"use strict";
(function () {
  const CM_BASE = "/static/vendor/codemirror/";
  // Loaded when the page is first shown, not with the dashboard (400 KB the bench page never needs).
  const CM_FILES = ["lib/codemirror.js", "mode/clike/clike.js", "mode/cmake/cmake.js", "mode/python/python.js",
    "mode/xml/xml.js", "mode/markdown/markdown.js", "addon/edit/matchbrackets.js", "addon/selection/active-line.js"];
  const E = {
    pid: null, project: null, files: [], version: null, path: null,
    want: null,         // a project another page asked to open (Projects page's "Open in editor")
    buffers: {},        // path -> {doc, base, clean (changeGeneration at the last load/save)}
    diags: [],          // the shown build's diagnostics
    build: null,        // the build of the last save: {id, status, result}
    cm: null, cmFailed: false, busy: false,
  };
  window.xrfEditor = E;  // test hook
  const q = (id) => document.getElementById(id);
  const el = (tag, attrs, ...kids) => {
    const e = document.createElement(tag);
    for (const [k, v] of Object.entries(attrs || {})) {
      if (k === "class") e.className = v; else if (k === "text") e.textContent = v;
      else if (k.startsWith("on")) e.addEventListener(k.slice(2), v); else e.setAttribute(k, v);
    }
    for (const k of kids) if (k != null) e.append(k);
    return e;
  };
  const sleep = (ms) => new Promise((r) => setTimeout(r, ms));
  const enc = (path) => path.split("/").map(encodeURIComponent).join("/");
  const errText = (e) => { try { const d = JSON.parse(e.message); return d.error || e.message; } catch (_) { return e.message; } };

  function status(text, kind) {
    const s = q("ed-status");
    s.textContent = text;
    s.className = "ed-status" + (kind ? " " + kind : "");
  }

  // ---- CodeMirror --------------------------------------------------------------------------------

  function loadScript(src) {
    return new Promise((resolve, reject) => {
      const s = document.createElement("script");
      s.src = src; s.onload = resolve; s.onerror = () => reject(new Error("could not load " + src));
      document.head.append(s);
    });
  }

  async function loadCodeMirror() {
    if (window.CodeMirror) return;
    // Its stylesheet before the editor is made: CodeMirror measures its lines and gutter then.
    const style = new Promise((resolve, reject) => {
      const l = el("link", { rel: "stylesheet", href: CM_BASE + "lib/codemirror.css" });
      l.onload = resolve; l.onerror = () => reject(new Error("could not load " + l.href));
      document.head.append(l);
    });
    await loadScript(CM_BASE + CM_FILES[0]);  // the modes and addons register with it
    await Promise.all([style, ...CM_FILES.slice(1).map((f) => loadScript(CM_BASE + f))]);
  }

  function modeFor(path) {
    const name = path.split("/").pop();
    if (/\.(c|h)$/.test(name)) return "text/x-csrc";
    if (/\.(cpp|cc|cxx|hpp|hh|hxx|ipp|tpp)$/.test(name)) return "text/x-c++src";
    if (name === "CMakeLists.txt" || name.endsWith(".cmake")) return "text/x-cmake";
    if (name.endsWith(".py")) return "text/x-python";
    if (/\.(xml|urdf|launch)$/.test(name)) return "application/xml";
    if (name.endsWith(".md")) return "text/x-markdown";
    return "text/plain";
  }

  function makeEditor() {
    const host = q("ed-cm");
    if (!window.CodeMirror) {
      // Without the package the page still edits (a plain text box), without highlighting or markers.
      E.cmFailed = true;
      const ta = el("textarea", { id: "ed-plain", class: "ed-plain", spellcheck: "false" });
      host.append(ta);
      return;
    }
    E.cm = window.CodeMirror(host, {
      lineNumbers: true, matchBrackets: true, styleActiveLine: true, indentUnit: 4, tabSize: 4,
      gutters: ["ed-diag-gutter", "CodeMirror-linenumbers"], value: "",
      extraKeys: { "Ctrl-S": () => save(), "Cmd-S": () => save() },
    });
    E.cm.on("change", () => updateDirty());
  }

  // ---- projects and files ------------------------------------------------------------------------

  async function loadProjects() {
    // An educator reviews every student's project (and its history against the template).
    const me = await xrf.meReady;
    const edu = xrf.may("educator");
    const list = await xrf.api("GET", "/api/projects" + (edu ? "?all=true" : ""));
    const sel = q("ed-project");
    sel.textContent = "";
    if (!list.length) sel.append(el("option", { value: "", text: "no projects: make one on the Projects page" }));
    for (const p of list) sel.append(el("option", { value: p.id, text: `${p.name} (#${p.id})` + (edu && p.owner !== me.username ? ` · ${p.owner}` : "") }));
    // E.want: the project another page asked for ("Open in editor" on the Projects page).
    const asked = E.want; E.want = null;
    const want = asked != null && list.some((p) => p.id === asked) ? asked
      : E.pid != null && list.some((p) => p.id === E.pid) ? E.pid : list.length ? list[0].id : null;
    if (want != null) { sel.value = String(want); if (want !== E.pid) await openProject(want); else await refreshFiles(); }
  }

  function anyDirty() { return Object.keys(E.buffers).some(isDirty); }

  async function openProject(pid) {
    if (pid === E.pid) return;
    if (anyDirty() && !confirm("You have unsaved changes in this project. Leave them?")) {
      q("ed-project").value = String(E.pid);
      return;
    }
    E.pid = pid; E.path = null; E.buffers = {}; E.diags = []; E.build = null;
    q("ed-diags").textContent = "";
    q("ed-diff-out").textContent = "";
    E.project = await xrf.api("GET", `/api/projects/${pid}`);
    // Panels of other modules that follow the open project (pages/grading.js: Check my project).
    document.dispatchEvent(new CustomEvent("xrf-editor-project", { detail: pid }));
    await refreshFiles();
    const pick = E.files.find((f) => f.editable && /^src\/.*\.(cpp|cc)$/.test(f.path) && !/main\.cpp$/.test(f.path))
      || E.files.find((f) => f.editable);
    if (pick) await openFile(pick.path);
    await loadVersions();
    // The newest build of the current version: its errors are shown as if just built.
    const v = E.versions && E.versions[0];
    if (v && v.build) await showBuild(v.build.id);
  }

  async function refreshFiles() {
    const r = await xrf.api("GET", `/api/projects/${E.pid}/files`);
    E.files = r.files; E.version = r.version;
    const ul = q("ed-files");
    ul.textContent = "";
    for (const f of r.files) {
      const li = el("li", { "data-path": f.path, class: (f.path === E.path ? "current " : "") + (f.editable ? "" : "muted"),
        title: f.editable ? `${f.size} bytes` : f.reason }, f.path);
      if (f.editable) li.addEventListener("click", () => openFile(f.path));
      ul.append(li);
    }
    q("ed-version").textContent = `version ${r.version}`;
    markFiles();
  }

  async function openFile(path, line) {
    if (!E.buffers[path]) {
      const f = await xrf.api("GET", `/api/projects/${E.pid}/files/${enc(path)}`);
      if (!f.editable) { status(`${path}: ${f.reason}; it cannot be edited here`, "bad"); return; }
      const b = { base: f.version, text: f.content, saved: f.content };
      if (E.cm) { b.doc = window.CodeMirror.Doc(f.content, modeFor(path)); b.clean = b.doc.changeGeneration(); }
      E.buffers[path] = b;
    }
    E.path = path;
    const b = E.buffers[path];
    if (E.cm) E.cm.swapDoc(b.doc); else { q("ed-plain").value = b.text; q("ed-plain").oninput = () => { b.text = q("ed-plain").value; updateDirty(); }; }
    q("ed-path").textContent = path;
    document.querySelectorAll("#ed-files li").forEach((li) => li.classList.toggle("current", li.dataset.path === path));
    applyMarkers();
    updateDirty();
    if (line && E.cm) {
      E.cm.setCursor({ line: line - 1, ch: 0 });
      E.cm.scrollIntoView({ line: line - 1, ch: 0 }, 120);
      E.cm.focus();
    }
  }

  function isDirty(path) {
    const b = E.buffers[path];
    if (!b) return false;
    return b.doc ? !b.doc.isClean(b.clean) : b.text !== b.saved;
  }

  function updateDirty() {
    q("ed-dirty").textContent = E.path && isDirty(E.path) ? "● unsaved" : "";
    document.querySelectorAll("#ed-files li").forEach((li) => li.classList.toggle("dirty", isDirty(li.dataset.path)));
  }

  function textOf(path) {
    const b = E.buffers[path];
    return b.doc ? b.doc.getValue() : b.text;
  }

  // ---- save = a version, built -------------------------------------------------------------------

  async function save(overwrite) {
    if (E.pid == null || !E.path || E.busy) return null;
    const path = E.path, b = E.buffers[path];
    const gen = b.doc ? b.doc.changeGeneration() : null;
    const text = textOf(path);
    E.busy = true;
    status(`Saving ${path}…`);
    try {
      const base = overwrite != null ? overwrite : b.base;
      const { data, res } = await xrfLib.send("PUT", `/api/projects/${E.pid}/files/${enc(path)}?base=${base}`, text,
        { "Content-Type": "text/plain; charset=utf-8" });
      if (res.status === 401) { xrf.toLogin(); return null; }
      if (!res.ok) {
        // Nothing is lost: the text stays in the editor, unsaved.
        const d = data.detail;
        const msg = d && typeof d === "object" ? d.error : (d || res.statusText);
        status(msg, "bad");
        if (res.status === 409 && d && d.current_version) offerOverwrite(d.current_version);
        return null;
      }
      b.base = data.version.n;
      if (b.doc) b.clean = gen; else b.saved = text;
      updateDirty();
      E.build = data.build;
      status(data.new_version ? `Saved: version ${data.version.n}. Building #${data.build.id}…`
        : `No change: still version ${data.version.n}` + (data.build ? `, build #${data.build.id}` : ""));
      refreshFiles().catch(() => {});
      loadVersions().catch(() => {});
      clearMarkers();
      return await waitBuild(data.build.id);
    } catch (e) {
      status(errText(e), "bad");
      return null;
    } finally {
      E.busy = false;
    }
  }

  function offerOverwrite(current) {
    const s = q("ed-status");
    s.append(" ", el("button", { class: "small", id: "ed-overwrite", text: "save mine anyway",
      onclick: () => save(current) }));
  }

  async function waitBuild(bid) {
    for (;;) {
      const b = await xrf.api("GET", `/api/projects/${E.pid}/builds/${bid}`);
      if (b.status === "ok" || b.status === "failed") { await showBuild(bid, b); return b; }
      status(`Version ${E.buffers[E.path] ? E.buffers[E.path].base : ""}: build #${bid} ${b.status}` +
        (b.position > 0 ? ` (#${b.position} in the queue)` : "") + "…");
      await sleep(400);
    }
  }

  async function showBuild(bid, b) {
    b = b || await xrf.api("GET", `/api/projects/${E.pid}/builds/${bid}`);
    E.build = { id: b.id, status: b.status, result: b.result };
    E.diags = ((b.details && b.details.diagnostics) || []).filter((d) => d.kind === "error" || d.kind === "warning");
    if (b.status === "ok") status(`Build #${b.id} ok — ${b.result}` + (E.diags.length ? ` (${E.diags.length} warnings)` : ""), "ok");
    else if (b.status === "failed") status(`Build #${b.id} failed: ${b.result}`, "bad");
    renderDiags();
    applyMarkers();
    markFiles();
    q("ed-run").disabled = false;
    // The first error of the open file in view, its message under it included.
    const first = E.diags.find((d) => d.kind === "error" && d.in_project && d.file === E.path && d.line);
    if (first && E.cm) E.cm.scrollIntoView({ line: Math.min(first.line, E.cm.lineCount()) - 1, ch: 0 }, 150);
    if (E.pid != null) loadVersions().catch(() => {});  // the history shows how its builds ended
  }

  // ---- diagnostics: a list, markers in the gutter, the message under its line ----------------------

  function renderDiags() {
    const ul = q("ed-diags");
    ul.textContent = "";
    for (const d of E.diags.slice(0, 100)) {
      const loc = d.file ? `${d.file}:${d.line}${d.col ? ":" + d.col : ""}` : "";
      const li = el("li", { class: "diag " + d.kind + (d.in_project ? " clickable" : "") }, el("span", { class: "loc", text: loc }),
        el("span", { text: ` ${d.kind}: ${d.message}` }));
      if (d.in_project && d.file && d.line) li.addEventListener("click", () => openFile(d.file, d.line));
      ul.append(li);
    }
  }

  function clearMarkers() {
    E.diags = [];
    renderDiags();
    applyMarkers();
    markFiles();
  }

  function applyMarkers() {
    if (!E.cm) return;
    const cm = E.cm;
    cm.clearGutter("ed-diag-gutter");
    (E.widgets || []).forEach((w) => w.clear());
    (E.lineClasses || []).forEach((h) => cm.removeLineClass(h, "background", "ed-line-error"));
    E.widgets = []; E.lineClasses = [];
    const here = E.diags.filter((d) => d.in_project && d.file === E.path && d.line);
    const seen = new Set();
    for (const d of here) {
      const line = Math.min(d.line, cm.lineCount()) - 1;
      const marker = el("div", { class: "ed-marker " + d.kind, title: d.message, "data-line": d.line, text: d.kind === "error" ? "✖" : "▲" });
      if (!seen.has(line)) { cm.setGutterMarker(line, "ed-diag-gutter", marker); seen.add(line); }
      if (d.kind === "error") E.lineClasses.push(cm.addLineClass(line, "background", "ed-line-error"));
      const w = el("div", { class: "ed-inline " + d.kind, "data-line": d.line, text: `${d.kind}: ${d.message}` });
      E.widgets.push(cm.addLineWidget(line, w, { coverGutter: false, noHScroll: true }));
    }
  }

  function markFiles() {
    const bad = new Set(E.diags.filter((d) => d.kind === "error" && d.in_project).map((d) => d.file));
    document.querySelectorAll("#ed-files li").forEach((li) => li.classList.toggle("has-error", bad.has(li.dataset.path)));
  }

  // ---- build and run: exactly the build of the saved source ----------------------------------------

  async function waitState(names, ms) {
    const t0 = Date.now();
    while (Date.now() - t0 < ms) {
      if (xrf.state && xrf.state.active && names.includes(xrf.state.name)) return xrf.state.name;
      await sleep(100);
    }
    throw new Error(`the controller did not reach ${names.join(" or ")} (state ${xrf.state ? xrf.state.name : "?"})`);
  }

  async function buildAndRun() {
    if (E.pid == null) return;
    q("ed-run").disabled = true;
    try {
      let b = null;
      if (anyDirty()) {
        // Every unsaved file first (the one shown last): the run is of what the editor shows.
        const shown = E.path;
        for (const p of Object.keys(E.buffers).filter(isDirty)) {
          if (p !== shown) { await openFile(p); if (!(await save())) return; }
        }
        await openFile(shown);
        if (isDirty(shown)) b = await save(); else b = E.build;
        if (!b) return;
      } else if (E.build && E.build.id) {
        b = await waitBuild(E.build.id);
      } else {
        const r = await xrf.api("POST", `/api/projects/${E.pid}/builds`);
        b = await waitBuild(r.id);
      }
      if (b.status !== "ok") { status(`Build #${b.id} failed: ${b.result} — fix it and try again`, "bad"); return; }
      status(`Starting build #${b.id}…`);
      const r = await xrf.api("POST", `/api/projects/${E.pid}/builds/${b.id}/run`, {});
      E.run = r.run;
      status(`Run #${r.run.id} of build #${b.id} started`, "ok");
      if (!q("ed-torun").checked) return;
      await waitState(["IDLE"], 20000);
      xrf.send({ type: "command", cmd: "initialise" });
      await waitState(["INITIALISED", "RUN"], 10000);
      if (xrf.state.name !== "RUN") xrf.send({ type: "command", cmd: "start" });
      await waitState(["RUN"], 10000);
      status(`Run #${r.run.id} of build #${b.id}: RUN (Esc stops it)`, "ok");
    } catch (e) {
      status("Could not run: " + errText(e), "bad");
    } finally {
      q("ed-run").disabled = false;
    }
  }

  // ---- files: new, delete --------------------------------------------------------------------------

  async function newFile() {
    const path = q("ed-newpath").value.trim();
    if (!path) return;
    if (E.files.some((f) => f.path === path)) { await openFile(path); return; }
    const { data, res } = await xrfLib.send("PUT", `/api/projects/${E.pid}/files/${enc(path)}?build=false`, "",
      { "Content-Type": "text/plain; charset=utf-8" });
    if (!res.ok) { status(typeof data.detail === "string" ? data.detail : res.statusText, "bad"); return; }
    q("ed-newpath").value = "";
    status(`${path} added: version ${data.version.n}`);
    await refreshFiles();
    await loadVersions();
    await openFile(path);
  }

  async function deleteFile() {
    if (!E.path || !confirm(`Remove ${E.path} from the project? (Earlier versions keep it.)`)) return;
    try {
      const r = await xrf.api("DELETE", `/api/projects/${E.pid}/files/${enc(E.path)}?base=${E.buffers[E.path].base}`);
      status(`${E.path} removed: version ${r.version.n}`);
      delete E.buffers[E.path];
      E.path = null;
      if (E.cm) E.cm.swapDoc(window.CodeMirror.Doc(""));
      q("ed-path").textContent = "";
      await refreshFiles();
      await loadVersions();
    } catch (e) { status(errText(e), "bad"); }
  }

  // ---- history and diffs ---------------------------------------------------------------------------

  function templateOf() {
    const o = E.project && E.project.origin || "";
    return o.startsWith("template:") ? o : "template:base";
  }

  async function loadVersions() {
    E.versions = await xrf.api("GET", `/api/projects/${E.pid}/versions`);
    const ul = q("ed-versions");
    ul.textContent = "";
    for (const v of E.versions) {
      const when = new Date(v.created * 1000).toLocaleTimeString();
      const build = v.build ? ` · build #${v.build.id} ${v.build.status}` : "";
      ul.append(el("li", { "data-n": v.n, title: `source ${v.source_hash}`, onclick: () => diff(String(v.n - 1 || templateOf()), String(v.n)) },
        el("b", { text: `v${v.n}` }), el("span", { class: "muted small", text: ` ${when} · ${v.author}` }),
        el("div", { class: "small", text: v.origin + build })));
    }
    for (const id of ["ed-diff-a", "ed-diff-b"]) {
      const sel = q(id), keep = sel.value;
      sel.textContent = "";
      for (const v of E.versions) sel.append(el("option", { value: String(v.n), text: `v${v.n} (${v.origin})` }));
      for (const t of ["template:base", "template:20sim"]) sel.append(el("option", { value: t, text: t.replace(":", " ") }));
      if (keep && [...sel.options].some((o) => o.value === keep)) sel.value = keep;
      else sel.value = id === "ed-diff-a" ? String(E.versions.length > 1 ? E.versions[1].n : templateOf()) : String(E.versions[0].n);
    }
  }

  async function diff(a, b) {
    q("ed-diff-a").value = a; q("ed-diff-b").value = b;
    const out = q("ed-diff-out");
    try {
      const d = await xrf.api("GET", `/api/projects/${E.pid}/diff?a=${encodeURIComponent(a)}&b=${encodeURIComponent(b)}`);
      out.textContent = "";
      const n = d.files.length;  // "1 file changed", "2 files changed", "0 files changed"
      out.append(el("div", { class: "ed-diff-sum", text: `${d.a} → ${d.b}: ${n} file${n === 1 ? "" : "s"} changed, +${d.added} −${d.removed}` }));
      for (const f of d.files) {
        const box = el("div", { class: "ed-diff-file", "data-path": f.path },
          el("div", { class: "ed-diff-head", text: `${f.path} — ${f.status}` + (f.diff != null ? ` (+${f.added} −${f.removed})` : " (binary or large: not shown)") }));
        if (f.diff) {
          const pre = el("pre", { class: "ed-diff" });
          for (const line of f.diff.split("\n")) {
            const cls = line.startsWith("+++") || line.startsWith("---") ? "h" : line[0] === "+" ? "add" : line[0] === "-" ? "del" : line.startsWith("@@") ? "hunk" : "";
            pre.append(el("div", { class: cls, text: line }));
          }
          box.append(pre);
        }
        out.append(box);
      }
    } catch (e) { out.textContent = errText(e); }
  }

  // ---- page ----------------------------------------------------------------------------------------

  function init(root) {
    root.classList.add("editor-page");
    root.innerHTML = `
      <section class="panel" id="ed-side">
        <h2>Edit</h2>
        <select id="ed-project" aria-label="project"></select>
        <div class="muted small" id="ed-version"></div>
        <ul id="ed-files" class="ed-files"></ul>
        <div class="row ed-newrow"><input id="ed-newpath" placeholder="src/new_file.cpp" maxlength="300"><button id="ed-new" class="secondary small">New file</button></div>
        <h3>History</h3>
        <ul id="ed-versions" class="ed-versions"></ul>
      </section>
      <section class="panel" id="ed-main">
        <h2><span id="ed-path" class="mono"></span> <span id="ed-dirty" class="ed-dirty"></span>
          <span class="spacer"></span>
          <button id="ed-save" title="save as a new version and build it (Ctrl-S)">Save <kbd>Ctrl-S</kbd></button>
          <button id="ed-run" title="save, build, and run exactly that build on the bench">Build &amp; run</button>
          <label class="check" title="after starting: initialise and start (the controller drives the robot)"><input type="checkbox" id="ed-torun" checked> to RUN</label>
          <button id="ed-delete" class="secondary small">Remove file</button>
        </h2>
        <div id="ed-status" class="ed-status" role="status"></div>
        <div id="ed-cm" class="ed-cm"></div>
        <ul id="ed-diags" class="diags"></ul>
        <h3>Compare versions</h3>
        <div class="row">
          <select id="ed-diff-a" aria-label="from"></select> → <select id="ed-diff-b" aria-label="to"></select>
          <button id="ed-diff" class="secondary small">Diff</button>
          <button id="ed-diff-template" class="secondary small" title="what was written on top of the template the project started from">Against the template</button>
        </div>
        <div id="ed-diff-out" class="ed-diff-out"></div>
      </section>`;
    q("ed-project").addEventListener("change", () => { const v = Number(q("ed-project").value); if (v) openProject(v).catch((e) => status(errText(e), "bad")); });
    q("ed-save").addEventListener("click", () => save());
    q("ed-run").addEventListener("click", buildAndRun);
    q("ed-new").addEventListener("click", () => newFile().catch((e) => status(errText(e), "bad")));
    q("ed-delete").addEventListener("click", deleteFile);
    q("ed-diff").addEventListener("click", () => diff(q("ed-diff-a").value, q("ed-diff-b").value));
    q("ed-diff-template").addEventListener("click", () => diff(templateOf(), String(E.versions[0].n)));
    // Ctrl-S anywhere on this page saves (not the browser's "save page").
    document.addEventListener("keydown", (ev) => {
      if ((ev.ctrlKey || ev.metaKey) && ev.key.toLowerCase() === "s" && !root.classList.contains("hidden")) {
        ev.preventDefault();
        if (!E.cm || !E.cm.hasFocus()) save();
      }
    });
    window.addEventListener("beforeunload", (ev) => { if (anyDirty()) { ev.preventDefault(); ev.returnValue = ""; } });
    E.ready = loadCodeMirror().catch((e) => status(e.message + ": the editor needs Debian's libjs-codemirror (./lab installs it); a plain text box instead", "bad"))
      .then(() => makeEditor());
  }

  async function show() {
    await E.ready;
    try { await loadProjects(); } catch (e) { status(errText(e), "bad"); }
    if (E.cm) E.cm.refresh();
  }

  E.open = async (pid, path, line) => { await E.ready; location.hash = "#editor"; await openProject(pid); if (path) await openFile(path, line); };
  E.save = save; E.buildAndRun = buildAndRun; E.openFile = openFile; E.diff = diff;
  xrf.addPage({ id: "editor", title: "Editor", order: 15, perm: "projects", init, show });
})();
