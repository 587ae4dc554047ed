// Parameters panel (issue 28, docs/students/tuning.md): the running controller's tunable
// parameters, on the Bench page (below the setpoints) and on the Watch page (beside the scope).
// Every watcher sees the values and each applied set (the `params` WebSocket message); the bench
// holder edits one or several and Apply sends them as one set (POST /api/params), which the loop
// takes at one cycle boundary: the panel shows that cycle. Revert sets the defaults.
"use strict";

(function () {
  const P = { msg: null, panels: [], status: "", bad: false };
  const fmt = (v) => (typeof v === "number" ? String(+v.toPrecision(6)) : "");

  function mount(container, where) {
    const section = document.createElement("section");
    section.className = "panel params-panel";
    section.innerHTML = `
      <h2>Parameters <span class="muted small params-origin"></span></h2>
      <div class="muted small params-note"></div>
      <table class="params-table"><thead><tr><th>name</th><th>value</th><th>new</th><th>unit</th><th>default</th><th>range</th></tr></thead>
        <tbody></tbody></table>
      <div class="row">
        <button class="params-apply">Apply</button>
        <button class="params-revert secondary">Revert to defaults</button>
        <button class="params-save secondary" title="a new version of the project holding these values (xrf_params.json); its next run starts with them">Save as the project's parameters</button>
        <span class="params-status small" role="status"></span>
      </div>`;
    if (where) container.insertBefore(section, where.nextSibling); else container.append(section);
    section.querySelector(".params-apply").addEventListener("click", () => apply(section, false));
    section.querySelector(".params-revert").addEventListener("click", () => apply(section, true));
    section.querySelector(".params-save").addEventListener("click", save);
    P.panels.push(section);
    render(section);
    return section;
  }

  function render(section) {
    const m = P.msg;
    const params = (m && m.params) || [];
    section.querySelector(".params-origin").textContent = m && m.origin === "20sim" ? "20-sim" : "";
    section.querySelector(".params-note").textContent = m ? m.note : "Start a run to tune its parameters.";
    const body = section.querySelector("tbody");
    const typed = {};  // keep what the user is typing across a re-render
    body.querySelectorAll("tr").forEach((tr) => {
      const i = tr.querySelector(".params-new");
      if (i && i.value !== "") typed[tr.dataset.name] = i.value;
    });
    body.innerHTML = params.map((p) => `
      <tr data-name="${xrf.esc(p.name)}">
        <td class="params-name">${xrf.esc(p.name)}</td>
        <td class="params-value">${fmt(p.value)}</td>
        <td><input class="params-new" type="text" inputmode="decimal" size="8" aria-label="new value of ${xrf.esc(p.name)}"></td>
        <td>${xrf.esc(p.unit)}</td>
        <td>${fmt(p.default)}</td>
        <td>${p.has_range ? `${fmt(p.min)} … ${fmt(p.max)}`
          : `<input class="params-min" size="6" value="${fmt(p.min)}" aria-label="min of ${xrf.esc(p.name)}"> … <input class="params-max" size="6" value="${fmt(p.max)}" aria-label="max of ${xrf.esc(p.name)}">`}</td>
      </tr>`).join("");
    body.querySelectorAll("tr").forEach((tr) => {
      if (typed[tr.dataset.name] !== undefined) tr.querySelector(".params-new").value = typed[tr.dataset.name];
    });
    const live = !!(m && m.run_id && params.length);
    const may = xrf.mayDrive ? xrf.mayDrive() : false;
    section.querySelectorAll("button, input").forEach((b) => { b.disabled = !live || !may; });
    section.querySelector(".params-save").disabled = !live || !may || projectOf() === null;
    const st = section.querySelector(".params-status");
    st.textContent = P.status;
    st.className = "params-status small" + (P.bad ? " bad" : "");
  }

  function renderAll() { P.panels.forEach(render); }

  // The uploaded project the current run was built from (the run's build is named
  // project-<pid>-build-<bid>), else null: a bundled example has no versions to save into.
  function projectOf() {
    const b = xrf.run && xrf.run.run && xrf.run.run.build;
    const m = /^project-(\d+)-build-\d+$/.exec(b || "");
    return m ? Number(m[1]) : null;
  }

  // Through the editor's API: a new version (shown in the editor and the version diff), no build.
  async function save() {
    const pid = projectOf();
    try {
      const f = await xrf.api("GET", "/api/params-file");
      const res = await fetch(`/api/projects/${pid}/files/${f.path}?build=false`, {
        method: "PUT", body: f.content, headers: { ...xrf.csrfHeaders(), "Content-Type": "text/plain" },
      });
      const data = await res.json().catch(() => ({}));
      if (!res.ok) throw new Error(data.detail || res.statusText);
      P.status = `saved as version ${data.version.n} of the project: its next run starts with these values`;
      P.bad = false;
    } catch (e) { P.status = "not saved: " + e.message; P.bad = true; }
    renderAll();
  }

  async function apply(section, revert) {
    const params = (P.msg && P.msg.params) || [];
    const values = {}, ranges = {};
    for (const tr of section.querySelectorAll("tbody tr")) {
      const p = params.find((q) => q.name === tr.dataset.name);
      if (!p) continue;
      const text = tr.querySelector(".params-new").value.trim();
      if (revert) values[p.name] = p.default;
      else if (text !== "") {
        const v = Number(text);
        values[p.name] = text === "" || Number.isNaN(v) ? text : v;  // the appliance says what is wrong with it
      }
      const lo = tr.querySelector(".params-min"), hi = tr.querySelector(".params-max");
      if (lo && hi && (Number(lo.value) !== p.min || Number(hi.value) !== p.max) && values[p.name] !== undefined) {
        ranges[p.name] = [Number(lo.value), Number(hi.value)];
      }
    }
    if (!Object.keys(values).length) { P.status = "Type a new value first."; P.bad = true; renderAll(); return; }
    P.status = "applying…"; P.bad = false; renderAll();
    try {
      const r = await xrf.api("POST", "/api/params", { values, ranges });
      section.querySelectorAll(".params-new").forEach((i) => { i.value = ""; });
      P.status = `applied at cycle ${r.cycle}: ` + r.changes.map((c) => `${c.name} ${fmt(c.old)} → ${fmt(c.new)}`).join(", ");
      P.bad = false;
      P.msg = { ...P.msg, params: r.params };
    } catch (e) {
      P.status = "not applied: " + e.message;
      P.bad = true;
    }
    renderAll();
  }

  // Markers on the Bench page's live plots (xrf.plots: uPlot instances made per run by app.js):
  // a dashed line at each applied set, at its cycle's time on the plots' axis (seconds since the
  // loop's first deadline = cycle / frequency), so the response before and after is visible.
  P.markers = [];
  P.markersRun = null;
  function drawMarkers(u) {
    const marks = xrf.paramMarkers();
    if (!marks.length) return;
    const ctx = u.ctx, { top, height } = u.bbox;
    ctx.save();
    ctx.strokeStyle = "#e36209";
    ctx.lineWidth = 1.5 * devicePixelRatio;
    ctx.setLineDash([4 * devicePixelRatio, 3 * devicePixelRatio]);
    for (const mk of marks) {
      const x = u.valToPos(mk.t, "x", true);
      if (!(x >= u.bbox.left && x <= u.bbox.left + u.bbox.width)) continue;
      ctx.beginPath(); ctx.moveTo(x, top); ctx.lineTo(x, top + height); ctx.stroke();
    }
    ctx.restore();
  }
  function hookPlots() {
    for (const p of Object.values(xrf.plots || {})) {
      const u = p && p.plot;
      if (!u || !u.hooks || u._paramsMarkers) continue;
      u.hooks.draw = (u.hooks.draw || []).concat(drawMarkers);
      u._paramsMarkers = true;
    }
  }
  // {cycle, t, changes} of each applied set of the current run, t in seconds on the plots' axis
  // (the run's frequency is known from its `run` message): for the scope (pages/watch.js), tests.
  xrf.paramMarkers = () => {
    const freq = xrf.run && xrf.run.run && xrf.run.run.cycle_freq;
    return freq ? P.markers.map((mk) => ({ ...mk, t: mk.cycle / freq })) : [];
  };

  // A page opened (or reloaded) during a run gets the sets applied before it from the run's
  // change table, so its plots and scope mark them too; later ones come as `applied` messages.
  function addMarker(cycle, changes) {
    if (P.markers.some((mk) => mk.cycle === cycle)) return;
    P.markers.push({ cycle, changes });
    P.markers.sort((a, b) => a.cycle - b.cycle);
  }
  async function seedMarkers(runId) {
    try {
      const r = await xrf.api("GET", `/api/logs/runs/${runId}/param-changes`);
      if (P.markersRun !== runId) return;
      for (const c of r.changes) {
        const mk = P.markers.find((x) => x.cycle === c.cycle);
        if (mk) { if (!mk.changes.some((d) => d.name === c.name)) mk.changes.push(c); } else addMarker(c.cycle, [c]);
      }
    } catch (e) { /* someone else's run or none: no markers to add */ }
  }

  xrf.handlers.params = (m) => {
    P.msg = m;
    if (m.run_id !== P.markersRun) {
      P.markers = []; P.markersRun = m.run_id;
      if (m.run_id) seedMarkers(m.run_id);
    }
    if (m.event === "applied") addMarker(m.cycle, m.changes);
    hookPlots();
    if (m.event === "applied" && m.changes) {
      P.status = `applied at cycle ${m.cycle} by ${m.who}: ` + m.changes.map((c) => `${c.name} ${fmt(c.old)} → ${fmt(c.new)}`).join(", ");
      P.bad = false;
    } else if (m.event === "table") P.status = "";
    renderAll();
  };
  xrf.on("lease", () => setTimeout(renderAll));
  // Who may edit is known only once /api/me has answered and the lease is known, in either order
  // and possibly after the last params/lease message (a slow /api/me left the inputs disabled:
  // the flaky browser test). lease.js calls xrf.permsChanged whenever the user or the lease
  // changes: the panel's flags follow it too.
  const permsChanged = xrf.permsChanged;
  xrf.permsChanged = function () {
    if (permsChanged) permsChanged.apply(this, arguments);
    renderAll();
  };
  xrf.meReady.then(() => setTimeout(renderAll));
  xrf.on("run", () => setTimeout(renderAll));  // "Save" needs the run's project (projectOf)
  // The Watch page mounts one beside its scope (pages/watch.js); the Bench page's is here.
  xrf.paramsPanel = (container) => mount(container, null);
  const bench = document.getElementById("page-bench");
  if (bench) mount(bench, document.getElementById("panel-setpoints"));
})();
