// Watch page: every signal of the running controller with its current value (OpenPLC's monitor):
// Xeno2Ros and Ros2Xeno fields, encoders, PWM, digital inputs and outputs; and a scope of any of
// them: a time window to choose, freeze, and a trigger on a signal crossing a level.
// Data: the dashboard's WebSocket (telemetry samples at the appliance's telemetry rate, each one as
// app.js plays it out, xrf.onSample; Ros2Xeno included:
// the values the loop has, read from its shared memory, whoever wrote them: this tab, another, the
// ROS 2 bridge, the CLI). Docs: docs/students/dashboard.md ("Watch").
"use strict";
(function () {
  const BUFFER_S = 120;        // history kept for the scope, whatever window is shown
  const TABLE_HZ = 10;         // the table is redrawn at most this often (values still all counted)
  const PRE = 0.25;            // a triggered capture shows this fraction of its window before the trigger
  const W = {
    signals: [],               // [{key, group, name, type}]
    values: {},                // key -> latest value
    stats: {},                 // key -> {min, max}
    samples: [],               // [{t, v: {key: number}}], oldest first
    plotted: new Set(), frozen: false, armed: null, triggered: null,
    tableUpdates: 0, lastTable: 0, plot: null, dirty: false, cycle: null, t: null,
  };
  window.xrfWatch = W;  // test hook
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
  const visible = () => W.root && !W.root.classList.contains("hidden");

  // ---- the signals -----------------------------------------------------------------------------

  function signalList(schema) {
    const out = [];
    for (const f of schema.xeno2ros || []) {
      if (f.count) out.push({ key: "x." + f.name, group: "Xeno2Ros", name: f.name, type: `${f.type}[${f.count}]`, array: true });
      else out.push({ key: "x." + f.name, group: "Xeno2Ros", name: f.name, type: f.type });
    }
    for (const f of schema.ros2xeno || []) {
      out.push({ key: "r." + f.name, group: "Ros2Xeno", name: f.name, type: f.count ? `${f.type}[${f.count}]` : f.type, array: !!f.count });
    }
    // The bench's channels (the run message's count; 4 before any run): an encoder, a PWM and a
    // digital output per channel, two digital inputs per channel.
    const n = schema.channels || 4;
    for (let i = 1; i <= n; i++) out.push({ key: "enc" + i, group: "Encoders", name: "enc" + i, type: "14-bit count" });
    for (let i = 1; i <= n; i++) out.push({ key: "pwm" + i, group: "PWM", name: "pwm" + i, type: "±2047" });
    for (let i = 1; i <= 2 * n; i++) out.push({ key: "din" + i, group: "Digital in", name: "din" + i, type: "bit" });
    for (let i = 1; i <= n; i++) out.push({ key: "dout" + i, group: "Digital out", name: "dout" + i, type: "bit" });
    return out;
  }

  function setSchema(schema) {
    const keys = JSON.stringify(signalList(schema).map((s) => s.key));
    if (keys === JSON.stringify(W.signals.map((s) => s.key))) return;
    W.signals = signalList(schema);
    W.values = {}; W.stats = {}; W.samples = []; W.triggered = null;
    // Until the loop's first telemetry says otherwise, the controller's Ros2Xeno is all zeros.
    for (const f of schema.ros2xeno || []) if (!f.count) W.values["r." + f.name] = f.type === "bool" ? false : 0;
    for (const [k, x] of Object.entries(W.loop || {})) W.values["r." + k] = x;
    // The default choice follows the run's fields until the student picks their own.
    if (!W.picked || ![...W.plotted].some((k) => W.signals.some((s) => s.key === k))) {
      W.plotted = new Set(W.signals.filter((s) => s.group === "Xeno2Ros" && !s.array).slice(0, 4).map((s) => s.key));
      if (!W.plotted.size) W.plotted.add("enc1");
    }
    if (W.root) { buildTable(); buildTriggerSelect(); buildPlot(); }
  }

  function numeric(v) { return typeof v === "boolean" ? Number(v) : typeof v === "number" ? v : null; }

  function onTelemetry(m) {
    const v = {};
    (m.enc || []).forEach((x, i) => { v["enc" + (i + 1)] = x; });
    (m.pwm || []).forEach((x, i) => { v["pwm" + (i + 1)] = x; });
    (m.din || []).forEach((x, i) => { v["din" + (i + 1)] = x; });
    (m.dout || []).forEach((x, i) => { v["dout" + (i + 1)] = x; });
    for (const [k, x] of Object.entries(m.xeno2ros || {})) v["x." + k] = x;
    // Ros2Xeno as the loop has it ({} for someone else's run): never what this page last sent.
    if (m.ros2xeno && Object.keys(m.ros2xeno).length) {
      W.loop = m.ros2xeno;
      for (const [k, x] of Object.entries(m.ros2xeno)) v["r." + k] = x;
    }
    W.cycle = m.cycle; W.t = m.t;
    const sample = { t: m.t, v: {} };
    for (const [k, x] of Object.entries(v)) {
      W.values[k] = x;
      const n = numeric(x);
      if (n === null) continue;
      sample.v[k] = n;
      const s = W.stats[k] || (W.stats[k] = { min: n, max: n });
      if (n < s.min) s.min = n;
      if (n > s.max) s.max = n;
    }
    const prev = W.samples[W.samples.length - 1];
    if (prev && m.t < prev.t) { W.samples = []; W.triggered = null; }  // a new run: its own time axis
    // Telemetry stopped meanwhile (the tab was hidden: app.js followVisibility): a gap, not a line.
    else if (prev && m.t > prev.t + 1) W.samples.push({ t: prev.t + 1e-3, v: {} });
    W.samples.push(sample);
    while (W.samples.length && W.samples[0].t < m.t - BUFFER_S) W.samples.shift();
    checkTrigger(prev, sample);
    W.dirty = true;
  }

  // ---- the table ---------------------------------------------------------------------------------

  function fmt(v) {
    if (v === undefined || v === null) return "–";
    if (typeof v === "number") return Number.isInteger(v) ? String(v) : v.toFixed(4);
    if (Array.isArray(v)) return "[" + v.map(fmt).join(", ") + "]";
    return String(v);
  }

  function buildTable() {
    const tb = q("watch-body");
    tb.textContent = "";
    let group = "";
    for (const s of W.signals) {
      if (s.group !== group) {
        group = s.group;
        tb.append(el("tr", { class: "watch-group" }, el("th", { colspan: "6", text: group })));
      }
      const cb = el("input", { type: "checkbox", "data-key": s.key, title: "plot it in the scope", "aria-label": "plot " + s.name });
      cb.checked = W.plotted.has(s.key);
      cb.disabled = !!s.array;
      cb.addEventListener("change", () => { W.picked = true; if (cb.checked) W.plotted.add(s.key); else W.plotted.delete(s.key); buildPlot(); });
      tb.append(el("tr", { id: "watch-row-" + s.key.replace(/\./g, "-"), "data-key": s.key },
        el("td", {}, cb), el("td", { class: "mono", text: s.name }), el("td", { class: "muted small", text: s.type }),
        el("td", { class: "val mono" }), el("td", { class: "min mono muted small" }), el("td", { class: "max mono muted small" })));
    }
    W.lastTable = 0;
    renderTable(true);
  }

  function renderTable(force) {
    if (W.frozen && !force) return;
    const now = performance.now();
    if (!force && now - W.lastTable < 1000 / TABLE_HZ) return;
    W.lastTable = now;
    W.tableUpdates += 1;
    for (const tr of q("watch-body").querySelectorAll("tr[data-key]")) {
      const k = tr.dataset.key, st = W.stats[k];
      const text = fmt(W.values[k]);
      const cell = tr.cells[3];
      if (cell.textContent !== text) { cell.textContent = text; cell.classList.remove("changed"); void cell.offsetWidth; cell.classList.add("changed"); }
      tr.cells[4].textContent = st ? fmt(st.min) : "";
      tr.cells[5].textContent = st ? fmt(st.max) : "";
    }
    q("watch-cycle").textContent = W.cycle == null ? "no data yet" : `cycle ${W.cycle} · t = ${W.t.toFixed(3)} s`;
  }

  // ---- the scope ---------------------------------------------------------------------------------

  function windowS() { return Number(q("watch-window").value) || 5; }

  // The scope's y axes: one per unit, as the Bench page's plots (app.js xrf.unitPlotOpts).
  function buildPlot() {
    const host = q("watch-plot");
    host.textContent = "";
    const keys = [...W.plotted].filter((k) => W.signals.some((s) => s.key === k && !s.array));
    W.plotKeys = keys;
    const unit = xrf.unitPlotOpts(keys, fmt);
    W.scales = unit.scaleNames;
    const opts = {
      width: plotWidth(), height: 260, legend: { show: true }, cursor: { drag: { x: false, y: false } },
      scales: unit.scales, axes: unit.axes, series: unit.series,
    };
    opts.hooks = { draw: [drawParamMarkers] };
    W.plot = new uPlot(opts, [[], ...keys.map(() => [])], host);
    W.dirty = true;
    renderPlot(true);
  }

  // Applied parameter sets (pages/params.js keeps them: xrf.paramMarkers(), t = cycle / frequency,
  // the same clock as the telemetry's t) as dashed lines across the scope, so the response before
  // and after a change is told apart; W.markersShown says which cycles were drawn (the tests').
  function drawParamMarkers(u) {
    const marks = xrf.paramMarkers ? xrf.paramMarkers() : [];
    const zero = W.shown ? W.shown.zero : 0, { left, top, width, height } = u.bbox;
    const shown = [];
    u.ctx.save();
    u.ctx.strokeStyle = "#e36209";
    u.ctx.lineWidth = 1.5 * devicePixelRatio;
    u.ctx.setLineDash([4 * devicePixelRatio, 3 * devicePixelRatio]);
    for (const mk of marks) {
      const x = u.valToPos(mk.t - zero, "x", true);
      if (!(x >= left && x <= left + width)) continue;
      u.ctx.beginPath(); u.ctx.moveTo(x, top); u.ctx.lineTo(x, top + height); u.ctx.stroke();
      shown.push(mk.cycle);
    }
    u.ctx.restore();
    W.markersShown = shown;
  }

  // From its panel, and never past the window's right edge: the panel's width can follow its
  // content (the plot itself among it), so a plot built while the panel was wide kept it wide
  // (CI: a 1782 px scope in a 1280 px window).
  function plotWidth() {
    const panel = q("watch-scope-panel");
    const fromPanel = panel && panel.clientWidth ? panel.clientWidth - 28 : 600;
    const left = panel ? Math.max(0, panel.getBoundingClientRect().left) : 0;
    const room = document.documentElement.clientWidth - left - 28;
    return Math.max(280, Math.min(fromPanel, room));
  }

  // What the scope shows: the last window (running), or the window around the trigger.
  function renderPlot(force) {
    if (!W.plot || (W.frozen && !force)) return;
    const win = windowS();
    let t0, t1, zero = 0;
    const last = W.samples[W.samples.length - 1];
    if (W.triggered) {
      zero = W.triggered.t;
      t0 = zero - PRE * win; t1 = zero + (1 - PRE) * win;
    } else {
      t1 = last ? last.t : win; t0 = t1 - win;
    }
    const xs = [], cols = W.plotKeys.map(() => []);
    for (const s of W.samples) {
      if (s.t < t0 || s.t > t1) continue;
      xs.push(s.t - zero);
      W.plotKeys.forEach((k, i) => cols[i].push(s.v[k] ?? null));
    }
    W.plot.setData([xs, ...cols], false);
    W.plot.setScale("x", { min: t0 - zero, max: t1 - zero });
    xrf.fitScales(W.plot, W.scales, W.plotKeys, cols);  // app.js
    if (W.plot.cursor.idx == null) W.plot.setLegend();  // newest values, not "--", when not hovered
    W.shown = { t0, t1, zero, points: xs.length };
  }

  // The layout can resize the scope's panel after the plot was sized (the page's grid applied,
  // the window narrowed past the one-column width) without a resize event (CI: a scope built
  // before the grid, 1782 px in a 1280 px window): the panel is watched and the plot refitted
  // before the next paint. Anything else that leaves it too wide is caught twice a second.
  function fitPlot() {
    if (!W.plot || !visible()) return;
    const want = plotWidth();
    if (Math.abs(want - W.plot.width) > 2) W.plot.setSize({ width: want, height: 260 });
  }
  function watchPanelSize() {
    const panel = q("watch-scope-panel");
    if (panel && typeof ResizeObserver !== "undefined") new ResizeObserver(fitPlot).observe(panel);
  }
  let fitAt = 0;

  function frame(now) {
    if (now - fitAt >= 500) { fitAt = now; fitPlot(); }
    if (W.dirty && visible()) {
      W.dirty = false;
      renderTable(false);
      renderPlot(false);
      // A triggered capture completes once its post-trigger part has arrived: then it freezes.
      if (W.triggered && !W.frozen && W.t != null && W.t >= W.triggered.t + (1 - PRE) * windowS()) {
        setFrozen(true, `triggered at t = ${W.triggered.t.toFixed(3)} s: ${W.triggered.what}`);
        renderPlot(true);
      }
    }
    requestAnimationFrame(frame);
  }

  function setFrozen(on, why) {
    W.frozen = on;
    q("watch-freeze").textContent = on ? "Resume" : "Freeze";
    q("watch-freeze").classList.toggle("on", on);
    q("watch-state").textContent = on ? "FROZEN" + (why ? ": " + why : "") : W.armed ? "armed: waiting for the trigger" : "live";
    q("watch-state").className = "watch-state" + (on ? " frozen" : W.armed ? " armed" : "");
    if (!on) { W.triggered = null; W.dirty = true; }
  }

  // ---- the trigger -------------------------------------------------------------------------------

  function buildTriggerSelect() {
    const sel = q("watch-trig-signal"), keep = sel.value;
    sel.textContent = "";
    for (const s of W.signals.filter((x) => !x.array)) sel.append(el("option", { value: s.key, text: `${s.group}: ${s.name}` }));
    if (keep && [...sel.options].some((o) => o.value === keep)) sel.value = keep;
  }

  function arm() {
    const key = q("watch-trig-signal").value, level = Number(q("watch-trig-level").value);
    if (!key || !isFinite(level)) { q("watch-state").textContent = "choose a signal and a level"; return; }
    W.armed = { key, level, edge: q("watch-trig-edge").value };
    W.triggered = null;
    setFrozen(false);
    q("watch-state").textContent = `armed: ${key.replace(/^[xr]\./, "")} ${W.armed.edge} through ${level}`;
    q("watch-state").className = "watch-state armed";
  }

  function checkTrigger(prev, cur) {
    const a = W.armed;
    if (!a || !prev || W.frozen) return;
    const y0 = prev.v[a.key], y1 = cur.v[a.key];
    if (y0 === undefined || y1 === undefined) return;
    const up = y0 < a.level && y1 >= a.level, down = y0 > a.level && y1 <= a.level;
    if (!((a.edge === "rising" && up) || (a.edge === "falling" && down) || (a.edge === "either" && (up || down)))) return;
    // Where between the two samples the signal crossed the level (linear): the scope's t = 0.
    const f = y1 === y0 ? 1 : (a.level - y0) / (y1 - y0);
    W.triggered = { t: prev.t + f * (cur.t - prev.t), key: a.key, level: a.level, edge: a.edge, before: y0, after: y1,
      what: `${a.key.replace(/^[xr]\./, "")} ${up ? "rising" : "falling"} through ${a.level}` };
    W.armed = null;
    q("watch-state").textContent = `triggered at t = ${W.triggered.t.toFixed(3)} s: capturing…`;
    q("watch-state").className = "watch-state armed";
  }

  // ---- page --------------------------------------------------------------------------------------

  function init(root) {
    W.root = root;
    root.classList.add("watch-page");
    root.innerHTML = `
      <section class="panel" id="watch-table-panel">
        <h2>Watch <span class="muted small" id="watch-cycle">no data yet</span></h2>
        <div class="muted small" id="watch-note">Ros2Xeno: the values the loop has, whoever wrote them (any tab, ROS 2, the CLI).</div>
        <table class="watch-table"><thead><tr><th title="plot">⧉</th><th>signal</th><th>type</th><th>value</th><th>min</th><th>max</th></tr></thead>
          <tbody id="watch-body"></tbody></table>
      </section>
      <section class="panel" id="watch-scope-panel">
        <h2>Scope <span id="watch-state" class="watch-state">live</span></h2>
        <div class="row watch-controls">
          <label>window <select id="watch-window">
            <option value="0.5">0.5 s</option><option value="1">1 s</option><option value="2">2 s</option>
            <option value="5" selected>5 s</option><option value="10">10 s</option><option value="30">30 s</option><option value="60">60 s</option>
          </select></label>
          <button id="watch-freeze">Freeze</button>
        </div>
        <div class="row watch-controls">
          <label>trigger <select id="watch-trig-signal" aria-label="trigger signal"></select></label>
          <select id="watch-trig-edge" aria-label="edge"><option value="rising">rising</option><option value="falling">falling</option><option value="either">either</option></select>
          <label>through <input id="watch-trig-level" type="number" step="any" value="0" aria-label="level"></label>
          <button id="watch-arm">Arm</button>
        </div>
        <div id="watch-plot"></div>
        <div class="muted small">Tick signals in the table to plot them. A trigger captures one window (a quarter of it before the crossing, t = 0 at the crossing) and freezes; Resume goes live again.</div>
      </section>`;
    q("watch-freeze").addEventListener("click", () => { setFrozen(!W.frozen); if (!W.frozen) { W.armed = null; setFrozen(false); } });
    q("watch-arm").addEventListener("click", arm);
    if (xrf.paramsPanel) xrf.paramsPanel(root);  // the Parameters panel beside the scope (pages/params.js)
    q("watch-window").addEventListener("change", () => { W.dirty = true; renderPlot(true); });
    setSchema(xrf.schema || {});
    buildTable(); buildTriggerSelect(); buildPlot(); watchPanelSize();
    window.addEventListener("resize", () => { if (W.plot && visible()) W.plot.setSize({ width: plotWidth(), height: 260 }); });
    requestAnimationFrame(frame);
  }

  function show() {
    setSchema(xrf.schema || {});
    if (W.plot) W.plot.setSize({ width: plotWidth(), height: 260 });
    W.dirty = true;
  }

  xrf.onSample(onTelemetry);
  // An armed trigger, or a capture under way, keeps telemetry coming while the tab is hidden (app.js
  // followVisibility): the crossing it waits for must not be missed.
  xrf.keepTelemetry.push(() => !!W.armed || (!!W.triggered && !W.frozen));  // each sample of each telemetry message, played out (app.js)
  xrf.on("run", (m) => {
    if (m.ros2xeno && (m.event === "started" || m.event === "current")) {
      W.loop = null;  // a new run's loop starts from zero
      setSchema({ ros2xeno: m.ros2xeno, xeno2ros: m.xeno2ros, channels: m.channels });
    }
  });
  W.arm = arm; W.setFrozen = setFrozen;
  xrf.addPage({ id: "watch", title: "Watch", order: 5, init, show });
})();
