// Users page (educators): accounts (create, disable, reset, role), CSV class list import and
// the audit trail with filters and CSV export. API: appliance/xrflab/server/http/accounts.py.
"use strict";

(function () {
  const $ = (id) => document.getElementById(id);
  const esc = xrf.esc;  // frontend/lib.js
  const when = (t) => (t ? new Date(t * 1000).toLocaleString() : "–");

  const HTML = `<div class="page-body users">
    <section class="panel">
      <h2>Accounts</h2>
      <form id="u-create" class="row">
        <input id="u-name" placeholder="username" required autocapitalize="none" spellcheck="false">
        <input id="u-full" placeholder="full name">
        <select id="u-role"></select>
        <input id="u-email" placeholder="email (optional)" type="email">
        <button id="u-create-btn" type="submit">Create</button>
      </form>
      <div id="u-result" class="muted"></div>
      <table><thead><tr><th>username</th><th>name</th><th>role</th><th>status</th><th>last login</th><th></th></tr></thead>
        <tbody id="u-body"></tbody></table>
    </section>
    <section class="panel">
      <h2>Import a class list <span class="muted small">CSV: username,full name,role[,email]</span></h2>
      <div class="row"><input type="file" id="u-csv-file" accept=".csv,text/csv,text/plain"></div>
      <textarea id="u-csv" placeholder="s1234567,Ada Lovelace,student,ada@example.edu"></textarea>
      <div class="row"><button id="u-import" type="button">Import</button><a id="u-import-dl" class="hidden" download="one-time-passwords.csv">download the one-time passwords</a></div>
      <div id="u-import-result"></div>
    </section>
    <section class="panel">
      <h2>Audit trail</h2>
      <form id="a-filter" class="row">
        <input id="a-user" placeholder="username">
        <input id="a-action" placeholder="action (e.g. lease, command, user)">
        <label class="small">since <input id="a-since" type="datetime-local"></label>
        <button type="submit">Show</button>
        <a id="a-export" href="/api/audit.csv" download>export CSV</a>
      </form>
      <table><thead><tr><th>time</th><th>user</th><th>action</th><th>detail</th><th>address</th></tr></thead>
        <tbody id="a-body"></tbody></table>
    </section>
  </div>`;

  // The roles and the one a new account gets first come from the appliance (GET /api/roles,
  // server/security/roles.py): this page has no list of its own.
  let rolesReady = null;
  const loadRoles = () => (rolesReady = rolesReady || xrf.api("GET", "/api/roles").catch((e) => { rolesReady = null; throw e; }));
  const roleOptions = (roles, chosen) => roles.roles.map((r) => `<option${r.name === chosen ? " selected" : ""}>${esc(r.name)}</option>`).join("");

  async function loadUsers() {
    const roles = await loadRoles();
    if (!$("u-role").options.length) $("u-role").innerHTML = roleOptions(roles, roles.default);
    const users = await xrf.api("GET", "/api/users");
    const body = $("u-body");
    body.innerHTML = "";
    for (const u of users) {
      const tr = document.createElement("tr");
      tr.id = "user-" + u.username;
      if (u.disabled) tr.className = "disabled";
      tr.innerHTML = `<td>${esc(u.username)}</td><td>${esc(u.full_name)}</td>
        <td><select data-act="role">${roleOptions(roles, u.role)}</select></td>
        <td>${u.disabled ? "disabled" : u.must_change ? "one-time password" : "active"}</td><td>${when(u.last_login)}</td>
        <td><button type="button" class="secondary" data-act="reset">Reset password</button>
            <button type="button" class="secondary" data-act="toggle">${u.disabled ? "Enable" : "Disable"}</button></td>`;
      tr.querySelector("[data-act=reset]").addEventListener("click", () => reset(u));
      tr.querySelector("[data-act=toggle]").addEventListener("click", () => change(u, { disabled: !u.disabled }));
      tr.querySelector("[data-act=role]").addEventListener("change", (ev) => change(u, { role: ev.target.value }));
      body.append(tr);
    }
  }

  function showSecret(username, password) {
    $("u-result").innerHTML = `One-time password for <b>${esc(username)}</b>: <span class="secret" id="u-secret">${esc(password)}</span> — shown once; they choose their own at the first login.`;
  }

  async function change(u, patch) {
    try { await xrf.api("PATCH", `/api/users/${u.id}`, patch); } catch (e) { $("u-result").textContent = e.message; }
    loadUsers().catch(() => {});
  }

  async function reset(u) {
    if (!confirm(`Give ${u.username} a new one-time password? Their sessions and CLI token end.`)) return;
    try { const r = await xrf.api("POST", `/api/users/${u.id}/reset`); showSecret(r.user.username, r.password); }
    catch (e) { $("u-result").textContent = e.message; }
    loadUsers().catch(() => {});
  }

  async function create(ev) {
    ev.preventDefault();
    try {
      const r = await xrf.api("POST", "/api/users", { username: $("u-name").value.trim(), full_name: $("u-full").value.trim(),
        role: $("u-role").value, email: $("u-email").value.trim() });
      showSecret(r.user.username, r.password);
      $("u-create").reset();
    } catch (e) { $("u-result").textContent = e.message; }
    loadUsers().catch(() => {});
  }

  async function importList() {
    const out = $("u-import-result");
    out.textContent = "";
    $("u-import-dl").classList.add("hidden");
    try {
      const r = await xrf.api("POST", "/api/users/import", { csv: $("u-csv").value });
      const rows = r.created.map((c) => `<tr><td>${esc(c.user.username)}</td><td>${esc(c.user.full_name)}</td><td>${esc(c.user.role)}</td><td class="secret">${esc(c.password)}</td></tr>`);
      out.innerHTML = `<p>${r.created.length} accounts created. The one-time passwords are shown only now:</p><table><tbody>${rows.join("")}</tbody></table>`;
      const csv = "username,full name,role,one-time password\n" + r.created.map((c) => [c.user.username, c.user.full_name, c.user.role, c.password].map((v) => `"${String(v).replace(/"/g, '""')}"`).join(",")).join("\n");
      const dl = $("u-import-dl");
      dl.href = URL.createObjectURL(new Blob([csv], { type: "text/csv" }));
      dl.classList.remove("hidden");
      $("u-csv").value = "";
    } catch (e) { out.textContent = "Nothing imported: " + e.message; }
    loadUsers().catch(() => {});
  }

  function auditQuery() {
    const q = new URLSearchParams();
    if ($("a-user").value.trim()) q.set("username", $("a-user").value.trim());
    if ($("a-action").value.trim()) q.set("action", $("a-action").value.trim());
    if ($("a-since").value) q.set("since", String(new Date($("a-since").value).getTime() / 1000));
    return q;
  }

  async function loadAudit(ev) {
    if (ev) ev.preventDefault();
    const q = auditQuery();
    $("a-export").href = "/api/audit.csv?" + q.toString();
    q.set("limit", "300");
    const rows = await xrf.api("GET", "/api/audit?" + q.toString());
    $("a-body").innerHTML = rows.map((r) => `<tr><td>${when(r.t)}</td><td>${esc(r.username || "—")}</td><td>${esc(r.action)}</td>
      <td class="detail">${esc(JSON.stringify(r.detail))}</td><td>${esc(r.address)}</td></tr>`).join("");
  }

  xrf.meReady.then((me) => {
    if (!xrf.may("educator")) return;
    xrf.addPage({
      id: "users", title: "Users", order: 90,
      init(el) {
        el.innerHTML = HTML;
        $("u-create").addEventListener("submit", create);
        $("u-import").addEventListener("click", importList);
        $("u-csv-file").addEventListener("change", async (ev) => { const f = ev.target.files[0]; if (f) $("u-csv").value = await f.text(); });
        $("a-filter").addEventListener("submit", loadAudit);
      },
      show() { loadUsers().catch(() => {}); loadAudit().catch(() => {}); },
    });
  });
})();
