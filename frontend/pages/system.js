// System page: the `xrf doctor` checks (ok / warning / failure with the exact fix), refreshed on
// demand, and facts about the appliance. API: appliance/xrflab/server/http/system.py.
"use strict";

(function () {
  const $ = (id) => document.getElementById(id);
  const esc = xrf.esc;  // frontend/lib.js
  const LABEL = { ok: "ok", warning: "warning", failure: "FAILURE", "not checked": "not checked" };
  const CLS = { ok: "ok", warning: "warning", failure: "failure", "not checked": "skipped" };

  const HTML = `<div class="page-body system">
    <section class="panel">
      <h2>Appliance <span class="spacer"></span><button id="sys-facts-refresh" type="button" class="secondary small">refresh</button></h2>
      <dl class="facts" id="sys-facts"><dt>…</dt><dd></dd></dl>
    </section>
    <section class="panel">
      <h2>Doctor <span class="muted small" id="sys-doctor-when"></span><span class="spacer"></span>
        <button id="sys-refresh" type="button">Run the checks again</button></h2>
      <p class="muted small">The same checks as <code>xrf doctor</code> in a terminal: is this machine ready to be a
        real-time bench, and which run sandbox confines students' controllers (each protection layer holding or
        missing)? Anything not ok says exactly what to do (docs/install/doctor.md explains each message).</p>
      <div id="sys-counts" class="small"></div>
      <table class="sc-table"><thead><tr><th>check</th><th>status</th><th>detail and fix</th></tr></thead>
        <tbody id="sys-checks"><tr><td colspan="3" class="muted">checking…</td></tr></tbody></table>
    </section>
  </div>`;

  function size(bytes) {
    if (bytes == null) return "–";
    const gb = bytes / 1e9;
    return gb >= 1 ? gb.toFixed(1) + " GB" : (bytes / 1e6).toFixed(0) + " MB";
  }

  function duration(s) {
    if (s == null) return "–";
    const d = Math.floor(s / 86400), h = Math.floor((s % 86400) / 3600), m = Math.floor((s % 3600) / 60);
    return (d ? d + " d " : "") + (d || h ? h + " h " : "") + m + " min";
  }

  async function loadFacts() {
    const f = await xrf.api("GET", "/api/system");
    const b = f.bench || {};
    const rows = [
      ["version", `XRF Lab ${f.version}`],
      ["host", `${f.hostname} · ${f.platform} · Python ${f.python}`],
      ["data folder", f.data_dir],
      ["disk free", f.disk ? `${size(f.disk.free)} of ${size(f.disk.total)}` : "–"],
      ["appliance uptime", duration(f.uptime_s)],
      ["machine uptime", duration(f.host_uptime_s)],
      ["bench", b.mode === "sim" ? `simulated ico board + ${b.sim} plant` : `real bench (${b.spi_device})`],
      ["backend", b.backend],
      ["transport", b.transport],
      ["run", f.run_active ? "a loop run is active" : "no run"],
    ];
    $("sys-facts").innerHTML = rows.map(([k, v]) => `<dt>${esc(k)}</dt><dd data-fact="${esc(k)}">${esc(v)}</dd>`).join("");
  }

  // The parts of a check (the run sandbox's protection layers): each holding or missing, and why.
  function layers(items) {
    if (!items || !items.length) return "";
    return `<ul class="sys-layers">${items.map((i) => `<li data-layer="${esc(i.name)}" data-status="${esc(i.status)}">` +
      `<code>${esc(i.name)}</code> ${i.status === "ok" ? '<span class="ok">holds</span>'
        : `<b class="bad">MISSING</b>: ${esc(i.detail)}`}</li>`).join("")}</ul>`;
  }

  async function loadDoctor() {
    const btn = $("sys-refresh");
    btn.disabled = true;
    $("sys-doctor-when").textContent = "checking…";
    try {
      const d = await xrf.api("GET", "/api/system/doctor");
      const body = $("sys-checks");
      body.innerHTML = "";
      for (const c of d.checks) {
        const tr = document.createElement("tr");
        tr.dataset.id = c.id;
        tr.dataset.status = c.status;
        tr.className = "st-" + (c.status === "failure" ? "fail" : c.status === "warning" ? "warn" : c.status === "ok" ? "pass" : "skipped");
        tr.innerHTML = `<td>${esc(c.title)}<div class="muted small"><code>${esc(c.id)}</code></div></td>
          <td><span class="verdict v-${CLS[c.status] || "skipped"}">${esc(LABEL[c.status] || c.status)}</span></td>
          <td>${esc(c.detail)}${layers(c.items)}${c.fix && c.status !== "ok" ? `<div class="fix"><b>fix:</b> <code>${esc(c.fix)}</code></div>` : ""}</td>`;
        body.append(tr);
      }
      const n = d.counts;
      $("sys-counts").innerHTML = `${n.ok} ok, ${n.warning} warning(s), <span class="${n.failure ? "bad" : ""}">${n.failure} failure(s)</span>, ${n["not checked"]} not checked` +
        (d.live ? "" : " · the FPGA was not probed (the bench is in use)");
      $("sys-doctor-when").textContent = "checked " + new Date(d.checked_at * 1000).toLocaleTimeString() + ` (${d.duration_s.toFixed(1)} s)`;
    } catch (e) {
      $("sys-doctor-when").textContent = e.message;
    } finally {
      btn.disabled = false;
    }
  }

  xrf.addPage({
    id: "system", title: "System", order: 80,
    init(el) {
      el.innerHTML = HTML;
      $("sys-refresh").addEventListener("click", () => { loadDoctor(); loadFacts().catch(() => {}); });
      $("sys-facts-refresh").addEventListener("click", () => loadFacts().catch(() => {}));
      loadDoctor();
    },
    show() { loadFacts().catch((e) => { $("sys-facts").innerHTML = `<dt>error</dt><dd>${esc(e.message)}</dd>`; }); },
  });
})();
