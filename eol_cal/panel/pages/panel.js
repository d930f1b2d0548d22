// The operator panel: renders the station's state from /events; every text goes in as text.
"use strict";
const $ = (id) => document.getElementById(id);
let state = null;

function el(tag, text, cls) {
  const e = document.createElement(tag);
  if (text !== undefined && text !== null) e.textContent = String(text);
  if (cls) e.className = cls;
  return e;
}

function fmt(x, digits) {
  return x === null || x === undefined ? "-" : Number(x).toPrecision(digits || 4);
}

async function post(path, body) {
  const r = await fetch(path, { method: "POST", headers: { "Content-Type": "application/json" },
                               body: JSON.stringify(body || {}) });
  let doc = {};
  try { doc = await r.json(); } catch (e) { doc = { error: "HTTP " + r.status }; }
  if (!r.ok) showMessage("error", doc.error || ("HTTP " + r.status));
  return r.ok;
}

function showMessage(level, text) {
  const m = $("message");
  m.className = "message " + level;
  m.textContent = text;
}

function renderSteps(s) {
  const list = $("steps");
  list.replaceChildren();
  const now = Date.now() / 1000;
  for (const step of s.steps) {
    const li = el("li");
    li.dataset.step = step.step;
    li.dataset.what = step.what;
    li.appendChild(el("span", step.step));
    const secs = step.seconds !== null && step.seconds !== undefined ? step.seconds
      : (step.since ? now - step.since : null);
    const word = step.what === "start" ? "running" : step.what;
    li.appendChild(el("span", (secs === null ? "" : secs.toFixed(1) + " s ") + word));
    list.appendChild(li);
  }
}

function renderVerdict(v) {
  const box = $("verdict");
  box.dataset.verdict = v ? v.verdict : "none";
  $("verdict-word").textContent = v ? v.verdict.toUpperCase() : "-";
  $("verdict-serial").textContent = v ? v.serial + (v.kind === "refusal" ? " (refused)" : "") : "";
  const reasons = $("reasons");
  reasons.replaceChildren();
  if (v) for (const r of v.reasons.concat(v.notes)) reasons.appendChild(el("li", r));
  const body = $("margins").tBodies[0];
  body.replaceChildren();
  if (v) for (const m of v.margins) {
    const tr = el("tr", null, m.passed ? "in" : "out");
    tr.dataset.key = m.key;
    for (const t of [m.title, fmt(m.value) + " " + m.unit, (m.sense === "max" ? "\u2264 " : "\u2265 ") + fmt(m.limit) + " " + m.unit,
                     (m.margin >= 0 ? "+" : "") + fmt(m.margin, 3) + " " + m.unit]) tr.appendChild(el("td", t));
    body.appendChild(tr);
  }
  if (v && v.margins_left) {
    const tr = el("tr", null, "more");
    const td = el("td", `${v.margins_left} more limit(s) met with more margin (the report lists all)`);
    td.colSpan = 4;
    tr.appendChild(td);
    body.appendChild(tr);
  }
  // the run's directory and where the record went (the whole paths are in the terminal's lines and the record)
  const report = v && v.report ? v.report.split("/").slice(-2).join("/") : "-";
  $("verdict-where").textContent = v ? ("report " + report + "; record: " + (v.record.startsWith("database") ? "in the database" : v.record)) : "";
}

function renderTrace(all) {
  const traces = all.slice(-1);  // the latest capture: each acquisition has its own clock
  const c = $("trace");
  const g = c.getContext("2d");
  g.fillStyle = "#0a0a0a";
  g.fillRect(0, 0, c.width, c.height);
  $("trace-label").textContent = traces.length ? traces[0].label : "";
  if (!traces.length) return;
  let lo = Infinity, hi = -Infinity, t0 = Infinity, t1 = -Infinity;
  for (const t of traces) {
    for (const y of t.torque) { lo = Math.min(lo, y); hi = Math.max(hi, y); }
    t0 = Math.min(t0, t.t[0]); t1 = Math.max(t1, t.t[t.t.length - 1]);
  }
  if (hi <= lo) { hi = lo + 1; }
  const pad = 30, w = c.width - 2 * pad, h = c.height - 2 * pad;
  const colours = ["#40c4ff", "#00e676"];
  traces.forEach((t, k) => {
    g.strokeStyle = colours[k % colours.length];
    g.lineWidth = 1.5;
    g.beginPath();
    t.t.forEach((x, i) => {
      const px = pad + (x - t0) / Math.max(t1 - t0, 1e-9) * w, py = pad + (hi - t.torque[i]) / (hi - lo) * h;
      if (i === 0) g.moveTo(px, py); else g.lineTo(px, py);
    });
    g.stroke();
  });
  g.fillStyle = "#fff";
  g.font = "18px sans-serif";
  g.fillText(hi.toFixed(3) + " N\u00b7m", 4, 20);
  g.fillText(lo.toFixed(3) + " N\u00b7m", 4, c.height - 8);
  g.fillText((t1 - t0).toFixed(1) + " s", c.width - 70, c.height - 8);
}

function render(s) {
  state = s;
  $("station").textContent = s.station || "-";
  $("operator").textContent = s.operator || "not signed in";
  const signedIn = s.operator !== null;
  $("signin").hidden = signedIn;
  $("signout").hidden = !signedIn || s.phase !== "idle";
  const idle = s.phase === "idle" && !s.ended;
  $("scan").disabled = !signedIn || !idle;
  $("stop").disabled = !signedIn || s.phase !== "running";
  $("end").disabled = !signedIn || !idle;
  $("phase").textContent = s.ended ? "session ended" : (s.phase === "idle" ? "ready: scan a serial" : s.phase);
  $("serial").textContent = s.serial || (s.verdict ? s.verdict.serial : "-");
  const gate = $("gate");
  gate.hidden = !s.gate;
  if (s.gate) {
    gate.className = "banner" + (s.gate.blocked ? " blocked" : "");
    gate.textContent = (s.gate.blocked ? "PRODUCTION BLOCKED: " : "") + s.gate.line;
  }
  const alarms = $("alarms");
  alarms.hidden = !s.alarms.length;
  alarms.replaceChildren(...s.alarms.map((a) => el("div", "ALARM: " + a)));
  if (s.message) showMessage(s.message.level, s.message.text); else showMessage("", "");
  renderSteps(s);
  renderVerdict(s.verdict);
  renderTrace(s.traces);
  const c = s.counts;
  $("counts").textContent = c ? `${c.runs} run(s) of ${c.motors} motor(s): ${c.pass} pass, ${c.fail} fail, ${c.error} error`
    + (c.refused ? ` (${c.refused} refused)` : "") : "no motor yet";
  $("last").replaceChildren(...s.last.map((m) => {
    const li = el("li");
    li.appendChild(el("span", m.serial));
    li.appendChild(el("span", m.kind === "refusal" ? "refused" : m.verdict, "v-" + m.verdict));
    return li;
  }));
  if (!$("scan").disabled && document.activeElement !== $("signin-name")) $("scan").focus();
  if (!signedIn) $("signin-name").focus();
}

function connect() {
  const source = new EventSource("events");
  source.onmessage = (e) => render(JSON.parse(e.data));
  source.onerror = () => { $("phase").textContent = "connection lost: retrying"; };
}

document.addEventListener("DOMContentLoaded", () => {
  // a keyboard-wedge scanner types the code and Enter: the form's submit
  $("scanform").addEventListener("submit", (e) => {
    e.preventDefault();
    const line = $("scan").value;
    $("scan").value = "";
    post("scan", { line: line });
  });
  $("signin").addEventListener("submit", (e) => {
    e.preventDefault();
    post("signin", { name: $("signin-name").value });
    $("signin-name").value = "";
  });
  $("signout").addEventListener("click", () => post("signout"));
  $("stop").addEventListener("click", () => post("stop"));
  $("end").addEventListener("click", () => post("end"));
  setInterval(() => { if (state && state.phase === "running") renderSteps(state); }, 500);
  connect();
});
