// telesurg web surgeon console: state view, controls and the browser masters.
// The page is a master device: its pose (position in m, orientation quaternion x y z w in the
// master frame) and clutch go to the console process over /ws as "sample" frames, each stamped
// with the browser's own clock (performance.timeOrigin + event time, ms since the epoch).
"use strict";

const $ = (s) => document.querySelector(s);
const MASTER = new URLSearchParams(location.search).get("master") || "m1";
const SEND_MS = 10; // a sample every 10 ms (100 Hz) and at once on every input event

// ------------------------------------------------------------------ master state
const master = {
  p: [0, 0, 0], // m, master frame: x right, y up the screen, z out of the screen
  q: [0, 0, 0, 1], // x y z w
  key: false, // clutch key (Space) held
  pedal: false, // on-screen pedal held
  pad: false, // gamepad clutch trigger
  device: "mouse",
  hidden: false,
};
let mmPerPx = 0.2;
function clutch() { return master.key || master.pedal || master.pad; }

function qmul(a, b) {
  const [ax, ay, az, aw] = a, [bx, by, bz, bw] = b;
  return [aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
          aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz];
}
function qaxis(axis, ang) {
  const s = Math.sin(ang / 2);
  return [axis[0] * s, axis[1] * s, axis[2] * s, Math.cos(ang / 2)];
}
function qnorm(q) { const n = Math.hypot(...q) || 1; return q.map((v) => v / n); }
// W3C deviceorientation: R = Rz(alpha) · Rx(beta) · Ry(gamma), degrees
function qEuler(alpha, beta, gamma) {
  const d = Math.PI / 180;
  return qnorm(qmul(qmul(qaxis([0, 0, 1], alpha * d), qaxis([1, 0, 0], beta * d)), qaxis([0, 1, 0], gamma * d)));
}
const clampP = (v) => Math.max(-0.9, Math.min(0.9, v));
function move(dx, dy, dz) { // m
  master.p = [clampP(master.p[0] + dx), clampP(master.p[1] + dy), clampP(master.p[2] + dz)];
}

// ------------------------------------------------------------------ socket
// This tab's page id (kept across reloads: a reload keeps control); the server's session cookie
// (HttpOnly, set by /login) authenticates the socket.
const PAGE = sessionStorage.getItem("telesurg-page") ||
  [...crypto.getRandomValues(new Uint8Array(8))].map((b) => b.toString(16).padStart(2, "0")).join("");
sessionStorage.setItem("telesurg-page", PAGE);
let ws = null, wsOpen = false, refusedWhy = "";
window.consoleRole = null; // the last control message: {role: controller | viewer, holder, request}
window.consoleState = null; // the last state the server pushed (for tests and debugging)
window.consoleNotices = [];
function connect() {
  ws = new WebSocket((location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/ws?page=" + PAGE);
  ws.onopen = () => { wsOpen = true; refusedWhy = ""; master.key = master.pedal = master.pad = false; setLink(); };
  ws.onclose = (ev) => {
    wsOpen = false;
    if (ev.code >= 4400 && ev.code < 4500) { // refused by the door (not logged in, session expired)
      refusedWhy = ev.reason || "refused";
      logLine("error", "console: " + refusedWhy);
      setLink();
      setTimeout(connect, 10000);
      return;
    }
    setLink(); setTimeout(connect, 1000);
  };
  ws.onerror = () => {};
  ws.onmessage = (ev) => {
    const m = JSON.parse(ev.data);
    if (m.type === "state") render(m);
    else if (m.type === "overlay") overlay(m);
    else if (m.type === "notice") logLine("info", m.text);
    else if (m.type === "refused") logLine("error", "refused by the console: " + m.text);
    else if (m.type === "control") setRole(m);
    else if (m.type === "invite") {
      $("#invite-url").textContent = location.origin + m.url; $("#invite-s").textContent = m.valid_s;
      $("#invite-box").hidden = false;
    }
  };
}
function send(obj) { if (wsOpen) ws.send(JSON.stringify(obj)); }
let masterOn = false; // this console publishes browser master MASTER (web.master_service set)
let inControl = false; // this page controls the master (one page per master; the others view)
function setRole(m) {
  const was = inControl;
  window.consoleRole = m;
  inControl = m.role === "controller";
  const el = $("#control");
  el.textContent = inControl ? "this page is in control" :
    "VIEWER — " + (m.holder ? "page " + m.holder + " is in control" : "nobody is in control") +
    (m.request === m.page ? " (asked for control)" : "");
  el.className = inControl ? "ok" : "viewer";
  $("#take").hidden = inControl;
  $("#release").hidden = !inControl;
  $("#handover").hidden = !(inControl && m.request);
  if (inControl && m.request) $("#handover-text").textContent = "Page " + m.request + " asks for control of the master. Hand it over?";
  if (was && !inControl) { master.key = master.pedal = master.pad = false; pedal.classList.remove("on"); logLine("warning", "control of the master went to page " + (m.holder || "—") + ": this page is now a viewer"); }
  if (!was && inControl) logLine("info", "this page is in control of the master");
}
function sendSample(tMs) {
  if (!wsOpen || master.hidden || !masterOn || !inControl) return;
  send({ type: "sample", master: MASTER, t: tMs, p: master.p, q: master.q, clutch: clutch(),
         present: true, device: master.device });
}
const now = () => performance.timeOrigin + performance.now();
const evTime = (ev) => performance.timeOrigin + ev.timeStamp;
function setLink() {
  const l = $("#link");
  l.textContent = wsOpen ? "console connected" : refusedWhy ? "console " + refusedWhy : "console link lost — reconnecting";
  l.className = wsOpen ? "ok" : "bad";
  if (!wsOpen) setBanner("none", "NO LINK", "the page lost the console: the state shown is old");
}

// The safety banner (always on screen): the worst watchdog state of the arms and its causes.
const RANK = { OK: 1, DEGRADED: 2, HOLD: 3, ESTOP: 4 };
function setBanner(cls, state, cause) {
  const b = $("#banner");
  b.className = "b-" + cls;
  $("#banner-state").textContent = state;
  $("#banner-cause").textContent = cause;
  b.title = state + " " + cause;
}
function banner(m) {
  let worst = null;
  for (const a of m.arms) {
    const s = a.safety;
    const state = !s ? "NO STATE" : s.stale ? "STALE" : s.state;
    const rank = !s || s.stale ? 3.5 : RANK[s.state] || 3.5;
    const cause = !s ? "no watchdog state yet" : s.stale ? "the watchdog's state is old" : s.causes.join("; ");
    if (!worst || rank > worst.rank) worst = { rank, state, cause, arm: a.arm };
  }
  if (!worst) { setBanner("none", "NO ARMS", "the site reports no arm"); return; }
  const cls = RANK[worst.state] ? worst.state : "none";
  const who = m.arms.length > 1 ? worst.arm + ": " : "";
  setBanner(cls, worst.state, worst.cause ? "— " + who + worst.cause : m.arms.length > 1 ? "— every arm" : "");
}

// ------------------------------------------------------------------ mouse and keyboard
const view = $("#view");
let drag = null;
view.addEventListener("mousedown", (ev) => { drag = { x: ev.clientX, y: ev.clientY }; view.focus(); ev.preventDefault(); });
window.addEventListener("mouseup", () => { drag = null; });
window.addEventListener("mousemove", (ev) => {
  if (!drag) return;
  const dx = ev.clientX - drag.x, dy = ev.clientY - drag.y;
  drag = { x: ev.clientX, y: ev.clientY };
  master.device = "mouse";
  if (ev.shiftKey) { // rotation: horizontal drag about the master's y axis, vertical about x
    master.q = qnorm(qmul(qmul(qaxis([0, 1, 0], dx * 0.005), qaxis([1, 0, 0], dy * 0.005)), master.q));
  } else {
    move(dx * mmPerPx / 1000, -dy * mmPerPx / 1000, 0);
  }
  sendSample(evTime(ev));
});
view.addEventListener("wheel", (ev) => {
  ev.preventDefault();
  move(0, 0, -Math.sign(ev.deltaY) * 0.002);
  sendSample(evTime(ev));
}, { passive: false });
const STEP = { ArrowLeft: [-1, 0, 0], ArrowRight: [1, 0, 0], ArrowUp: [0, 1, 0], ArrowDown: [0, -1, 0], PageUp: [0, 0, 1], PageDown: [0, 0, -1] };
window.addEventListener("keydown", (ev) => {
  if (ev.target && ev.target.tagName === "INPUT") return;
  if (ev.code === "Space") { ev.preventDefault(); if (!ev.repeat) { master.key = true; master.device = "keyboard"; sendSample(evTime(ev)); } }
  else if (STEP[ev.key]) { ev.preventDefault(); const s = STEP[ev.key]; move(s[0] / 1000, s[1] / 1000, s[2] / 1000); sendSample(evTime(ev)); }
  else if (ev.key === "F1") { ev.preventDefault(); estop(); }
});
window.addEventListener("keyup", (ev) => {
  if (ev.code === "Space") { master.key = false; sendSample(evTime(ev)); }
});
window.addEventListener("blur", () => { master.key = false; drag = null; });

// ------------------------------------------------------------------ on-screen pedal (mouse or touch)
const pedal = $("#pedal");
function setPedal(on, ev) { master.pedal = on; pedal.classList.toggle("on", on); sendSample(ev ? evTime(ev) : now()); }
pedal.addEventListener("mousedown", (ev) => setPedal(true, ev));
pedal.addEventListener("mouseup", (ev) => setPedal(false, ev));
pedal.addEventListener("mouseleave", (ev) => { if (master.pedal) setPedal(false, ev); });
pedal.addEventListener("touchstart", (ev) => { ev.preventDefault(); master.device = "touch"; setPedal(true, ev); }, { passive: false });
pedal.addEventListener("touchend", (ev) => { ev.preventDefault(); setPedal(false, ev); }, { passive: false });
pedal.addEventListener("touchcancel", (ev) => setPedal(false, ev));

// ------------------------------------------------------------------ phone / tablet
let touch = null;
// (targetTouches: the finger on the view, while another may hold the pedal)
view.addEventListener("touchstart", (ev) => { ev.preventDefault(); const t = ev.targetTouches[0]; touch = { x: t.clientX, y: t.clientY }; }, { passive: false });
view.addEventListener("touchmove", (ev) => {
  ev.preventDefault();
  if (!touch || !ev.targetTouches.length) return;
  const t = ev.targetTouches[0];
  move((t.clientX - touch.x) * mmPerPx / 1000, -(t.clientY - touch.y) * mmPerPx / 1000, 0);
  touch = { x: t.clientX, y: t.clientY };
  master.device = "touch";
  sendSample(evTime(ev));
}, { passive: false });
view.addEventListener("touchend", () => { touch = null; });
window.addEventListener("deviceorientation", (ev) => {
  if (ev.alpha === null && ev.beta === null && ev.gamma === null) return;
  master.q = qEuler(ev.alpha || 0, ev.beta || 0, ev.gamma || 0);
  master.device = "touch";
  sendSample(evTime(ev));
});

// ------------------------------------------------------------------ gamepad (rate control)
let lastPad = 0;
function pollPad(t) {
  const pads = navigator.getGamepads ? [...navigator.getGamepads()].filter((p) => p && p.connected) : [];
  if (!pads.length) { master.pad = false; lastPad = t; return; }
  const g = pads[0], dt = Math.min(0.05, (t - (lastPad || t)) / 1000), v = 0.05; // m/s at full stick
  lastPad = t;
  const dz = (a) => (Math.abs(a) < 0.12 ? 0 : a);
  const lt = g.buttons[6] ? g.buttons[6].value : 0;
  move(dz(g.axes[0] || 0) * v * dt, -dz(g.axes[1] || 0) * v * dt, (-dz(g.axes[3] || 0) - lt) * v * dt);
  const rt = g.buttons[7] ? g.buttons[7].value : 0;
  master.pad = rt > 0.5;
  if (rt > 0.5 || dz(g.axes[0] || 0) || dz(g.axes[1] || 0)) master.device = "gamepad";
}

// ------------------------------------------------------------------ tip force: overlay and rumble
// The slave's tip force (measured_cf of the arm this page's master drives, pushed in the state at
// web.state_hz) is drawn over the picture — magnitude, direction, the tissue limit — and played on
// the gamepad's rumble (Gamepad API vibrationActuator, "dual-rumble"), intensity |F| / limit,
// and on a phone's vibration motor (buzz()).
// Quiet — the force stream stale, the watchdog holding (or its state stale), no state from the
// console for STATE_QUIET_MS, the page hidden or not in control — greys the overlay and stops the
// rumble at once (reset()); each effect lasts only RUMBLE_MS, so a page that stops being updated
// stops rumbling by itself.
const RUMBLE_MS = 150, RUMBLE_EVERY_MS = 60, STATE_QUIET_MS = 250;
const force = { arm: null, mag: 0, limit: 0, k: 0, quiet: "no force yet", rx: 0 };
let rumbling = 0, rumbledAt = 0; // the intensity playing (0: stopped), when it was last (re)started
window.consoleForce = force;
function actuator() {
  const pads = navigator.getGamepads ? [...navigator.getGamepads()].filter((p) => p && p.connected) : [];
  const a = pads.length ? pads[0].vibrationActuator : null;
  return a && typeof a.playEffect === "function" ? a : null;
}
// A phone or tablet (a touch screen with navigator.vibrate) buzzes too. Its motor has no
// intensity, so |F| / limit is the share of each BUZZ_MS it runs: vibrate(k × BUZZ_MS), renewed
// every BUZZ_MS (or at once on a change of a tenth); quiet stops it at once (vibrate(0)).
const BUZZ_MS = 100;
let buzzing = 0, buzzedAt = 0;
function buzz(k, t) {
  if (!(navigator.maxTouchPoints > 0) || typeof navigator.vibrate !== "function") { buzzing = 0; return; }
  if (k <= 0) {
    if (buzzing > 0) { buzzing = 0; navigator.vibrate(0); }
    return;
  }
  if (Math.abs(k - buzzing) < 0.1 && t - buzzedAt < BUZZ_MS) return;
  buzzing = k; buzzedAt = t;
  navigator.vibrate(Math.max(1, Math.round(k * BUZZ_MS)));
}
function rumble(k, t) {
  buzz(k, t);
  const act = actuator();
  if (!act) { rumbling = 0; return; }
  if (k <= 0) {
    if (rumbling > 0) { // stop at once
      rumbling = 0;
      if (typeof act.reset === "function") act.reset().catch(() => {});
      else act.playEffect("dual-rumble", { startDelay: 0, duration: 1, strongMagnitude: 0, weakMagnitude: 0 }).catch(() => {});
    }
    return;
  }
  if (Math.abs(k - rumbling) < 0.02 && t - rumbledAt < RUMBLE_EVERY_MS) return;
  rumbling = k; rumbledAt = t;
  act.playEffect("dual-rumble", { startDelay: 0, duration: RUMBLE_MS, strongMagnitude: k, weakMagnitude: k }).catch(() => {});
}
function forceQuiet(t) {
  if (master.hidden) return "page hidden";
  if (!wsOpen) return "no link to the console";
  if (t - force.rx > STATE_QUIET_MS) return "no state from the console";
  return force.quiet;
}
let shownWhy = "";
function tickRumble(t) {
  const why = forceQuiet(t);
  rumble(why || !inControl ? 0 : force.k, t);
  if (why !== shownWhy && force.arm) { // the overlay says why it is quiet, whichever side found it
    shownWhy = why;
    $("#force-why").textContent = why;
    const frac = force.mag / force.limit;
    $("#force").className = why ? "f-quiet" : frac >= 1 ? "f-over" : frac >= 0.5 ? "f-warn" : "f-ok";
  }
}
function showForce(m) {
  const a = m.arms.find((x) => x.master === MASTER) || m.arms[0];
  const box = $("#force");
  const f = a && a.force;
  if (!f) { box.hidden = true; force.quiet = "no force stream"; force.k = 0; return; }
  const s = a.safety;
  const held = !s || s.stale || s.state === "HOLD" || s.state === "ESTOP";
  Object.assign(force, { arm: a.arm, n: f.n, mag: f.mag, limit: f.limit_n, rx: now() });
  force.quiet = master.hidden ? "page hidden" : f.stale ? `force stream stale (${fmt(f.age_ms, 0)} ms old)` :
    held ? "watchdog " + (!s ? "state unknown" : s.stale ? "state stale" : s.state) : "";
  force.k = f.stale ? 0 : Math.min(1, f.mag / f.limit_n);
  if (force.k < 0.02) force.k = 0;
  box.hidden = false;
  const frac = f.mag / f.limit_n;
  box.className = force.quiet ? "f-quiet" : frac >= 1 ? "f-over" : frac >= 0.5 ? "f-warn" : "f-ok";
  $("#force-value").textContent = fmt(f.mag, 2);
  $("#force-limit").textContent = fmt(f.limit_n, 1);
  $("#force-why").textContent = shownWhy = force.quiet;
  dial(f, frac, !!force.quiet);
  tickRumble(now());
}
// The dial: the force's direction in the side view (x →, z ↑ of the arm's base frame, as the arm
// view's right panel) with the tissue limit as the red ring; below, the magnitude on a bar to
// 1.5 × the limit with the limit marked.
function dial(f, frac, quiet) {
  const c = $("#force-dial"), g = c.getContext("2d");
  const W = c.width, R = 54, cx = W / 2, cy = 62;
  g.clearRect(0, 0, W, c.height);
  const col = quiet ? "#888" : frac >= 1 ? "#ff4040" : frac >= 0.5 ? "#f0c040" : "#5fd35f";
  g.strokeStyle = "#ff4040"; g.lineWidth = 2; g.setLineDash([4, 3]);
  g.beginPath(); g.arc(cx, cy, R / 1.5, 0, 7); g.stroke(); g.setLineDash([]);
  const h = Math.hypot(f.n[0], f.n[2]) || 1, len = Math.min(1.5, frac) / 1.5 * R;
  const ux = f.n[0] / h, uy = -f.n[2] / h;
  if (len > 1) {
    const ex = cx + ux * len, ey = cy + uy * len;
    g.strokeStyle = g.fillStyle = col; g.lineWidth = 4;
    g.beginPath(); g.moveTo(cx, cy); g.lineTo(ex, ey); g.stroke();
    g.beginPath(); g.moveTo(ex + ux * 8, ey + uy * 8);
    g.lineTo(ex - uy * 6, ey + ux * 6); g.lineTo(ex + uy * 6, ey - ux * 6); g.fill();
  }
  const bx = 6, bw = W - 12, by = 132;
  g.fillStyle = "#333b44"; g.fillRect(bx, by, bw, 10);
  g.fillStyle = col; g.fillRect(bx, by, bw * Math.min(1.5, frac) / 1.5, 10);
  g.fillStyle = "#ff4040"; g.fillRect(bx + bw / 1.5 - 1, by - 4, 3, 18);
}

// ------------------------------------------------------------------ the quiet browser
document.addEventListener("visibilitychange", () => {
  master.hidden = document.visibilityState === "hidden";
  master.key = master.pedal = master.pad = false;
  pedal.classList.remove("on");
  if (master.hidden) {
    rumble(0, now());
    force.quiet = shownWhy = "page hidden"; $("#force-why").textContent = force.quiet; $("#force").className = "f-quiet";
    send({ type: "hidden", master: MASTER });
  }
});
window.addEventListener("pagehide", () => { master.hidden = true; rumble(0, now()); send({ type: "hidden", master: MASTER }); });

setInterval(() => { const t = now(); pollPad(t); tickRumble(t); sendSample(t); }, SEND_MS);

// ------------------------------------------------------------------ controls
function estop() { send({ type: "estop", arm: "*" }); logLine("warning", "E-STOP sent"); }
$("#estop").addEventListener("click", estop);
$("#estop").addEventListener("touchstart", (ev) => { ev.preventDefault(); estop(); }, { passive: false });
$("#reset").addEventListener("click", () => { $("#confirm").hidden = false; });
$("#confirm-no").addEventListener("click", () => { $("#confirm").hidden = true; });
$("#confirm-yes").addEventListener("click", () => { $("#confirm").hidden = true; send({ type: "reset", arm: "*", confirm: true }); });
let selArm = null;
function arm() { return selArm || (window.consoleState && window.consoleState.arms[0] && window.consoleState.arms[0].arm); }
function command(name, args, target) { if (arm()) send({ type: "command", arm: arm(), name, args, target: target || "slave" }); }
document.querySelectorAll("[data-cmd]").forEach((b) => b.addEventListener("click", () => command(b.dataset.cmd, b.dataset.args ? b.dataset.args.split(" ") : [])));
document.querySelectorAll("[data-mcmd]").forEach((b) => b.addEventListener("click", () => command(b.dataset.mcmd, [], "mapping")));
function jog(dir) { command("jog", ["frame=" + $("#jog-frame").value, "axis=" + $("#jog-axis").value, "direction=" + dir]); }
$("#jog-plus").addEventListener("click", () => jog(1));
$("#jog-minus").addEventListener("click", () => jog(-1));
$("#jog-frame").addEventListener("change", () => {
  const axes = $("#jog-frame").value === "joint" ? ["j1", "j2", "j3", "j4", "j5", "j6"] : ["x", "y", "z", "rx", "ry", "rz"];
  $("#jog-axis").innerHTML = axes.map((a) => `<option>${a}</option>`).join("");
});
$("#cmdline").addEventListener("submit", (ev) => {
  ev.preventDefault();
  const words = $("#cmd").value.trim().split(/\s+/).filter(Boolean);
  if (!words.length) return;
  const target = words[0] === "mapping" ? (words.shift(), "mapping") : "slave";
  command(words.shift(), words, target);
  $("#cmd").value = "";
});
$("#take").addEventListener("click", () => send({ type: "control", action: "take" }));
$("#release").addEventListener("click", () => send({ type: "control", action: "release" }));
$("#handover-yes").addEventListener("click", () => { $("#handover").hidden = true; send({ type: "control", action: "grant" }); });
$("#handover-no").addEventListener("click", () => { $("#handover").hidden = true; send({ type: "control", action: "refuse" }); });
$("#invite").addEventListener("click", () => send({ type: "invite" }));
$("#record").addEventListener("click", () => send({ type: "record", action: window.consoleState && window.consoleState.recording ? "stop" : "start" }));

// ------------------------------------------------------------------ rendering
function logLine(sev, text) {
  const d = document.createElement("div");
  d.className = sev;
  d.textContent = new Date().toLocaleTimeString() + " " + text;
  const log = $("#log");
  log.prepend(d);
  while (log.childNodes.length > 60) log.lastChild.remove();
  window.consoleNotices.push({ severity: sev, text });
}
const esc = (s) => String(s).replace(/[&<>"]/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;" }[c]));
const fmt = (v, n = 1) => (v === null || v === undefined ? "—" : Number(v).toFixed(n));
function st(s) { return `<span class="state st-${esc(s)}">${esc(s)}</span>`; }

function armHtml(a) {
  const tp = a.teleop, op = a.op, s = a.safety;
  const rows = [];
  rows.push(["teleop", tp ? `${st(tp.state)} ${tp.stale ? '<span class="bad">STALE</span>' : ""} <span class="dim">${esc(tp.reason)} · ${fmt(tp.since_s)} s · ${esc(tp.mode)}</span>` : '<span class="dim">no teleop state yet</span>']);
  rows.push(["slave", op ? `${st(op.state)} · mode <b class="control-mode">${esc(op.control_mode)}</b> · ${op.follow ? "following" : "holding"}${op.reason ? " — " + esc(op.reason) : ""}${op.stale ? ' <span class="bad">STALE</span>' : ""}` : '<span class="dim">no operating state</span>']);
  rows.push(["safety", s ? `${st(s.state)} ${s.causes.length ? '<span class="warn">' + esc(s.causes.join("; ")) + "</span>" : ""}${s.stale ? ' <span class="bad">STALE</span>' : ""}` : '<span class="dim">no safety state</span>']);
  rows.push(["latency", s && s.samples ? `p50 <b class="p50">${fmt(s.p50_ms)}</b> ms · p99 <b class="p99">${fmt(s.p99_ms)}</b> ms <span class="dim">(${s.samples})</span>` : '<span class="dim">—</span>']);
  rows.push(["master clock", s ? `<span class="clock">${s.clock_offset_ms >= 0 ? "+" : ""}${fmt(s.clock_offset_ms)}</span> ms <span class="dim">(its host's clock − the slave site's, as the watchdog measures it)</span>` : '<span class="dim">—</span>']);
  rows.push(["scale", `operator <b class="op-scale">${tp ? fmt(tp.scale, 2) : "—"}</b> · watchdog factor <b class="wd-scale">${s ? fmt(s.scale, 2) : "—"}</b>`]);
  rows.push(["tip mm", a.tip_mm ? `<span class="tip">${a.tip_mm.map((v) => fmt(v)).join(", ")}</span>` : "—"]);
  if (op && op.control_mode && op.control_mode !== "non_trocar" && op.rcm_error_mm !== null) rows.push(["RCM error", `${fmt(op.rcm_error_mm, 2)} mm`]);
  if (a.reply) rows.push(["reply", esc(a.reply)]);
  let h = `<h2>${esc(a.arm)} <span class="dim">← ${esc(a.master)}</span></h2>`;
  h += rows.map(([k, v]) => `<div class="row"><span class="k">${k}</span><span class="v ${k.replace(/\W/g, "")}">${v}</span></div>`).join("");
  h += a.joints.map((j) => {
    let bar = "";
    if (j.lo !== undefined) {
      const f = (j.pos - j.lo) / (j.hi - j.lo || 1);
      bar = `<div class="bar${f < 0.05 || f > 0.95 ? " near" : ""}"><i style="left:${(Math.max(0, Math.min(1, f)) * 100).toFixed(1)}%"></i></div>`;
    } else bar = "<div></div>";
    const deg = /^j/.test(j.name) && j.lo !== undefined && Math.abs(j.hi) < 7 ? fmt(j.pos * 180 / Math.PI) + "°" : fmt(j.pos, 4);
    return `<div class="joint"><span>${esc(j.name)}</span>${bar}<span>${deg}</span></div>`;
  }).join("");
  h += `<div class="events">${a.events.slice().reverse().map((e) => esc(`${e.src} ${e.kind}: ${e.text}`)).join("<br>")}</div>`;
  return h;
}

function render(m) {
  window.consoleState = m;
  mmPerPx = m.mouse_mm_per_px || mmPerPx;
  $("#site").textContent = "site " + m.site;
  const refused = m.door ? Object.entries(m.door.refused) : [];
  $("#alive").innerHTML = `<span class="dim">alive: ${esc(m.alive.join(" "))}</span>` +
    (refused.length ? ` <span class="warn" id="door-refused">refused at the door: ${esc(refused.map(([k, n]) => k + " " + n).join(", "))}</span>` : "");
  const ms = m.masters[MASTER];
  masterOn = !!ms;
  const el = $("#master-status");
  if (!ms) { el.textContent = "no browser master here (state and commands only)"; el.className = "dim"; }
  if (ms) {
    el.textContent = `master ${MASTER} (${ms.device || "—"}): ${ms.valid ? "publishing" : "not publishing"} · clutch ${ms.clutch ? "PRESSED" : ms.clutch_raw ? "held — release and press again" : "released"}`;
    el.className = ms.valid ? (ms.clutch ? "ok" : "") : "bad";
  }
  $("#record").textContent = m.recording ? "■ stop recording" : "● record";
  const box = $("#arms");
  for (const a of m.arms) {
    let d = document.getElementById("arm-" + a.arm);
    if (!d) {
      d = document.createElement("div");
      d.className = "arm"; d.id = "arm-" + a.arm;
      d.addEventListener("click", () => { selArm = a.arm; });
      box.appendChild(d);
    }
    d.innerHTML = armHtml(a);
  }
  banner(m);
  trial(m.trial);
  for (const n of m.notices || []) logLine(n.severity, n.text);
  scope(m.video || {});
  askConfirm(m.confirm);
  draw(m);
  showForce(m);
}

// The study's current trial (telesurg study): the task, its instructions, the clock, the score at
// the end. The condition is what the study lets the operator see: its code when blinded.
const PHASE = { setup: "setting up the arm…", ready: "ready: press the clutch to start", running: "", done: "done", failed: "stopped" };
function trial(t) {
  const box = $("#trial");
  box.hidden = !t;
  if (!t) return;
  box.className = "t-" + t.phase;
  $("#trial-title").textContent = `${t.practice ? "practice" : "trial"} ${t.trial}/${t.trials} · ${t.task}`;
  $("#trial-condition").textContent = t.condition;
  $("#trial-phase").textContent = PHASE[t.phase] ?? t.phase;
  $("#trial-clock").textContent = `${t.elapsed_s.toFixed(1)} s` + (t.time_limit_s ? ` / ${t.time_limit_s.toFixed(0)} s` : "");
  $("#trial-goals").textContent = t.goals ? `goals ${t.goals_reached}/${t.goals}` : "";
  $("#trial-instructions").textContent = t.instructions;
  $("#trial-result").textContent = t.result;
}

// A motion-starting command is carried out only once the operator confirms the server's question.
let asked = "";
function askConfirm(c) {
  if (!c || !inControl) { asked = ""; return; }
  const q = `${c.arm}: ${c.command}\n${c.question}\n\nStart this motion?`;
  if (q === asked) return;
  asked = q;
  setTimeout(() => send({ type: "confirm", yes: window.confirm(q) }), 0);
}

// The endoscope picture (camera service), shown once a camera publishes, with the frame's age;
// hidden on a site without a camera. MJPEG: an <img> on /video.mjpg. H.264 (a console with
// web.video = "h264", for a distance): access units read from /video.h264 with fetch, decoded by
// WebCodecs, painted on a canvas, with each frame's age at paint (capture → painted, this host's
// clock: the console corrects the slave site's capture time by the watchdog's clock offset).
function scope(video) {
  const cams = Object.keys(video);
  const box = $("#scope");
  if (!cams.length) { box.hidden = true; return; }
  const v = video[cams[0]];
  if (box.hidden) {
    if (v.encoding === "h264") startH264(cams[0]);
    else $("#endoscope").src = "/video.mjpg?camera=" + encodeURIComponent(cams[0]);
    box.hidden = false;
  }
  const old = v.age_ms > 500;
  let text = `camera ${esc(cams[0])} · ${v.width}×${v.height} ${esc(v.layout)} ${esc(v.encoding || "jpeg")} · ` +
    `<span class="${old ? "bad" : ""}">frame age ${v.age_at_arrival_ms} ms at arrival, ${v.age_ms} ms now</span>`;
  if (v.encoding === "h264") {
    const s = h264.stats();
    text += h264.error ? ` · <span class="bad">${esc(h264.error)}</span>`
      : ` · painted ${s.fps.toFixed(1)} fps, age at paint ${s.age_p50 === null ? "–" : Math.round(s.age_p50)} ms` +
        (s.shown_ms > 500 ? ` · <span class="bad">picture on screen ${Math.round(s.shown_ms)} ms old</span>` : "");
  }
  $("#scope-info").innerHTML = text;
}

// The H.264 picture: a packet is u32 length of the rest, u8 flags (1 keyframe), f64 capture time
// (ms since the epoch, this host's clock), u32 sequence, u16 width, u16 height, then the access
// unit (Annex B). The decoder starts at a keyframe (the server sends one first); a page that
// falls behind reconnects, and the server starts it again at a fresh keyframe.
const h264 = {
  error: "", count: 0,
  painted: [], // [paint time ms, age ms] of the last frames painted
  rx: [], // [arrival time ms, bytes] of the last packets
  stats() {
    const now = performance.timeOrigin + performance.now();
    const recent = this.painted.filter(([t]) => now - t < 2000);
    const ages = recent.map(([, a]) => a).sort((x, y) => x - y);
    const bytes = this.rx.filter(([t]) => now - t < 2000).reduce((n, [, b]) => n + b, 0);
    const last = this.painted[this.painted.length - 1]; // the picture on screen: its age now
    return { fps: recent.length / 2, age_p50: ages.length ? ages[ages.length >> 1] : null,
      kbps: bytes * 8 / 2000, frames: this.count, shown_ms: last ? now - last[0] + last[1] : null };
  },
};
const keep = (list, item) => { list.push(item); if (list.length > 3000) list.shift(); };
window.telesurgH264 = h264; // (read by the browser tests)

function avcCodec(au) { // "avc1.PPCCLL" from the access unit's SPS (NAL type 7)
  for (let i = 0; i + 6 < au.length; i++) {
    if (au[i] === 0 && au[i + 1] === 0 && au[i + 2] === 1 && (au[i + 3] & 0x1f) === 7) {
      return "avc1." + [au[i + 4], au[i + 5], au[i + 6]].map((b) => b.toString(16).padStart(2, "0")).join("");
    }
  }
  return null;
}

function startH264(cam) {
  const canvas = $("#endoscope-h264"), img = $("#endoscope");
  if (!("VideoDecoder" in window)) {
    h264.error = "this browser has no WebCodecs video decoder: start the console with web.video = \"mjpeg\"";
    return;
  }
  img.hidden = true; canvas.hidden = false;
  const g = canvas.getContext("2d");
  let dec = null, codec = null;
  const output = (frame) => {
    if (canvas.width !== frame.displayWidth || canvas.height !== frame.displayHeight) {
      canvas.width = frame.displayWidth; canvas.height = frame.displayHeight;
    }
    g.drawImage(frame, 0, 0);
    const capture = frame.timestamp / 1000;
    frame.close();
    requestAnimationFrame(() => { // painted with this animation frame
      const now = performance.timeOrigin + performance.now();
      keep(h264.painted, [now, now - capture]);
      h264.count++;
    });
  };
  async function run() {
    const ctl = new AbortController();
    try {
      const resp = await fetch("/video.h264?camera=" + encodeURIComponent(cam), { signal: ctl.signal, cache: "no-store" });
      if (!resp.ok) { h264.error = `video: ${resp.status} ${await resp.text()}`; return; }
      h264.error = "";
      const reader = resp.body.getReader();
      let buf = new Uint8Array(0);
      for (;;) {
        const { value, done } = await reader.read();
        if (done) break;
        const joined = new Uint8Array(buf.length + value.length); joined.set(buf); joined.set(value, buf.length); buf = joined;
        while (buf.length >= 4) {
          const dv = new DataView(buf.buffer, buf.byteOffset, buf.length);
          const n = dv.getUint32(0, true);
          if (buf.length < 4 + n) break;
          const key = (dv.getUint8(4) & 1) === 1, capture = dv.getFloat64(5, true);
          const au = buf.slice(21, 4 + n);
          keep(h264.rx, [performance.timeOrigin + performance.now(), 4 + n]);
          buf = buf.slice(4 + n);
          if (!dec || dec.state === "closed") {
            if (!key) continue;
            codec = avcCodec(au) || "avc1.42e01e";
            dec = new VideoDecoder({ output, error: (e) => { h264.error = `decoder: ${e.message}`; } });
            dec.configure({ codec, optimizeForLatency: true });
          }
          if (dec.decodeQueueSize > 4 && !key) { ctl.abort(); break; } // behind: start over at a keyframe
          dec.decode(new EncodedVideoChunk({ type: key ? "key" : "delta", timestamp: Math.round(capture * 1000), data: au }));
        }
        if (ctl.signal.aborted) break;
      }
    } catch (e) {
      if (!ctl.signal.aborted) h264.error = `video: ${e.message}`;
    }
    if (dec && dec.state !== "closed") dec.close();
    dec = null;
    setTimeout(run, 500); // the stream ended (the console restarted, the page fell behind): again
  }
  run();
}

// the picture on the page (the MJPEG image or the H.264 canvas) and its size in image pixels
function picture() {
  const c = $("#endoscope-h264");
  if (!c.hidden) return { el: c, w: c.width && c.clientWidth ? c.width : 0 };
  const img = $("#endoscope");
  return { el: img, w: img.naturalWidth };
}

// The predictive overlay: each following arm's commanded tip over the endoscope picture, which
// shows the arm as it was behind_ms ago (the video's delay): the surgeon sees where the tool
// is going before the picture shows it. Marks are placed in the image's pixels, scaled to the
// picture's size on the page; a stereo pair has one per eye.
function overlay(m) {
  const cams = Object.keys(m.cams || {});
  const box = $("#scope-marks"), pic = picture(), img = pic.el;
  const want = [];
  let lead = "";
  if (cams.length && !$("#scope").hidden && pic.w) {
    const c = m.cams[cams[0]];
    const kx = img.clientWidth / c.width, ky = img.clientHeight / c.height;
    for (const [arm, a] of Object.entries(c.arms)) {
      if (a.age_ms > 250) continue; // not following: no command to show (setpoint_cp at 100 Hz)
      a.px.forEach((p, eye) => {
        if (p && p[0] >= 0 && p[0] <= c.width && p[1] >= 0 && p[1] <= c.height) want.push([arm, eye, p[0] * kx, p[1] * ky]);
      });
    }
    if (want.length) lead = `○ commanded tip: ${Math.round(c.behind_ms)} ms ahead of the picture`;
  }
  while (box.children.length < want.length) { const d = document.createElement("div"); d.className = "cmd-mark"; box.appendChild(d); }
  while (box.children.length > want.length) box.lastChild.remove();
  want.forEach(([arm, eye, x, y], i) => {
    const d = box.children[i];
    d.dataset.arm = arm; d.dataset.eye = eye; d.style.left = x.toFixed(1) + "px"; d.style.top = y.toFixed(1) + "px";
  });
  $("#scope-lead").textContent = lead;
}

// Two orthographic views of each arm (base frame, mm): top (x right, y up) and side (x right,
// z up); links grey, forceps yellow, measured tip green, commanded tip (ghost) hollow magenta.
const bounds = { x: [-200, 900], y: [-500, 500], z: [-300, 900] };
function draw(m) {
  const c = view, g = c.getContext("2d");
  const W = c.width, H = c.height;
  g.fillStyle = "#0c0f12"; g.fillRect(0, 0, W, H);
  const panels = [["top view (x → , y ↑)", 0, 1], ["side view (x → , z ↑)", 0, 2]];
  const names = ["x", "y", "z"];
  panels.forEach(([title, u, v], i) => {
    const x0 = (i * W) / 2 + 10, w = W / 2 - 20, y0 = 24, h = H - 34;
    const bu = bounds[names[u]], bv = bounds[names[v]];
    const k = Math.min(w / (bu[1] - bu[0]), h / (bv[1] - bv[0]));
    const P = (p) => [x0 + (p[u] - bu[0]) * k, y0 + h - (p[v] - bv[0]) * k];
    g.strokeStyle = "#333b44"; g.strokeRect(x0, y0, w, h);
    g.fillStyle = "#7d8793"; g.font = "12px sans-serif"; g.fillText(title, x0, 16);
    for (const a of m.arms) {
      const sk = a.sketch;
      if (sk && sk.links) {
        g.strokeStyle = "#9aa5b1"; g.lineWidth = 6; g.beginPath();
        sk.links.forEach((p, j) => { const q = P(p); j ? g.lineTo(...q) : g.moveTo(...q); }); g.stroke();
      }
      if (sk && sk.forceps) {
        g.strokeStyle = "#e8c547"; g.lineWidth = 3; g.beginPath();
        sk.forceps.forEach((p, j) => { const q = P(p); j ? g.lineTo(...q) : g.moveTo(...q); }); g.stroke();
      }
      if (sk && sk.rcm) { for (const p of sk.rcm) { const q = P(p); g.strokeStyle = "#4dabf7"; g.lineWidth = 2; g.strokeRect(q[0] - 5, q[1] - 5, 10, 10); } }
      if (m.trial && m.trial.goals_mm && a === m.arms[0]) { // the study's goals: the next one filled
        m.trial.goals_mm.forEach((p, j) => {
          const q = P(p), next = j === m.trial.goals_reached;
          if (j < m.trial.goals_reached) return;
          g.strokeStyle = g.fillStyle = next ? "#4dabf7" : "#3b5d7a"; g.lineWidth = 2; g.beginPath(); g.arc(q[0], q[1], next ? 7 : 5, 0, 7);
          next ? g.fill() : g.stroke();
        });
      }
      if (a.ghost_mm) { const q = P(a.ghost_mm); g.strokeStyle = "#f06595"; g.lineWidth = 2; g.beginPath(); g.arc(q[0], q[1], 9, 0, 7); g.stroke(); }
      if (a.tip_mm) { const q = P(a.tip_mm); g.fillStyle = "#5fd35f"; g.beginPath(); g.arc(q[0], q[1], 5, 0, 7); g.fill(); }
      if (a.tip_mm && a.force && a.force.mag > 0.01) { // the tip force, 15 px per N, from the tip
        const q = P(a.tip_mm), f = a.force.n;
        g.strokeStyle = a.force.stale ? "#888" : a.force.mag >= a.force.limit_n ? "#ff4040" : "#f0c040"; g.lineWidth = 3;
        g.beginPath(); g.moveTo(q[0], q[1]); g.lineTo(q[0] + f[u] * 15, q[1] - f[v] * 15); g.stroke();
      }
    }
    g.lineWidth = 1;
  });
}

connect();
