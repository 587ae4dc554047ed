// Self-check page (educators): is it the bench or the student's code? Runs the bench self-check
// (progress live from `selfcheck` WebSocket messages), shows the report, keeps past reports and
// edits bench profiles. API: appliance/xrflab/server/http/selfcheck.py.
"use strict";

(function () {
  const $ = (id) => document.getElementById(id);
  const esc = xrf.esc;  // frontend/lib.js
  const MARK = { pass: "✓", warn: "!", fail: "✗", skipped: "–" };
  const WORD = { pass: "passed", warn: "warning", fail: "FAILED", skipped: "skipped" };
  const when = (iso) => { const d = new Date(iso); return isNaN(d) ? (iso || "–") : d.toLocaleString(); };

  const HTML = `<div class="page-body selfcheck">
    <section class="panel">
      <h2>Bench self-check</h2>
      <p class="muted small">Drives every part of the bench for a moment — ico board, SPI link, each motor and encoder,
        digital outputs and inputs — and says step by step whether it works. RELbot on its stand (wheels free), Jiwy turned
        to the middle of both axes, hands off the robot. Each motor gets two short pulses (at most 20 % power, 200 ms).</p>
      <div class="row">
        <span class="badge-inline" id="sc-bench">bench …</span>
        <label for="sc-profile">Bench profile</label>
        <select id="sc-profile"></select>
        <button id="sc-run" type="button">Run check</button>
        <button id="sc-abort" type="button" class="danger hidden">Abort</button>
      </div>
      <details id="sc-practise" class="hidden small"><summary>Practise: inject faults into the simulated board</summary>
        <div class="row"><input id="sc-faults" placeholder="e.g. dead_encoder=2 or reversed_motor=1" spellcheck="false" size="40">
          <span class="muted">simulated bench only; see docs/educators/selfcheck.md</span></div>
      </details>
      <div id="sc-msg" class="sc-msg hidden" role="status"></div>
    </section>

    <section class="panel" id="sc-progress-panel">
      <h2>Progress <span class="muted small" id="sc-progress-head">no check running</span></h2>
      <progress id="sc-bar" max="1" value="0" class="hidden"></progress>
      <div class="muted small" id="sc-progress"></div>
      <ol id="sc-steps" class="sc-steps"></ol>
    </section>

    <section class="panel" id="sc-report-panel">
      <h2>Report <span id="sc-verdict" class="verdict hidden"></span>
        <span class="spacer"></span>
        <span id="sc-export" class="hidden small">export:
          <a id="sc-export-json" download>JSON</a> · <a id="sc-export-md" download>Markdown</a></span></h2>
      <div id="sc-report-meta" class="muted small">Run a check, or open a past report below.</div>
      <table class="sc-table"><thead><tr><th></th><th>step</th><th>result</th><th>what to do</th></tr></thead>
        <tbody id="sc-report-steps"></tbody></table>
    </section>

    <section class="panel">
      <h2>Past reports <button id="sc-history-refresh" type="button" class="secondary small">refresh</button></h2>
      <table class="sc-table"><thead><tr><th>date</th><th>bench</th><th>result</th><th>steps</th><th>transport</th><th>export</th></tr></thead>
        <tbody id="sc-history"></tbody></table>
    </section>

    <section class="panel">
      <h2>Bench profiles <span class="muted small">what is wired where</span></h2>
      <div class="row">
        <label for="pf-name">Profile</label>
        <select id="pf-name"></select>
        <span id="pf-source" class="muted small"></span>
        <span class="spacer"></span>
        <button id="pf-save" type="button">Save</button>
        <button id="pf-reset" type="button" class="secondary">Reset to default</button>
      </div>
      <textarea id="pf-text" class="pf-text" spellcheck="false" aria-label="bench profile JSON"></textarea>
      <div id="pf-result" class="small" role="status"></div>
      <ul id="pf-errors" class="pf-errors"></ul>
    </section>
  </div>`;

  const st = { bench: null, profiles: [], running: null, steps: {}, shown: null };

  // ---- running a check --------------------------------------------------------------------------

  function message(html, kind) {
    const box = $("sc-msg");
    box.className = "sc-msg " + (kind || "");
    box.innerHTML = html;
    box.classList.toggle("hidden", !html);
  }

  function setRunning(on) {
    $("sc-run").disabled = on;
    $("sc-abort").classList.toggle("hidden", !on);
    $("sc-abort").disabled = false;
    $("sc-bar").classList.toggle("hidden", !on);
  }

  async function start(stopRun) {
    const body = { profile: $("sc-profile").value, stop_run: !!stopRun };
    const faults = $("sc-faults").value.trim();
    if (faults && st.bench && st.bench.mode === "sim") body.faults = faults;
    message("");
    $("sc-run").disabled = true;
    try {
      const r = await xrf.api("POST", "/api/selfcheck", body);
      beginView(r.id, r);
    } catch (e) {
      $("sc-run").disabled = false;
      if (/stop the run first/.test(e.message)) {
        message(`<b>${esc(e.message)}</b> — the self-check never runs over a student's loop.
          <button type="button" id="sc-stop-and-run" class="danger">Stop the run and check</button>`, "warn");
        $("sc-stop-and-run").addEventListener("click", () => start(true));
      } else {
        message(esc(e.message), "bad");
      }
    }
  }

  async function abort() {
    $("sc-abort").disabled = true;
    $("sc-progress").textContent = "aborting: the outputs are being switched off…";
    try { await xrf.api("POST", "/api/selfcheck/abort"); } catch (e) { message(esc(e.message), "bad"); }
  }

  function beginView(id, info) {
    if (st.running === id) return;
    st.running = id;
    st.steps = {};
    $("sc-steps").innerHTML = "";
    $("sc-progress-head").textContent = `check ${id}: ${info.profile || ""} · ${info.transport || ""}` +
      (info.sim ? ` (simulated ${info.sim}${info.faults ? ", faults " + info.faults : ""})` : "");
    $("sc-progress").textContent = "starting…";
    $("sc-bar").value = 0;
    setRunning(true);
    for (const s of info.steps || []) addStep(s);
    if (info.progress) progress(info.progress);
  }

  function addStep(s) {
    let li = st.steps[s.id];
    if (!li) {
      li = document.createElement("li");
      li.dataset.step = s.id;
      st.steps[s.id] = li;
      $("sc-steps").append(li);
    }
    li.dataset.status = s.status;
    li.className = "st-" + s.status;
    li.innerHTML = `<span class="mark">${MARK[s.status] || "?"}</span> <code>${esc(s.id)}</code> ${esc(s.title)}
      <div class="small">${esc(s.message)}</div>${s.action && s.status !== "pass" ? `<div class="small action">→ ${esc(s.action)}</div>` : ""}`;
  }

  function progress(m) {
    $("sc-progress").textContent = m.text || m.step || "";
    if (typeof m.fraction === "number") $("sc-bar").value = m.fraction;
  }

  function onMessage(m) {
    if (!$("sc-steps")) return;  // the page has not been opened yet: show() loads the state
    if (m.event === "begin") { beginView(m.check, m); return; }
    if (st.running !== null && m.check !== st.running) return;
    if (st.running === null && m.event !== "report" && m.event !== "error") { beginView(m.check, m); }
    switch (m.event) {
      case "start": $("sc-progress").textContent = `checker started (${m.transport || ""})`; break;
      case "progress": progress(m); break;
      case "step": addStep(m); break;
      case "end":
        $("sc-progress").textContent = `done: ${m.verdict}` + (m.outputs_zeroed ? " · outputs zeroed" : " · outputs NOT confirmed zero");
        $("sc-bar").value = 1;
        break;
      case "error":
        st.running = null; setRunning(false);
        message(esc(m.message), "bad");
        $("sc-progress").textContent = "could not run";
        break;
      case "report":
        st.running = null; setRunning(false);
        if (m.report) showReport(m.name, m.report);
        if (m.save_error) message("the report could not be saved: " + esc(m.save_error), "bad");
        loadHistory().catch(() => {});
        break;
    }
  }

  // ---- reports ----------------------------------------------------------------------------------

  function exportUrl(name, fmt) { return `/api/selfcheck/reports/${encodeURIComponent(name)}/export?fmt=${fmt}`; }

  function showReport(name, r) {
    st.shown = name;
    const v = $("sc-verdict");
    v.textContent = r.verdict.toUpperCase();
    v.className = "verdict v-" + r.verdict;
    v.dataset.verdict = r.verdict;
    const c = r.counts || {};
    $("sc-report-meta").innerHTML = `<b>${esc(r.bench)}</b> bench · ${esc(when(r.started))} · ${esc(r.transport)}` +
      (r.sim ? ` (simulated ${esc(r.sim)})` : "") + (r.faults ? ` · injected faults <code>${esc(r.faults)}</code>` : "") +
      ` · ${c.pass || 0} passed, ${c.warn || 0} warnings, ${c.fail || 0} failed, ${c.skipped || 0} skipped · ` +
      `<span id="sc-zeroed" data-zeroed="${r.outputs_zeroed ? "yes" : "no"}" class="${r.outputs_zeroed ? "ok" : "bad"}">` +
      `${r.outputs_zeroed ? "outputs zeroed" : "outputs NOT confirmed zero"}</span>` +
      (r.error ? `<div class="bad">${esc(r.error)}</div>` : "");
    const body = $("sc-report-steps");
    body.innerHTML = "";
    for (const s of r.steps || []) {
      const tr = document.createElement("tr");
      tr.dataset.step = s.id;
      tr.dataset.status = s.status;
      tr.className = "st-" + s.status;
      tr.innerHTML = `<td class="mark" title="${WORD[s.status] || s.status}">${MARK[s.status] || "?"}</td>
        <td>${esc(s.title)}<div class="muted small"><code>${esc(s.id)}</code> · ${WORD[s.status] || esc(s.status)}</div></td>
        <td>${esc(s.message)}</td><td>${s.status === "pass" ? "" : esc(s.action)}</td>`;
      body.append(tr);
    }
    const ex = $("sc-export");
    ex.classList.toggle("hidden", !name);
    if (name) {
      $("sc-export-json").href = exportUrl(name, "json");
      $("sc-export-md").href = exportUrl(name, "markdown");
    }
  }

  async function openReport(name) {
    try { const r = await xrf.api("GET", `/api/selfcheck/reports/${encodeURIComponent(name)}`); showReport(name, r); }
    catch (e) { message(esc(e.message), "bad"); }
  }

  async function loadHistory() {
    const rows = await xrf.api("GET", "/api/selfcheck/reports");
    const body = $("sc-history");
    body.innerHTML = rows.length ? "" : `<tr><td colspan="6" class="muted">no reports yet</td></tr>`;
    for (const r of rows) {
      const tr = document.createElement("tr");
      tr.dataset.name = r.name;
      tr.className = "clickable";
      const c = r.counts;
      tr.innerHTML = `<td>${esc(when(r.started))}</td><td>${esc(r.bench)}</td>
        <td><span class="verdict v-${esc(r.verdict)}">${esc(r.verdict)}</span></td>
        <td class="small">${c.pass} ✓ ${c.warn ? c.warn + " ! " : ""}${c.fail ? c.fail + " ✗ " : ""}${c.skipped} –</td>
        <td class="small">${esc(r.transport)}${r.sim ? " · " + esc(r.sim) : ""}${r.faults ? " · " + esc(r.faults) : ""}</td>
        <td class="small"><a href="${exportUrl(r.name, "json")}" download>JSON</a> · <a href="${exportUrl(r.name, "markdown")}" download>MD</a></td>`;
      tr.addEventListener("click", (ev) => { if (ev.target.tagName !== "A") openReport(r.name); });
      body.append(tr);
    }
  }

  // ---- bench and profiles -----------------------------------------------------------------------

  async function loadStatus() {
    const s = await xrf.api("GET", "/api/selfcheck");
    st.bench = s.bench;
    $("sc-bench").textContent = s.bench.mode === "sim" ? `simulated bench · ${s.bench.sim}` : `real bench · ${s.bench.device}`;
    $("sc-practise").classList.toggle("hidden", s.bench.mode !== "sim");
    if (s.running) beginView(s.running.id, s.running);
    else if (st.running !== null) { st.running = null; setRunning(false); }
    if (s.run_active && !s.running) message(esc(s.run_active) + " — the check will offer to stop it.", "warn");
    if (!st.shown && s.last && s.last.report) showReport(s.last.name, s.last.report);
    warnMismatch();
  }

  function warnMismatch() {
    const p = st.profiles.find((x) => x.name === $("sc-profile").value);
    const note = $("sc-profile").title = (p && st.bench && st.bench.mode === "sim" && p.robot && p.robot !== st.bench.sim)
      ? `this profile is for ${p.robot}, the simulated bench is ${st.bench.sim}: motor steps will fail` : "";
    $("sc-profile").classList.toggle("mismatch", !!note);
  }

  async function loadProfiles() {
    st.profiles = await xrf.api("GET", "/api/profiles");
    for (const id of ["sc-profile", "pf-name"]) {
      const sel = $(id);
      const keep = sel.value;
      sel.innerHTML = st.profiles.map((p) => `<option value="${esc(p.name)}">${esc(p.name)} — ${esc(p.title)}${p.source === "edited" ? " (edited)" : ""}</option>`).join("");
      const pick = keep || (id === "sc-profile" && st.bench && st.bench.sim) || "relbot";
      if (st.profiles.some((p) => p.name === pick)) sel.value = pick;
    }
    warnMismatch();
  }

  // The editor's loads may overlap (the page shown and the profile picked at once): only the
  // latest fills the text, and none once someone typed after it was asked for (their edit would
  // be replaced by the saved text under their hands; CI: an edit saved as the original).
  let editorLoads = 0;
  let edits = 0;

  async function loadEditor() {
    const name = $("pf-name").value;
    if (!name) return;
    const load = ++editorLoads;
    const editsBefore = edits;
    $("pf-errors").innerHTML = ""; $("pf-result").textContent = "";
    const r = await xrf.api("GET", `/api/profiles/${encodeURIComponent(name)}`);
    if (load !== editorLoads || edits !== editsBefore) return;
    $("pf-text").value = JSON.stringify(r.profile, null, 2);
    showSource(r);
  }

  function showSource(r) {
    $("pf-source").textContent = r.source === "edited" ? "edited copy in the data folder" + (r.has_default ? " (overrides the default)" : "") : "the default (deploy/profiles)";
    $("pf-reset").disabled = r.source !== "edited" || !r.has_default;
  }

  async function saveProfile() {
    const name = $("pf-name").value;
    const errs = $("pf-errors");
    errs.innerHTML = ""; $("pf-result").textContent = "";
    let body;
    try { body = JSON.parse($("pf-text").value); }
    catch (e) { errs.innerHTML = `<li data-field=""><b>JSON</b>: ${esc(e.message)}</li>`; return; }
    // Encoded here: whatever JSON was typed (even a bare string) goes as JSON.
    const { data, res } = await xrfLib.send("PUT", `/api/profiles/${encodeURIComponent(name)}`, JSON.stringify(body),
      { "Content-Type": "application/json" });
    if (res.status === 422 && data.detail && data.detail.errors) {
      $("pf-result").innerHTML = `<span class="bad">Not saved: ${data.detail.errors.length} problem(s).</span>`;
      for (const e of data.detail.errors) {
        const li = document.createElement("li");
        li.dataset.field = e.field;
        li.innerHTML = (e.field ? `<b>${esc(e.field)}</b>: ` : "") + esc(e.message);
        errs.append(li);
      }
      return;
    }
    if (!res.ok) { $("pf-result").innerHTML = `<span class="bad">${esc(data.detail || res.statusText)}</span>`; return; }
    $("pf-result").innerHTML = `<span class="ok">Saved to ${esc(data.path)}.</span>`;
    showSource(data);
    loadProfiles().catch(() => {});
  }

  async function resetProfile() {
    const name = $("pf-name").value;
    if (!confirm(`Remove the edited copy of ${name}? The default applies again.`)) return;
    try {
      const r = await xrf.api("DELETE", `/api/profiles/${encodeURIComponent(name)}`);
      $("pf-text").value = JSON.stringify(r.profile, null, 2);
      $("pf-errors").innerHTML = "";
      $("pf-result").innerHTML = `<span class="ok">Back to the default.</span>`;
      showSource(r);
      loadProfiles().catch(() => {});
    } catch (e) { $("pf-result").innerHTML = `<span class="bad">${esc(e.message)}</span>`; }
  }

  xrf.meReady.then((me) => {
    if (!xrf.may("educator")) return;
    xrf.on("selfcheck", onMessage);
    xrf.addPage({
      id: "selfcheck", title: "Self-check", order: 70,
      init(el) {
        el.innerHTML = HTML;
        $("sc-run").addEventListener("click", () => start(false));
        $("sc-abort").addEventListener("click", abort);
        $("sc-profile").addEventListener("change", warnMismatch);
        $("sc-history-refresh").addEventListener("click", () => loadHistory().catch(() => {}));
        $("pf-name").addEventListener("change", () => loadEditor().catch((e) => { $("pf-result").textContent = e.message; }));
        $("pf-text").addEventListener("input", () => { edits += 1; });
        $("pf-save").addEventListener("click", () => saveProfile().catch((e) => { $("pf-result").textContent = e.message; }));
        $("pf-reset").addEventListener("click", resetProfile);
      },
      show() {
        loadStatus().then(loadProfiles).then(() => { if (!$("pf-text").value) return loadEditor(); })
          .catch((e) => message(esc(e.message), "bad"));
        loadHistory().catch(() => {});
      },
    });
  });
})();
