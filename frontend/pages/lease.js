// The bench lease in the header (who drives, the queue, Take / Release / Queue), the user menu
// (password change, log out) and the STOP rule for people who do not hold the bench.
// Server side: appliance/xrflab/server/security/lease.py; the rule: docs/educators/accounts.md.
"use strict";

(function () {
  const $ = (id) => document.getElementById(id);
  const L = { lease: null };
  xrf.lease = L;

  function el(tag, attrs, text) {
    const e = document.createElement(tag);
    Object.entries(attrs || {}).forEach(([k, v]) => e.setAttribute(k, v));
    if (text !== undefined) e.textContent = text;
    return e;
  }

  // ---- header widgets --------------------------------------------------------------------------
  const bar = document.querySelector(".topbar");
  const spacer = bar.querySelector(".spacer");
  const box = el("div", { id: "lease", class: "lease", title: "the bench lease: who may drive" });
  box.append(el("span", { class: "muted" }, "bench:"), el("span", { id: "lease-holder", class: "who" }, "…"),
    el("span", { id: "lease-queue", class: "queue" }, ""));
  const buttons = {
    take: el("button", { id: "btn-lease-take", type: "button" }, "Take"),
    takeover: el("button", { id: "btn-lease-takeover", type: "button", title: "educators: take the bench from its holder" }, "Take over"),
    release: el("button", { id: "btn-lease-release", type: "button", class: "secondary" }, "Release"),
    queue: el("button", { id: "btn-lease-queue", type: "button" }, "Queue"),
    leave: el("button", { id: "btn-lease-leave", type: "button", class: "secondary" }, "Leave queue"),
  };
  Object.values(buttons).forEach((b) => { b.classList.add("hidden"); box.append(b); });
  // In the status strip (index.html), beside the state and the alarm: one line that never moves.
  const strip = $("status-strip");
  if (strip) strip.append(box); else bar.insertBefore(box, spacer);

  const me = el("div", { id: "me", class: "me" });
  const meName = el("span", { id: "me-name" }, "");
  const pwBtn = el("button", { id: "btn-password", type: "button" }, "Password");
  const outBtn = el("button", { id: "btn-logout", type: "button" }, "Log out");
  me.append(meName, pwBtn, outBtn);
  bar.insertBefore(me, $("btn-estop"));

  const notice = el("div", { id: "notice", class: "notice hidden", role: "alert" });
  const noticeText = el("span", { id: "notice-text" });
  const noticeClose = el("button", { "aria-label": "dismiss", type: "button" }, "×");
  notice.append(noticeText, noticeClose);
  noticeClose.addEventListener("click", () => notice.classList.add("hidden"));
  bar.append(notice);  // floats under the sticky bar (style.css): shown or hidden, the page stays put

  function say(text, ms) {
    noticeText.textContent = text;
    notice.classList.remove("hidden");
    clearTimeout(say.t);
    if (ms) say.t = setTimeout(() => notice.classList.add("hidden"), ms);
  }
  xrf.notice = say;

  // ---- state -----------------------------------------------------------------------------------
  const mine = () => !!(xrf.me && L.lease && L.lease.holder && L.lease.holder.id === xrf.me.id);
  const queued = () => !!(xrf.me && L.lease && L.lease.queue.some((u) => u.id === xrf.me.id));
  xrf.holdsBench = mine;
  xrf.mayDrive = () => xrf.may("educator") || (xrf.may("drive") && mine());

  // Why this user cannot use a command button now ("" when they can): the one rule every button
  // of the dashboard asks (the Bench's commands, Start/End run, STOP), the same as the appliance's
  // own check (server/http/runs.py): a safe command (stop, pause: the state machine's `safe`)
  // needs the "stop" permission, everything else "drive" with the bench lease (educators always).
  // Permissions are /api/me's `perms` (server/security/roles.py), never a role's name.
  const WATCH_ONLY = "you may watch only: ask the student at the bench or an educator";
  xrf.driveBlock = function () {
    if (!xrf.me) return "…";
    if (xrf.mayDrive()) return "";
    if (!xrf.may("drive")) return WATCH_ONLY;
    const l = L.lease;
    return l && l.holder ? `${l.holder.username} holds the bench: queue for it to drive` : "take the bench to drive";
  };
  xrf.commandBlock = function (safe) {
    // Stopping is never held back while the user is still unknown (the first moments of the page).
    if (!xrf.me) return safe ? "" : "…";
    if (safe) return xrf.may("stop") ? "" : WATCH_ONLY;
    return xrf.driveBlock();
  };

  function render() {
    const l = L.lease;
    const m = xrf.me;
    if (!l || !m) return;
    const holder = $("lease-holder");
    holder.textContent = l.holder ? (mine() ? "you" : l.holder.username) : "free";
    holder.classList.toggle("mine", mine());
    holder.title = l.holder ? `held by ${l.holder.username} (${l.holder.role}) since ${new Date(l.holder.since * 1000).toLocaleTimeString()}` : "nobody holds the bench";
    $("lease-queue").textContent = l.queue.length ? "queue: " + l.queue.map((u) => u.username).join(", ") : "";
    const canLease = xrf.may("lease");
    const show = {
      take: canLease && !l.holder,
      takeover: xrf.may("educator") && l.holder && !mine(),
      release: l.holder && (mine() || xrf.may("educator")),
      queue: canLease && !xrf.may("educator") && l.holder && !mine() && !queued(),
      leave: queued(),
    };
    Object.entries(buttons).forEach(([k, b]) => b.classList.toggle("hidden", !show[k]));
    document.body.dataset.drive = xrf.mayDrive() ? "yes" : "no";
    if (xrf.permsChanged) xrf.permsChanged();  // every button's enabled state and reason (app.js)
  }

  function onLease(m) {
    const before = L.lease;
    L.lease = m;
    render();
    const meId = xrf.me && xrf.me.id;
    if (!meId || !before) return;
    const prev = m.previous && m.previous.id === meId;
    if (m.event === "takeover" && prev) say(`${m.holder.username} (educator) took over the bench; you are watching now` + (queued() ? ", first in the queue: it comes back to you when they release it." : "."));
    else if (m.event === "intervention" && mine() && m.by && m.by.id !== meId) say(`${m.by.username} ${m.command === "pause" ? "paused" : "stopped"} your run (anyone at the bench may pause or stop it).`, 10000);
    else if (m.event === "handover" && m.holder && m.holder.id === meId) say("The bench is yours now: you can drive.", 8000);
    else if (m.event === "released" && prev && m.reason === "idle") say("The bench was released: nothing was driven for a while.", 10000);
    else if ((m.event === "released" || m.event === "handover") && prev && m.by && m.by.id !== meId) say(`${m.by.username} released the bench.`, 8000);
  }
  xrf.on("lease", onLease);

  async function act(path) {
    try { onLease(await xrf.api("POST", "/api/lease/" + path)); } catch (e) { say(e.message, 6000); }
  }
  buttons.take.addEventListener("click", () => act("take"));
  buttons.takeover.addEventListener("click", () => act("take"));
  buttons.release.addEventListener("click", () => act("release"));
  buttons.queue.addEventListener("click", () => act("queue"));
  buttons.leave.addEventListener("click", () => act("leave"));

  // ---- the STOP rule -----------------------------------------------------------------------------
  // Stopping is always safe: every student and educator may stop or pause a running controller,
  // holder or not. Ending a run (STOP outside RUN/PAUSED) is driving: the holder or an educator.
  // Observers only watch.
  xrf.stopBlocked = function () {
    const m = xrf.me;
    if (!m) return false;
    if (!xrf.may("stop")) {
      say("Observers watch only: ask the student at the bench or an educator to stop it.", 6000);
      return true;
    }
    if (xrf.mayDrive()) return false;
    const s = xrf.state;
    if (s.active && s.allowed.includes("stop")) return false;  // RUN, PAUSED: stop is safe, for everyone
    if (xrf.run && xrf.run.active) {
      const who = L.lease && L.lease.holder ? L.lease.holder.username : "nobody";
      say(`You do not hold the bench (${who} does): STOP stops a running or paused controller for anyone, but only the holder or an educator ends the run.`, 8000);
      return true;
    }
    return false;
  };

  // ---- user menu ---------------------------------------------------------------------------------
  const dlg = el("dialog", { id: "pw-dialog", class: "pw" });
  dlg.innerHTML = `<form method="dialog" id="pw-form">
    <h2>Change password</h2>
    <label for="pw-current">Current password</label><input id="pw-current" type="password" autocomplete="current-password" required>
    <label for="pw-new">New password (at least 10 characters)</label><input id="pw-new" type="password" autocomplete="new-password" minlength="10" required>
    <label for="pw-again">New password again</label><input id="pw-again" type="password" autocomplete="new-password" minlength="10" required>
    <div class="form-error" id="pw-error" role="alert"></div>
    <div class="row"><button id="pw-save" type="submit">Save</button><button id="pw-cancel" type="button" class="secondary">Cancel</button></div>
  </form>`;
  document.body.append(dlg);
  pwBtn.addEventListener("click", () => { $("pw-form").reset(); $("pw-error").textContent = ""; dlg.showModal(); });
  $("pw-cancel").addEventListener("click", () => dlg.close());
  $("pw-form").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    if ($("pw-new").value !== $("pw-again").value) { $("pw-error").textContent = "the two new passwords differ"; return; }
    try {
      await xrf.api("POST", "/api/auth/password", { current: $("pw-current").value, new: $("pw-new").value });
      dlg.close();
      say("Password changed. Other sessions and your CLI token were logged out.", 6000);
      if (xrf.ws) xrf.ws.close();  // reconnects with the new session
    } catch (e) { $("pw-error").textContent = e.message; }
  });
  outBtn.addEventListener("click", async () => {
    try { await xrf.api("POST", "/api/auth/logout"); } catch (e) { /* gone already */ }
    location.href = "/login";
  });

  xrf.meReady.then((m) => {
    meName.textContent = `${m.username} · ${m.role}`;
    meName.title = m.full_name || m.username;
    render();
    xrf.api("GET", "/api/lease").then((l) => { if (!L.lease) onLease(l); else render(); }).catch(() => {});
  });
})();
