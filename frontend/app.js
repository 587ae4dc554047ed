// XRF Lab dashboard: one WebSocket to the appliance, plain DOM, uPlot for the plots.
// Everything the page shows comes from WebSocket messages (state, run, telemetry, timing,
// monitor, alarm); REST is used only for the build list, starting/ending runs, the run list and
// the state machine to draw (GET /api/state-machine).
"use strict";

const WINDOW_S = 10;         // seconds of history in the live plots
const SETPOINT_HZ = 20;      // slider drags are sent at most this often
const MONITOR_LINES = 500;

const $ = (id) => document.getElementById(id);

const xrf = {                // also the test hook: tests read window.xrf
  ws: null,
  pages: {},                 // id -> {id, title, order, perm, el, init, show}: see addPage()
  listeners: {},             // message type -> [fn]: see on()
  state: { state: 0, name: "NO RUN", allowed: [], active: false },
  run: null,
  plots: {},
  telemetryCount: 0,          // samples drawn
  telemetryMessages: 0,       // telemetry messages received (each carries telemetry_per_message samples)
  lastTelemetry: null,        // the last sample drawn, with its message's run_id, lost and ros2xeno
  schema: { ros2xeno: [], xeno2ros: [] },
};
window.xrf = xrf;

// ---- who is logged in (docs/developers/security.md) -----------------------------------------
// Escaping, the CSRF header and requests are frontend/lib.js's (loaded first); the pages reach
// them as xrf.esc, xrf.csrfHeaders and xrf.api. No session: the login page.
xrf.esc = xrfLib.esc;
xrf.csrfHeaders = xrfLib.csrfHeaders;
// How a run ended (runs.END_REASONS on the server: "self exit", "hang", "appliance restart", ...).
xrf.endReason = (r) => r.end_reason ? ` (${r.end_reason.replace(/_/g, " ")})` : (r.crash_reason ? ` (${r.crash_reason})` : "");
const endReason = xrf.endReason;
xrf.toLogin = function () { location.href = "/login?next=" + encodeURIComponent(location.pathname + location.hash); };
xrf.me = null;
xrf.meReady = fetch("/api/me").then((r) => {
  if (r.status === 401) { xrf.toLogin(); return new Promise(() => {}); }
  return r.json();
}).then((me) => { xrf.me = me; if (me.must_change) xrf.toLogin(); return me; });
// What the user may do: a permission of /api/me's `perms` (server/security/roles.py's Perm: "watch",
// "stop", "lease", "drive", "projects", "educator"). Pages ask this, never a role's name.
xrf.may = (perm) => !!xrf.me && xrf.me.perms.includes(perm);

// ---- state machine drawing ------------------------------------------------------------------

const NODES = {
  IDLE: [70, 60], INITIALISING: [250, 60], INITIALISED: [430, 60], RUN: [610, 60], PAUSING: [790, 60],
  QUIT: [70, 200], ERROR: [250, 200], STOPPED: [430, 200], STOPPING: [610, 200], PAUSED: [790, 200],
};
const NODE_W = 124, NODE_H = 36;
// The transitions are not written here: the appliance serves them (GET /api/state-machine),
// read out of rt_core's C command table, so the drawing cannot disagree with the loop. Only
// the layout is the page's: where each state sits and the curve of an edge that would cross a
// node if drawn straight ("from>to": control point).
const CURVES = { "RUN>INITIALISING": [430, -15], "PAUSED>INITIALISING": [610, 125], "STOPPED>QUIT": [250, 275] };

// [from, to, command or "" for a hook completing, optional curve control point]
function edgesOf(machine) {
  const edges = machine.transitions.map((t) => [t.from, t.to, t.cmd]);
  // A hook completing along a command's edge (INITIALISED -> RUN, RUN -> STOPPING) is drawn
  // once, as that command's edge.
  for (const c of machine.completions) {
    if (!edges.some(([from, to]) => from === c.from && to === c.to)) edges.push([c.from, c.to, ""]);
  }
  return edges.map(([from, to, cmd]) => [from, to, cmd, CURVES[from + ">" + to]]);
}
const SVGNS = "http://www.w3.org/2000/svg";

function svgEl(tag, attrs, parent) {
  const el = document.createElementNS(SVGNS, tag);
  for (const [k, v] of Object.entries(attrs)) el.setAttribute(k, v);
  if (parent) parent.appendChild(el);
  return el;
}

// Point where the segment from the centre of a node towards (tx, ty) leaves its rectangle.
function border([cx, cy], [tx, ty]) {
  const dx = tx - cx, dy = ty - cy;
  const sx = dx ? (NODE_W / 2 + 4) / Math.abs(dx) : Infinity;
  const sy = dy ? (NODE_H / 2 + 4) / Math.abs(dy) : Infinity;
  const s = Math.min(sx, sy);
  return [cx + dx * s, cy + dy * s];
}

function drawStateMachine(machine) {
  const svg = $("state-machine");
  svg.textContent = "";
  // A state this page has no place for still shows (below the others) rather than vanishing.
  const spare = machine.states.filter((s) => !NODES[s.name]);
  spare.forEach((s, i) => { NODES[s.name] = [70 + 180 * (i % 5), 250 + 60 * Math.floor(i / 5)]; });
  const defs = svgEl("defs", {}, svg);
  for (const [id, color] of [["arrow", "#9ca3af"], ["arrow-on", "#1f6feb"]]) {
    const m = svgEl("marker", { id, viewBox: "0 0 10 10", refX: 9, refY: 5, markerWidth: 7, markerHeight: 7, orient: "auto-start-reverse" }, defs);
    svgEl("path", { d: "M0,0 L10,5 L0,10 z", fill: color }, m);
  }
  for (const [from, to, cmd, ctrl] of edgesOf(machine)) {
    const g = svgEl("g", { class: "edge" + (cmd ? "" : " auto"), "data-from": from, "data-cmd": cmd }, svg);
    const a = NODES[from], b = NODES[to];
    const [x1, y1] = border(a, ctrl || b), [x2, y2] = border(b, ctrl || a);
    const d = ctrl ? `M${x1},${y1} Q${ctrl[0]},${ctrl[1]} ${x2},${y2}` : `M${x1},${y1} L${x2},${y2}`;
    svgEl("path", { d }, g);
    const mid = ctrl ? [(x1 + 2 * ctrl[0] + x2) / 4, (y1 + 2 * ctrl[1] + y2) / 4] : [(x1 + x2) / 2, (y1 + y2) / 2];
    const t = svgEl("text", { x: mid[0] + (y1 === y2 ? 0 : 8), y: mid[1] - 5 }, g);
    t.textContent = cmd || "done";
  }
  for (const { name } of machine.states) {
    const [x, y] = NODES[name];
    const g = svgEl("g", { class: "node", id: "node-" + name }, svg);
    svgEl("rect", { x: x - NODE_W / 2, y: y - NODE_H / 2, width: NODE_W, height: NODE_H, rx: 8 }, g);
    svgEl("text", { x, y }, g).textContent = name;
  }
}

// A button per command, in the C list's order; a safe one (stop, pause: channels.h's XRF_CMDS)
// stays usable without the bench (accounts.css, data-safe).
function drawCommands(machine) {
  const box = $("commands");
  box.textContent = "";
  for (const c of machine.commands) {
    const b = document.createElement("button");
    b.dataset.cmd = c.name;
    if (c.safe) b.dataset.safe = "";
    b.textContent = c.name;
    b.disabled = true;  // until applyState says the command is allowed now
    b.addEventListener("click", () => sendCommand(c.name));
    box.appendChild(b);
  }
}

// ---- state ----------------------------------------------------------------------------------

// States a reset is accepted from (the C table, through GET /api/state-machine), and the states
// whose hook completes into one of them: the state published may skip that step.
function resettableStates() {
  const m = xrf.machine;
  if (!m) return new Set();
  const from = new Set(m.transitions.filter((t) => t.cmd === "reset").map((t) => t.from));
  for (const c of m.completions) if (from.has(c.to)) from.add(c.from);
  return from;
}

function applyState(s) {
  const before = xrf.state;
  const ended = xrf.run && !xrf.run.active && xrf.run.run;
  if (!s.active && ended && (s.run_id == null || s.run_id === ended.id)) {
    // The appliance's last word on an ended run is the loop's last state, inactive: RUN for a
    // crash. Shown as RUN it read as running under the crash banner (issue 19).
    s = { ...s, name: ended.crashed ? "CRASHED" : "ENDED", allowed: [] };
  }
  xrf.state = s;
  const name = $("state-name");
  name.textContent = s.name;
  name.classList.toggle("none", !s.active);
  stripState(s.name, s.active ? (s.name === "RUN" ? "run" : "live") : (s.name === "CRASHED" ? "bad" : "none"));
  // An accepted reset zeroes the setpoints on the appliance (server/http/runs.py): show that here too.
  // (From these states only a reset leads to INITIALISING/INITIALISED; the state published may
  // skip INITIALISING when the controller's init is quick.)
  if (s.active && ["INITIALISING", "INITIALISED"].includes(s.name) && before.active && resettableStates().has(before.name)) {
    showSetpoints(zeroed(xrf.appliedSetpoint));
  }
  document.querySelectorAll("#state-machine .node").forEach((n) => n.classList.toggle("current", s.active && n.id === "node-" + s.name));
  const allowed = new Set(s.active ? s.allowed : []);
  document.querySelectorAll("#state-machine .edge").forEach((e) => {
    e.classList.toggle("enabled", e.dataset.from === s.name && allowed.has(e.dataset.cmd));
  });
  updateCommandButtons();
  const rej = $("rejected");
  if (s.rejected && s.rejected.ticket !== xrf.dismissedReject) {
    rej.textContent = `Rejected: ${s.rejected.name} (${s.rejected.cmd}) — ${s.rejected.reason}`;
    rej.classList.remove("hidden");
  } else {
    rej.classList.add("hidden");
  }
  if (s.last_error) $("run-detail").dataset.error = s.last_error;
  updateRunSummary();
}

// Why the user may not use a command button now, "" when they may: pages/lease.js's one rule
// (permissions from /api/me and the bench lease). `safe`: stop and pause, never held back
// before that rule has loaded.
function blockOf(safe) { return xrf.commandBlock ? xrf.commandBlock(safe) : safe ? "" : "…"; }

// A command is usable when the state machine accepts it now and the user may send it; a button
// that is not says why on hover.
function updateCommandButtons() {
  const s = xrf.state, allowed = new Set(s.active ? s.allowed : []);
  document.querySelectorAll("#commands button").forEach((b) => {
    const why = !s.active ? "no live run" : !allowed.has(b.dataset.cmd) ? `not accepted in ${s.name} (the state machine above)`
      : blockOf(b.dataset.safe !== undefined);
    b.disabled = !!why;
    b.title = why;
  });
}

// Every button whose use depends on who the user is and who holds the bench, again: called by
// pages/lease.js when the lease or the user changes.
xrf.permsChanged = function () {
  if (!xrf.started) return;  // init() draws them all once
  updateCommandButtons();
  updateRunSummary();
  updateSetpointsEnabled();
};

// The status strip's state badge (index.html, #strip-state): on every page, never scrolled away.
function stripState(text, kind) {
  const el = $("strip-state");
  if (!el) return;
  el.textContent = text;
  el.className = "strip-state " + kind;
}

function sendCommand(cmd) {
  if (!xrf.ws || xrf.ws.readyState !== WebSocket.OPEN) return;
  xrf.ws.send(JSON.stringify({ type: "command", cmd }));
}

// The documented stop rule (docs/students/dashboard.md): RUN or PAUSED -> `stop` (the
// controller's own safe stop); in any other state of a live run, end the run (quit, then signals).
function emergencyStop() {
  // Who may: pages/lease.js explains to whoever may not (observers; students without the bench
  // when stopping would end the run). Stop and pause themselves work for every student.
  if (xrf.stopBlocked && xrf.stopBlocked()) return;
  const s = xrf.state;
  if (s.active && s.allowed.includes("stop")) {  // RUN or PAUSED (the C command table says)
    sendCommand("stop");
  } else if (xrf.run && xrf.run.active) {
    endRun();
  }
}

// ---- run ------------------------------------------------------------------------------------

async function api(method, path, body) {
  const { ok, status, data, res } = await xrfLib.send(method, path, body || undefined);
  if (status === 401) { xrf.toLogin(); throw new Error("logged out"); }
  if (!ok) {
    const err = new Error(data.detail ? (typeof data.detail === "string" ? data.detail : JSON.stringify(data.detail)) : res.statusText);
    err.status = status;
    throw err;
  }
  return data;
}

async function loadBench() {
  try {
    const b = await api("GET", "/api/bench");
    xrf.benchSim = b.sim;
    xrf.benchMode = b.mode;
    $("bench").title = b.profile;
    showPlant();
  } catch (e) { $("bench").textContent = "bench ?"; }
}

// The header's plant badge: the live run's plant (a Jiwy run on a bench whose default is RELbot),
// else the bench's. Called by both the bench's answer and every run message, whichever comes
// first: the WebSocket's snapshot can arrive before GET /api/bench answers.
function showPlant() {
  if (!xrf.benchMode) return;  // GET /api/bench has not answered yet; it calls this when it does
  const m = xrf.run, r = m && m.run;
  if (xrf.benchMode !== "sim") { $("bench").textContent = "real bench"; return; }
  $("bench").textContent = `simulated · ${r && m.active && r.sim ? r.sim : xrf.benchSim}`;
}

// The plant menu lists rt_core's plant table (GET /api/plants): this page has no list of plants.
async function loadPlants() {
  const menu = $("sim-select");
  for (const p of await api("GET", "/api/plants")) {
    if ([...menu.options].some((o) => o.value === p.name)) continue;
    const o = document.createElement("option");
    o.value = p.name;
    o.textContent = p.name;
    o.title = p.title;
    menu.appendChild(o);
  }
}

// The build of a run just started from anywhere (Projects, Editor, another tab): "Start run" here
// then starts that build again, not the example picked before (issue 19).
let wantBuild = null;

async function loadBuilds() {
  const sel = $("build-select");
  const keep = sel.value;
  const builds = await api("GET", "/api/builds");
  sel.innerHTML = "";
  for (const b of builds) {
    const o = document.createElement("option");
    o.value = b.name;
    if (b.kind === "project") {  // the newest successful build of each of the user's projects
      o.textContent = `${b.label} (your project)`;
      o.dataset.project = b.project_id;
      o.dataset.build = b.build_id;
    } else {
      o.textContent = `${b.name} (${b.kind}${b.status === "ready" ? "" : ", " + b.status})`;
    }
    sel.appendChild(o);
  }
  // A run just started; else the user's choice; else the build of the current run; else the
  // example for this bench's plant.
  const current = xrf.run && xrf.run.run && xrf.run.run.build;
  const plant = builds.find((b) => b.kind === "example" && b.name === xrf.benchSim);
  const has = (n) => n && builds.some((b) => b.name === n);
  const pick = [wantBuild, keep, current, plant && plant.name].find(has);
  if (has(wantBuild)) wantBuild = null;
  if (pick) sel.value = pick;
}

async function startRun() {
  const btn = $("btn-start-run");
  btn.disabled = true;
  startRun.busy = true;
  $("run-detail").textContent = `Building and starting ${$("build-select").value}…`;
  try {
    const opt = $("build-select").selectedOptions[0];
    const body = {};
    if ($("sim-select").value) body.sim = $("sim-select").value;
    if ($("log-timing").checked) body.log_timing = true;
    if (opt && opt.dataset.project) {  // a project build runs as from the Projects page (linked to its build)
      await api("POST", `/api/projects/${opt.dataset.project}/builds/${opt.dataset.build}/run`, body);
    } else {
      await api("POST", "/api/runs", { build: $("build-select").value, ...body });
    }
  } catch (e) {
    // Refused by the run sandbox (a protection layer missing, runs not allowed without it): the
    // appliance also says so to every page as a confinement alarm (`started: false`), which the
    // alarm bar shows (HANDLERS.alarm).
    $("run-detail").textContent = "Could not start: " + e.message;
  } finally {
    startRun.busy = false;
    updateRunSummary();
    loadBuilds().catch(() => {});
  }
}

async function endRun() {
  try { await api("POST", "/api/runs/current/stop"); } catch (e) { $("run-detail").textContent = e.message; }
}

async function loadRuns() {
  const runs = await api("GET", "/api/runs?limit=8");
  const body = $("runs-body");
  body.innerHTML = "";
  for (const r of runs) {
    const tr = document.createElement("tr");
    tr.id = "run-row-" + r.id;
    const cells = [r.id, r.build, r.status + endReason(r), r.state, r.cycles, r.misses];
    cells.forEach((c, i) => {
      const td = document.createElement("td");
      td.textContent = c;
      if (i === 2 && r.crashed) td.className = "crashed";
      tr.appendChild(td);
    });
    tr.title = r.message;
    body.appendChild(tr);
  }
}

function applyRun(m) {
  xrf.run = m;
  const r = m.run;
  if (m.ros2xeno && (m.event === "started" || m.event === "current")) {
    xrf.schema = { ros2xeno: m.ros2xeno, xeno2ros: m.xeno2ros, channels: m.channels };
    buildSetpoints(m.ros2xeno, m.setpoint || {});
    buildPlots(m.xeno2ros, m.channels);
    if (m.redacted) $("setpoints").innerHTML = '<div class="muted">Setpoints and signals are the run owner\'s.</div>';
  }
  if (r) {
    // Someone else's run (m.redacted): its state and motion are everyone's, its build, output
    // and signals its owner's (docs/developers/security.md, "what others may watch").
    const build = m.redacted ? "another user's controller" : r.build;
    const what = m.active ? `run #${r.id}: ${build} on ${r.sim}` + (m.cycle_freq ? ` @ ${m.cycle_freq} Hz` : "")
      : `run #${r.id} ${r.status}` + endReason(r);
    $("run-detail").textContent = m.active ? `${what} · ${m.program || ""} · ${m.backend || ""}/${m.transport || ""}` : `${what}: ${r.message}`;
  }
  applyConfinement(m);
  if (r && !m.active && (m.event === "ended" || m.event === "current")) {
    // The run is over (a crash included): no state message follows, so the state shown must not
    // stay RUN (issue 19: the badge read RUN under a crash banner).
    applyState({ state: 0, name: r.crashed ? "CRASHED" : "ENDED", allowed: [], active: false });
  }
  if (r && !m.redacted && m.event === "started") {
    wantBuild = r.build;
    loadBuilds().catch(() => {});
  }
  if (m.event === "started") clearAlarm();  // the last run's alarm is history now
  else if (m.event === "ended") clearAlarm("deadline_miss");  // its misses end with it; a crash stays up
  // The header's plant badge follows the run (a Jiwy run on a bench whose default is RELbot).
  showPlant();
  if (m.setpoint && !m.redacted) xrf.appliedSetpoint = { ...m.setpoint };
  updateSetpointsEnabled();
  updateRunSummary();
  loadRuns().catch(() => {});
}

// ---- the run sandbox's missing protection (xrflab.guest; docs/educators/controllers.md) --------
// A controller started with a protection layer missing (the educator's --allow-unconfined): a red
// banner in the sticky top bar, on every page, for as long as that run is live.

function missingText(missing) {
  return Object.entries(missing || {}).map(([layer, why]) => why ? `${layer} (${why})` : layer).join("; ");
}

function showConfinement(runId, missing) {
  const box = $("confinement-banner");
  const text = missingText(missing);
  xrf.confinement = text ? { run_id: runId, missing } : null;
  if (!text) { box.classList.add("hidden"); box.textContent = ""; return; }
  box.textContent = "";
  const head = document.createElement("span");
  head.textContent = "This controller runs WITHOUT: ";
  const why = document.createElement("span");
  why.className = "why";
  why.textContent = text;
  box.append(head, why);
  box.dataset.runId = runId ?? "";
  box.title = "The run sandbox could not give this protection; an educator allowed runs without it (xrf serve --allow-unconfined). xrf doctor and the System page say how to fix it.";
  box.classList.remove("hidden");
}

function applyConfinement(m) {
  const r = m.run;
  if (!m.active) {  // the run is over: so is the warning about it
    if (!xrf.confinement || !r || xrf.confinement.run_id === r.id) showConfinement(null, null);
    return;
  }
  if (m.confinement) showConfinement(r && r.id, m.confinement.missing);
}

function updateRunSummary() {
  const r = xrf.run && xrf.run.run;
  const build = xrf.run && xrf.run.redacted ? "(not yours)" : r && r.build;
  $("run-summary").textContent = xrf.run && xrf.run.active && r ? `#${r.id} ${build} · ${xrf.state.name}` : "no active run";
  const drive = blockOf(false);
  const end = !(xrf.run && xrf.run.active) ? "no live run" : drive;
  $("btn-end-run").disabled = !!end;
  $("btn-end-run").title = end;
  const start = startRun.busy ? "starting…" : drive;
  $("btn-start-run").disabled = !!start;
  $("btn-start-run").title = start;
  // STOP is reachable, on every page, for everyone who may stop (safety): only a user who may
  // not stop anything (an observer) sees it off, with why. Esc still answers them (lease.js).
  const stop = blockOf(true);
  $("btn-estop").disabled = !!stop;
  $("btn-estop").title = stop || "Stop (Esc): RUN/PAUSED → stop; otherwise end the run";
}

// ---- setpoints ------------------------------------------------------------------------------

let pendingSetpoint = {}, setpointTimer = null;
const editedAt = {};  // field -> performance.now() of the user's last change here
// How long a field the user just changed is left alone by followLoop: the change's way to the
// loop and back in telemetry (1/SETPOINT_HZ, a cycle, a telemetry message's period: 2/telemetry_hz,
// and its play-out, 1/telemetry_hz) with room for a busy bench.
const EDIT_HOLD_MS = 1500;

function queueSetpoint(name, value) {
  pendingSetpoint[name] = value;
  editedAt[name] = performance.now();
  if (setpointTimer) return;
  setpointTimer = setTimeout(() => {
    setpointTimer = null;
    const fields = pendingSetpoint;
    pendingSetpoint = {};
    if (xrf.ws && xrf.ws.readyState === WebSocket.OPEN) xrf.ws.send(JSON.stringify({ type: "setpoint", fields }));
  }, 1000 / SETPOINT_HZ);
}

// What the appliance last applied (run message, acks): a refused change goes back to it.
xrf.appliedSetpoint = {};

function zeroed(sp) {
  const out = {};
  for (const [k, v] of Object.entries(sp || {})) out[k] = typeof v === "boolean" ? false : Array.isArray(v) ? v.map(() => 0) : 0;
  return out;
}

// Put values into the controls (not sent: they are what the appliance has).
function showSetpoints(values) {
  for (const [k, v] of Object.entries(values || {})) {
    if (Array.isArray(v)) continue;
    const num = $("sp-" + k), range = $("sp-range-" + k);
    if (num && num.type === "checkbox") num.checked = !!v;
    else if (num) num.value = v;
    if (range) range.value = v;
  }
  xrf.appliedSetpoint = { ...xrf.appliedSetpoint, ...values };
}

// The controls follow the Ros2Xeno the loop has (telemetry's `ros2xeno`: written from this page,
// another tab, the ROS 2 bridge or the CLI), except a field the user is changing: the one with
// the focus (a number being typed, a slider held) or changed here in the last EDIT_HOLD_MS.
function followLoop(values) {
  const now = performance.now(), focused = document.activeElement;
  const fresh = {};
  for (const [k, raw] of Object.entries(values)) {
    if (Array.isArray(raw) || k in pendingSetpoint || now - (editedAt[k] || -Infinity) < EDIT_HOLD_MS) continue;
    const num = $("sp-" + k), range = $("sp-range-" + k);
    if (!num || num === focused || range === focused) continue;
    // A float32 field comes back as the nearest float32 (0.1 -> 0.10000000149): 7 digits of it.
    const f32 = (xrf.schema.ros2xeno.find((f) => f.name === k) || {}).type === "float32";
    const v = f32 && typeof raw === "number" ? Number(raw.toPrecision(7)) : raw;
    const shown = num.type === "checkbox" ? num.checked : Number(num.value);
    if (shown !== v) fresh[k] = v;
  }
  if (Object.keys(fresh).length) showSetpoints(fresh);
}

// Without the bench (a student who does not hold it, an observer) the controls are disabled: a
// change would be refused, and a slider keeping a value never applied misleads (issue 19).
function updateSetpointsEnabled() {
  const live = !!(xrf.run && xrf.run.active && !xrf.run.redacted);
  const may = xrf.mayDrive ? xrf.mayDrive() : true;
  $("setpoints").querySelectorAll("input").forEach((i) => {
    i.disabled = !live || !may;
    i.title = live && !may ? "take the bench to move the setpoints" : "";
  });
}
xrf.updateSetpointsEnabled = updateSetpointsEnabled;

function buildSetpoints(fields, current) {
  const box = $("setpoints");
  box.innerHTML = "";
  if (!fields.length) { box.innerHTML = '<div class="muted">This build has no Ros2Xeno fields.</div>'; return; }
  for (const f of fields) {
    const row = document.createElement("div");
    row.className = "sp";
    const label = document.createElement("label");
    label.textContent = f.name;
    label.title = `${f.type} ${f.name}`;
    row.appendChild(label);
    if (f.count) {  // arrays: a number box per element would crowd a tablet; show as read-only
      const span = document.createElement("span");
      span.className = "muted small";
      span.textContent = `${f.type}[${f.count}] (set from ROS 2 or the CLI)`;
      row.appendChild(span);
      box.appendChild(row);
      continue;
    }
    if (f.type === "bool") {
      const cb = document.createElement("input");
      cb.type = "checkbox"; cb.id = "sp-" + f.name; cb.checked = !!current[f.name];
      cb.addEventListener("change", () => queueSetpoint(f.name, cb.checked));
      row.appendChild(cb);
      box.appendChild(row);
      continue;
    }
    const isInt = /int/.test(f.type);
    const range = document.createElement("input");
    range.type = "range"; range.id = "sp-range-" + f.name;
    range.min = -10; range.max = 10; range.step = isInt ? 1 : 0.01;
    const num = document.createElement("input");
    num.type = "number"; num.id = "sp-" + f.name; num.step = isInt ? 1 : 0.01;
    range.value = num.value = current[f.name] ?? 0;
    label.htmlFor = num.id;
    const parse = (v) => (isInt ? Math.round(Number(v)) : Number(v));
    range.addEventListener("input", () => { num.value = range.value; queueSetpoint(f.name, parse(range.value)); });
    num.addEventListener("input", () => {
      if (num.value === "" || !isFinite(Number(num.value))) return;
      const v = parse(num.value);
      if (Math.abs(v) > Number(range.max)) { range.max = Math.abs(v); range.min = -Math.abs(v); }
      range.value = v;
      queueSetpoint(f.name, v);
    });
    row.appendChild(range);
    row.appendChild(num);
    box.appendChild(row);
  }
  xrf.appliedSetpoint = { ...current };
  updateSetpointsEnabled();
}

// ---- plots ----------------------------------------------------------------------------------

const COLORS = ["#1f6feb", "#d73a49", "#28a745", "#f6a01a", "#6f42c1", "#17a2b8", "#e83e8c", "#6c757d"];

// A series' legend value (uPlot's `value`): at the cursor while hovered, else the newest sample;
// uPlot alone shows "--" until the plot is hovered. Watch's scope uses it too.
xrf.legendValue = (fmt) => (u, v, si, idx) => {
  if (idx == null) {
    const d = u.data[si] || [];
    for (let i = d.length - 1; i >= 0; i--) if (d[i] != null) { v = d[i]; break; }
  }
  return v == null ? "--" : fmt(v);
};
const plotNumber = (v) => (Number.isInteger(v) ? String(v) : v.toFixed(3));

// ---- y axes per unit: the Bench page's plots and Watch's scope (pages/watch.js) --------------
// One y scale per unit where the unit is known (encoder counts, PWM, bits), else one per signal
// (a message field's unit is the student's), each autoscaled: a 0-2 rad position is not
// flattened by 0-16000 counts beside it (issue 31). Axes beyond MAX_AXES are not drawn (room for
// the plot); their signals still scale on their own, and the legend shows their values.
// A signal's key: "enc1", "pwm2", "din1", "dout1", "x.<Xeno2Ros field>", "r.<Ros2Xeno field>".
const MAX_AXES = 4;
xrf.scaleOf = (key) => {
  if (/^enc\d/.test(key)) return "counts";
  if (/^pwm\d/.test(key)) return "PWM";
  if (/^d(in|out)\d/.test(key)) return "bit";
  return key.replace(/^[xr]\./, "");
};

// uPlot options for these keys: scales (in the order of each one's first signal), their axes
// (left, right, left, ...; coloured as their first signal) and one series per key.
xrf.unitPlotOpts = (keys, valueFmt) => {
  const scales = [];
  keys.forEach((k, i) => { const sc = xrf.scaleOf(k); if (!scales.some((x) => x.name === sc)) scales.push({ name: sc, color: COLORS[i % COLORS.length] }); });
  const axes = scales.slice(0, MAX_AXES).map((sc, i) => ({
    scale: sc.name, side: i % 2 ? 1 : 3, stroke: sc.color, label: sc.name, labelSize: 16,
    grid: { show: i === 0 }, size: xrf.axisWidth,
  }));
  return {
    scaleNames: scales.map((x) => x.name),
    scales: { x: { time: false }, ...Object.fromEntries(scales.map((sc) => [sc.name, { auto: true }])) },
    axes: [{ size: 30 }, ...(axes.length ? axes : [{ size: 62 }])],
    series: [{ label: "t (s)" }, ...keys.map((k, i) => ({
      label: k.replace(/^[xr]\./, ""), scale: xrf.scaleOf(k), stroke: COLORS[i % COLORS.length], width: 1.5,
      value: xrf.legendValue(valueFmt),
    }))],
  };
};

// After setData(…, false), which leaves every scale as it was: each y scale is fitted to what it
// shows now, with a margin, and a flat signal gets a range around its value instead of none. A
// range that still holds the data and is not more than four times too wide is kept: a scale that
// moved every frame would re-measure and re-lay its axis every frame.
xrf.fitScales = (plot, scaleNames, keys, cols) => {
  for (const name of scaleNames) {
    let lo = Infinity, hi = -Infinity;
    cols.forEach((c, i) => {
      if (xrf.scaleOf(keys[i]) !== name) return;
      for (const v of c) if (v != null) { if (v < lo) lo = v; if (v > hi) hi = v; }
    });
    if (lo > hi) continue;
    const pad = hi > lo ? (hi - lo) * 0.08 : Math.max(Math.abs(hi) * 0.1, 0.5);
    const cur = plot.scales[name];
    if (cur && cur.min != null && cur.min <= lo && hi <= cur.max && cur.max - cur.min <= 4 * (hi - lo + 2 * pad)) continue;
    plot.setScale(name, { min: lo - pad, max: hi + pad });
  }
};

// A Bench page plot of these signals (keys as above), the last WINDOW_S seconds.
function makePlot(id, keys) {
  const el = $(id);
  el.innerHTML = "";
  const width = Math.max(200, el.clientWidth || el.parentElement.clientWidth || 300);
  const unit = xrf.unitPlotOpts(keys, plotNumber);
  const opts = {
    width, height: 180,
    legend: { show: true },
    cursor: { drag: { x: false, y: false } },
    scales: unit.scales, axes: unit.axes, series: unit.series,
  };
  const data = [[], ...keys.map(() => [])];
  const plot = new uPlot(opts, data, el);
  return { plot, data, keys, names: keys.map((k) => k.replace(/^[xr]\./, "")), scaleNames: unit.scaleNames, dirty: false };
}

// One key per channel of the bench: `channels` is the run's count (the run message's, from the
// run's shared-memory header: 4 on one ico board, 9 on the youBot); 4 before any run.
xrf.channelKeys = (prefix, channels) => Array.from({ length: channels || 4 }, (_, i) => prefix + (i + 1));

function buildChannelPlots(channels) {
  xrf.plots.enc = makePlot("plot-enc", xrf.channelKeys("enc", channels));
  xrf.plots.pwm = makePlot("plot-pwm", xrf.channelKeys("pwm", channels));
}

function buildPlots(xeno2ros, channels) {
  const scalar = xeno2ros.filter((f) => !f.count).map((f) => "x." + f.name);
  xrf.plots.xeno2ros = makePlot("plot-xeno2ros", scalar);
  buildChannelPlots(channels);
}

// Samples further apart than this are not joined by a line (a hidden tab took no telemetry).
const GAP_S = 1;

function pushSample(p, t, values) {
  if (!p) return;
  const d = p.data;
  const last = d[0].length ? d[0][d[0].length - 1] : null;
  if (last !== null && t > last + GAP_S) d.forEach((a, i) => a.push(i ? null : last + 1e-3));  // a gap
  d[0].push(t);
  values.forEach((v, i) => d[i + 1].push(typeof v === "boolean" ? Number(v) : v));
  while (d[0].length && d[0][0] < t - WINDOW_S) d.forEach((a) => a.shift());
  p.dirty = true;
}

// ---- telemetry: samples played out at their own spacing ----------------------------------------
// A telemetry message carries several samples, oldest first (Settings.telemetry_per_message: 6,
// 5 messages a second for the 30 samples a second the plots draw: each message costs the
// appliance a wake-up and a socket write, issue 30 item 4). Drawn all at once the plots would
// advance in 200 ms steps; so the oldest is drawn on arrival and each later one at its own
// distance (its t) after the one before: the plots move at 30 steps a second as with one sample a
// message, each sample shown one sample period (33 ms) after it arrived at the latest. A message
// arriving while samples of the one before are still waiting draws those at once first: the
// order is kept and the page never falls behind by more than a message. Every consumer of
// samples (the Bench page's plots, pages/watch.js's scope) takes them from here: xrf.onSample.
const PLAYOUT_MAX_MS = 100;  // the longest gap played out between two samples of one message
const sampleListeners = [];
let playout = [], playoutTimer = null;
xrf.onSample = (fn) => sampleListeners.push(fn);

function drawSample(s) {
  applyTelemetry(s);
  for (const fn of sampleListeners) {
    try { fn(s); } catch (e) { console.error(e); }
  }
}

function playNext() {
  playoutTimer = null;
  const [s, next] = [playout.shift(), playout[0]];
  drawSample(s);
  if (next) playoutTimer = setTimeout(playNext, Math.min(PLAYOUT_MAX_MS, Math.max(0, (next.t - s.t) * 1000)));
}

function playTelemetry(m) {
  xrf.telemetryMessages += 1;
  if (playoutTimer) { clearTimeout(playoutTimer); playoutTimer = null; }
  while (playout.length) drawSample(playout.shift());
  const samples = m.samples || [];
  if (!samples.length) return;
  // The message's Ros2Xeno is the loop's at its newest sample; an older sample whose Ros2Xeno was
  // another (sent at another time) gets {} (unknown: the controls and the scope keep theirs).
  const newest = samples[samples.length - 1].ros2xeno_t_sent_ns;
  playout = samples.map((s) => ({ ...s, run_id: m.run_id, lost: m.lost,
    ros2xeno: s.ros2xeno_t_sent_ns === newest ? m.ros2xeno : {} }));
  playNext();
}

function applyTelemetry(m) {
  xrf.telemetryCount += 1;
  xrf.lastTelemetry = m;
  const p = xrf.plots.xeno2ros;
  if (p) pushSample(p, m.t, p.names.map((n) => m.xeno2ros[n]));
  // The run message names the count; should a sample's differ (a run message missed), the
  // plots follow the sample rather than drop or invent channels.
  if (xrf.plots.enc && m.enc.length !== xrf.plots.enc.keys.length) buildChannelPlots(m.enc.length);
  pushSample(xrf.plots.enc, m.t, m.enc);
  pushSample(xrf.plots.pwm, m.t, m.pwm);
  if (m.ros2xeno && Object.keys(m.ros2xeno).length && !(xrf.run && xrf.run.redacted)) followLoop(m.ros2xeno);
}

// A controller that must get ready before it may move says so in a bool Xeno2Ros field: the
// cell example's `homed` (every axis found its home switch; RUN is refused until then), the
// youBot example's `arm_ready` (the arm reached its ready pose; base motion is refused until
// then). A project with neither field shows no badge. [field, text when true, when false, title]
const READINESS = [
  ["homed", "homed", "not homed", "Xeno2Ros homed: every axis found its home switch; RUN is refused until then"],
  ["arm_ready", "arm ready", "arm not ready",
    "Xeno2Ros arm_ready: the arm reached its ready pose; the base refuses motion until then"],
];
function showReadiness(m) {
  const el = $("homed-badge");
  const x = m && m.xeno2ros ? m.xeno2ros : {};
  const r = READINESS.find(([field]) => typeof x[field] === "boolean");
  el.classList.toggle("hidden", !r);
  if (!r) return;
  const ok = x[r[0]];
  el.textContent = ok ? r[1] : r[2];
  el.title = r[3];
  el.classList.toggle("ok", ok);
  el.classList.toggle("bad", !ok);
}

// Redraw at most once per animation frame, however fast samples arrive.
function redraw() {
  for (const p of Object.values(xrf.plots)) {
    if (p && p.dirty) {
      if (p.scaleNames) {  // a plot of signals: x follows the data, each y scale fits its own
        p.plot.setData(p.data, false);
        const xs = p.data[0];
        if (xs.length) p.plot.setScale("x", { min: xs[0], max: Math.max(xs[xs.length - 1], xs[0] + 1e-3) });
        xrf.fitScales(p.plot, p.scaleNames, p.keys, p.data.slice(1));
      } else {
        p.plot.setData(p.data);
      }
      p.dirty = false;
      if (p.plot.cursor.idx == null) p.plot.setLegend();  // the newest values, not "--"
    }
  }
  const m = xrf.lastTelemetry;
  showReadiness(m);
  if (m) {
    $("xeno2ros-values").textContent = Object.entries(m.xeno2ros)
      .map(([k, v]) => `${k}=${typeof v === "number" ? v.toFixed(3) : v}`).join("  ");
  }
  requestAnimationFrame(redraw);
}

function resizePlots() {
  for (const [key, p] of Object.entries(xrf.plots)) {
    if (!p) continue;
    const el = key === "jitter" ? $("plot-jitter") : $("plot-" + key);
    p.plot.setSize({ width: Math.max(200, el.clientWidth), height: key === "jitter" ? 140 : 180 });
  }
}

// ---- timing ---------------------------------------------------------------------------------

function us(ns) { return ns === undefined ? "–" : (ns / 1000).toFixed(ns < 10000 ? 1 : 0) + " µs"; }

// uPlot axis size (px) that fits the longest tick label, measured in the axis font, plus the
// tick and the gap uPlot draws beside the labels.
function axisWidth(u, values) {
  if (!values || !values.length) return 40;
  const ctx = axisWidth.ctx || (axisWidth.ctx = document.createElement("canvas").getContext("2d"));
  ctx.font = (u.axes[1] && u.axes[1].font && u.axes[1].font[0]) || "12px system-ui, sans-serif";
  const widest = Math.max(...values.map((v) => ctx.measureText(String(v)).width));
  return Math.ceil(widest / devicePixelRatio) + 18;
}
xrf.axisWidth = axisWidth;

function applyTiming(m) {
  const row = $("run-row-" + m.run_id);  // the live run's row: the stored record is written at its end
  if (row) {
    row.cells[3].textContent = xrf.state.name;
    row.cells[4].textContent = m.cycles;
    row.cells[5].textContent = m.misses;
  }
  $("t-cycles").textContent = m.cycles;
  $("t-misses").textContent = m.misses;
  $("t-misses").classList.toggle("bad", m.misses > 0);
  $("t-freq").textContent = m.cycle_freq + " Hz";
  const w = m.stages.wakeup || {};
  $("t-p50").textContent = us(w.p50);
  $("t-p99").textContent = us(w.p99);
  $("t-max").textContent = us(w.max);
  $("t-work").textContent = us((m.stages.cycle || {}).p99);
  const el = $("plot-jitter");
  if (!xrf.plots.jitter) {
    xrf.plots.jitter = {
      plot: new uPlot({
        width: Math.max(200, el.clientWidth), height: 140, legend: { show: false },
        scales: { x: { time: false, distr: 3 }, y: { distr: 3 } },
        // The y axis as wide as its widest label ("10,000" was clipped at a fixed 50 px: issue 19).
        axes: [{ size: 30 }, { size: axisWidth }],
        series: [{}, { label: "cycles", stroke: "#1f6feb", fill: "rgba(31,111,235,.35)", paths: uPlot.paths.bars({ size: [0.9, 40] }), points: { show: false } }],
      }, [[], []], el),
      data: [[], []], dirty: false,
    };
  }
  const j = xrf.plots.jitter;
  // Log-log bars: x = bucket lower edge in µs (0 pushed to 0.01 so the log scale can show it).
  j.data = [m.jitter.edges.map((e) => Math.max(e / 1000, 0.01)), m.jitter.counts];
  j.dirty = true;
}

// ---- monitor, alarms ------------------------------------------------------------------------

// Whether the monitor follows the newest line: set by the user's scrolling only. Measured at each
// append instead, a hidden console (another page shown: every size 0) read as "at the bottom"
// once and as "scrolled up" forever after (issue 19).
let monitorFollow = true;

function monitorScrolled() {
  const pre = $("monitor");
  if (pre.clientHeight === 0) return;  // hidden: not the user
  monitorFollow = pre.scrollTop + pre.clientHeight >= pre.scrollHeight - 4;
}

function appendMonitor(lines, source) {
  const pre = $("monitor");
  const atBottom = monitorFollow;
  // monitor.printf text usually ends in its own newline; one line per entry here.
  const text = lines.map((l) => (source === "stdout" ? "│ " : "") + l.text.replace(/\n+$/, "")).join("\n") + "\n";
  pre.textContent += text;
  const all = pre.textContent.split("\n");
  if (all.length > MONITOR_LINES) pre.textContent = all.slice(-MONITOR_LINES).join("\n");
  if (atBottom) pre.scrollTop = pre.scrollHeight;
}

// The alarm slot of the status strip (fixed height: showing or hiding it never moves the page).
// A crash or hang is not overwritten by a later deadline miss; a deadline miss stays up with its
// count until dismissed or the next run starts, instead of coming and going every few seconds.
function showAlarm(m) {
  const box = $("alarm");
  // A late one of a run that is over (its timing task's last second): not news for anyone.
  const live = xrf.run && xrf.run.active && xrf.run.run;
  if (m.kind === "deadline_miss" && m.run_id != null && !(live && live.id === m.run_id)) return;
  const serious = ["crash", "hang", "confinement", "log", "memory", "pids", "disk", "cpu"];
  if (m.kind === "deadline_miss" && !box.classList.contains("hidden") && serious.includes(box.dataset.kind)) return;
  box.classList.toggle("warn", m.kind === "deadline_miss");
  const prefix = { crash: "Loop crashed: ", hang: "Loop hung: ", log: "Logging stopped: ", deadline_miss: "Timing: ",
    confinement: "Run sandbox: ", memory: "Run stopped, memory: ", pids: "Run stopped, processes: ",
    disk: "Run stopped, disk: ", cpu: "Run stopped, CPU: ", host_lost: "Supervision: " };
  let text = (prefix[m.kind] || "") + m.message;
  if (m.kind === "deadline_miss") {
    showAlarm.misses = (box.dataset.kind === "deadline_miss" && !box.classList.contains("hidden") ? showAlarm.misses || 0 : 0) + 1;
    if (showAlarm.misses > 1) text += ` (${showAlarm.misses} alarms, last at ${new Date().toLocaleTimeString()})`;
  }
  $("alarm-text").textContent = text;
  box.title = text;
  box.dataset.kind = m.kind;
  box.classList.remove("hidden");
}

// Take the alarm down: any (a new run, a new holder of the bench), or only one of `kind`.
function clearAlarm(kind) {
  const box = $("alarm");
  if (kind && box.dataset.kind !== kind) return;
  box.classList.add("hidden");
  showAlarm.misses = 0;
}
xrf.clearAlarm = clearAlarm;

// ---- pages ----------------------------------------------------------------------------------
// The bench page is index.html's <main id="page-bench">. Every other page is a module in
// frontend/pages/ that calls xrf.addPage({id, title, order, perm, init(el), show(el)}); its element is
// made here. The header (state, STOP) and the Esc key stay on every page.

xrf.addPage = function (page) {
  let el = document.getElementById("page-" + page.id);
  if (!el) {
    el = document.createElement("main");
    el.id = "page-" + page.id;
    el.className = "page hidden";
    document.querySelector("footer.foot").before(el);
  }
  xrf.pages[page.id] = { order: 50, ...page, el, ready: false };
  if (xrf.started) { renderNav(); route(); }  // before the page has started, init() does both
};

// A page may name the permission it needs (`perm`, one of /api/me's perms): without it, no tab,
// and its address shows the Bench (a tab that can only refuse is no use).
const usable = (p) => !p.perm || xrf.may(p.perm);

// Subscribe to a WebSocket message type ("*" for every message).
xrf.on = function (type, fn) { (xrf.listeners[type] = xrf.listeners[type] || []).push(fn); };
xrf.send = function (msg) { if (xrf.ws && xrf.ws.readyState === 1) xrf.ws.send(JSON.stringify(msg)); };
xrf.api = (method, path, body) => api(method, path, body);

function renderNav() {
  const nav = $("nav");
  nav.textContent = "";
  Object.values(xrf.pages).filter(usable).sort((a, b) => a.order - b.order).forEach((p) => {
    const a = document.createElement("a");
    a.href = "#" + p.id;
    a.textContent = p.title;
    a.dataset.page = p.id;
    nav.appendChild(a);
  });
  highlightNav();
}

function highlightNav() {
  const current = (location.hash || "#bench").slice(1);
  document.querySelectorAll("#nav a").forEach((a) => a.classList.toggle("current", a.dataset.page === current));
}

function route() {
  const id = (location.hash || "#bench").slice(1);
  const target = xrf.pages[id] && usable(xrf.pages[id]) ? id : "bench";
  for (const p of Object.values(xrf.pages)) {
    const on = p.id === target;
    p.el.classList.toggle("hidden", !on);
    if (on) {
      if (!p.ready && p.init) { p.init(p.el); }
      p.ready = true;
      if (p.show) p.show(p.el);
    }
  }
  highlightNav();
  if (target === "bench") {
    resizePlots();
    if (monitorFollow) $("monitor").scrollTop = $("monitor").scrollHeight;
  }
}

// ---- the WebSocket --------------------------------------------------------------------------
// What the Bench page does with each kind of message /ws sends. The kinds and their fields are
// defined once, on the appliance (xrflab/server/ws/messages.py, published at GET /api/ws-schema);
// this table has an entry for every server kind there (tests/ui/test_state_machine_ui.py checks
// it against the schema). Pages add their own listeners with xrf.on(kind, fn).
const HANDLERS = {
  state: (m) => applyState(m),
  run: (m) => applyRun(m),
  telemetry: (m) => playTelemetry(m),
  timing: (m) => applyTiming(m),
  monitor: (m) => appendMonitor(m.lines, m.source),
  alarm: (m) => {
    // A started run missing a layer (`started`): the banner (the run message says the same). A
    // refused run (its message says why it was not started): the alarm bar.
    if (m.kind === "confinement" && m.started) showConfinement(m.run_id, m.missing);
    else if (m.kind === "confinement" && m.started === false) {
      showAlarm({ ...m, message: "the controller was not started: " + m.message });  // as POST /api/runs says
    } else showAlarm(m);
  },
  build: (m) => { if (m.line) appendMonitor([{ text: m.line }], "stdout"); else loadBuilds().catch(() => {}); },
  ack: (m) => {
    if (m.accepted === false) applyState({ ...xrf.state });
    if (m.setpoint) xrf.appliedSetpoint = { ...m.setpoint };
  },
  error: (m) => {
    appendMonitor([{ text: "! " + m.error }], "error");
    if (m.request === "setpoint") {  // refused (no bench, a bad value): back to what is applied
      showSetpoints(xrf.appliedSetpoint);
      if (xrf.notice) xrf.notice("Setpoint not applied: " + m.error, 6000);
    }
  },
  // The bench lease (pages/lease.js, setpoint controls), the ROS 2 bridge (pages/ros.js) and the
  // self-check (pages/selfcheck.js) are their pages' listeners; the Bench page needs nothing more.
  lease: () => {},
  ros: () => {},
  selfcheck: () => {},
  pong: () => {},
};
xrf.handlers = HANDLERS;

// A hidden tab (another tab in front, the window minimised) takes no telemetry: nobody sees its
// plots, and each message costs the appliance a wake-up and a socket write (issue 30 item 4: a
// lab's background tabs). It keeps every other topic (state, alarms, the lease, the console), and
// telemetry comes back when it is shown again (the plots then have a gap). A page may keep it
// while hidden (xrf.keepTelemetry: the Watch page with a trigger armed, which must not miss
// its crossing). Until a tab is hidden the appliance's default holds: every topic.
const REPLIES = new Set(["ack", "pong", "error"]);
xrf.keepTelemetry = [];  // functions: true while a page needs telemetry though the tab is hidden
xrf.telemetryWanted = true;
function followVisibility() {
  const want = document.visibilityState !== "hidden" || xrf.keepTelemetry.some((fn) => fn());
  if (want === xrf.telemetryWanted) return;
  xrf.telemetryWanted = want;
  const topics = Object.keys(HANDLERS).filter((k) => !REPLIES.has(k) && (want || k !== "telemetry"));
  xrf.send({ type: "subscribe", topics });
}
xrf.followVisibility = followVisibility;
document.addEventListener("visibilitychange", followVisibility);

function connect() {
  const ws = new WebSocket((location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/ws");
  xrf.ws = ws;
  ws.onopen = () => {
    $("conn").textContent = "connected"; $("conn").className = "badge ok";
    xrf.telemetryWanted = true;  // a new connection takes every topic
    followVisibility();
  };
  ws.onclose = () => {
    $("conn").textContent = "disconnected — retrying"; $("conn").className = "badge bad";
    // A refused handshake or a session that ended: back to the login page, else retry.
    setTimeout(() => fetch("/api/me").then((r) => (r.status === 401 ? xrf.toLogin() : connect())).catch(connect), 1000);
  };
  ws.onmessage = (ev) => {
    const m = JSON.parse(ev.data);
    for (const fn of (xrf.listeners[m.type] || []).concat(xrf.listeners["*"] || [])) {
      try { fn(m); } catch (e) { console.error(e); }
    }
    const handle = HANDLERS[m.type];
    if (handle) handle(m);
    else console.warn("message of a kind the dashboard does not know:", m.type);
  };
}

// ---- keys -----------------------------------------------------------------------------------

function onKey(ev) {
  if (ev.key === "Escape") {  // works everywhere, even while typing in a setpoint box
    ev.preventDefault();
    emergencyStop();
    return;
  }
  const typing = ["INPUT", "SELECT", "TEXTAREA"].includes(document.activeElement && document.activeElement.tagName);
  if (typing || ev.ctrlKey || ev.metaKey || ev.altKey) return;
  const cmd = { p: "pause", s: "start", i: "initialise" }[ev.key.toLowerCase()];
  const button = cmd && document.querySelector(`#commands button[data-cmd="${cmd}"]`);
  if (button && !button.disabled) sendCommand(cmd);  // the button's own rule (applyState)
}

// Esc inside an embedded frame (the 3D view, the rerun viewer: same origin, through the
// appliance) never reached this page's listener: the frame's own window gets the key (issue 19).
// Every iframe of the page, now or later, gets the same Esc handler on each document it loads.
function frameKey(ev) {
  if (ev.key !== "Escape") return;  // only Esc: letters typed into a viewer are the viewer's
  ev.preventDefault();
  emergencyStop();
}

function hookFrame(frame) {
  const hook = () => {
    try {
      const w = frame.contentWindow;
      if (w && !w.__xrfEsc) { w.__xrfEsc = true; w.addEventListener("keydown", frameKey, true); }
    } catch (e) { /* another origin: not ours to listen to */ }
  };
  if (frame.__xrfHooked) return;
  frame.__xrfHooked = true;
  frame.addEventListener("load", hook);
  hook();
}
xrf.hookFrame = hookFrame;

function watchFrames() {
  document.querySelectorAll("iframe").forEach(hookFrame);
  new MutationObserver((changes) => {
    for (const c of changes) for (const n of c.addedNodes) {
      if (n.nodeType !== 1) continue;
      if (n.tagName === "IFRAME") hookFrame(n);
      else n.querySelectorAll && n.querySelectorAll("iframe").forEach(hookFrame);
    }
  }).observe(document.body, { childList: true, subtree: true });
}

// ---- start ----------------------------------------------------------------------------------

function init() {
  xrf.pages.bench = { id: "bench", title: "Bench", order: 0, el: $("page-bench"), ready: true };
  xrf.started = true;
  renderNav();
  window.addEventListener("hashchange", route);
  route();
  xrf.meReady.then(() => { renderNav(); route(); });  // the tabs this user may use
  applyState(xrf.state);
  xrf.machineReady = fetch("/api/state-machine").then((r) => r.json()).then((machine) => {
    xrf.machine = machine;
    drawStateMachine(machine);
    drawCommands(machine);
    applyState(xrf.state);  // the state may have come first: mark its node and edges now
  });
  $("btn-estop").addEventListener("click", emergencyStop);
  $("btn-start-run").addEventListener("click", startRun);
  $("btn-end-run").addEventListener("click", endRun);
  $("btn-clear").addEventListener("click", () => { $("monitor").textContent = ""; monitorFollow = true; });
  $("monitor").addEventListener("scroll", monitorScrolled);
  watchFrames();
  let holder;  // the bench's holder's id as last seen (undefined: not seen yet)
  xrf.on("lease", (m) => {
    setTimeout(updateSetpointsEnabled);  // after lease.js has the new holder
    // A new holder (a take-over, a hand-over, a release) starts afresh: the timing alarm was the
    // previous holder's. A crash or a sandbox alarm stays: it is about the bench itself.
    const now = m.holder ? m.holder.id : null;
    if (holder !== undefined && now !== holder) clearAlarm("deadline_miss");
    holder = now;
  });
  $("alarm-close").addEventListener("click", () => $("alarm").classList.add("hidden"));
  $("rejected").addEventListener("click", () => { xrf.dismissedReject = xrf.state.rejected && xrf.state.rejected.ticket; $("rejected").classList.add("hidden"); });
  document.addEventListener("keydown", onKey, true);
  window.addEventListener("resize", () => { clearTimeout(init.t); init.t = setTimeout(resizePlots, 150); });
  loadBench().then(() => loadBuilds()).catch(() => {});
  loadPlants().catch(() => {});
  loadRuns().catch(() => {});
  buildPlots([]);
  connect();
  requestAnimationFrame(redraw);
}

document.addEventListener("DOMContentLoaded", init);
