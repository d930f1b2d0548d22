// The line view: renders the line's state from /events; every text goes in as text.
"use strict";
const $ = (id) => document.getElementById(id);

function el(tag, text, cls) {
  const e = document.createElement(tag);
  if (text !== undefined && text !== null) e.textContent = String(text);
  if (cls) e.className = cls;
  return e;
}

const pct = (x) => (x === null || x === undefined ? "-" : (100 * x).toFixed(1) + " %");
const when = (t) => (t ? t.replace("T", " ").slice(0, 19) : "-");

function card(s) {
  const box = el("div", null, "station");
  box.dataset.station = s.station;
  box.dataset.state = s.state;
  box.appendChild(el("h2", s.station));
  box.appendChild(el("div", s.state.toUpperCase(), "state"));
  box.appendChild(el("div", `last run ${when(s.last_at)} UTC; ${s.runs} run(s), yield ${pct(s.yield)}, first pass ${pct(s.fpy)}`));
  if (s.gate && s.state !== "blocked") box.appendChild(el("div", s.gate, "where"));
  for (const a of s.alarms) box.appendChild(el("div", "ALARM: " + a, "v-error"));
  const list = el("ol");
  for (const r of s.last) {
    const li = el("li");
    li.appendChild(el("span", r.serial + " "));
    li.appendChild(el("span", r.kind === "refusal" ? "refused" : r.verdict, "v-" + r.verdict));
    li.appendChild(el("span", " " + when(r.started_at).slice(11)));
    list.appendChild(li);
  }
  box.appendChild(list);
  return box;
}

function render(s) {
  $("db").textContent = s.db;
  $("fpy").textContent = pct(s.fpy);
  $("updated").textContent = s.read_at ? "read " + when(s.read_at).slice(11) + " UTC" : "not read yet";
  const err = $("error");
  err.hidden = !s.error;
  err.textContent = s.error || "";
  const alarms = $("alarms");
  alarms.hidden = !s.alarms.length;
  alarms.replaceChildren(...s.alarms.map((a) => el("div", "ALARM: " + a)));
  $("stations").replaceChildren(...s.stations.map(card));
  $("shifts").tBodies[0].replaceChildren(...s.shifts.map((r) => {
    const tr = el("tr");
    for (const t of [r.shift, r.station, r.runs, r.pass, r.fail, r.error, pct(r.yield), pct(r.fpy)]) tr.appendChild(el("td", t));
    return tr;
  }));
}

document.addEventListener("DOMContentLoaded", () => {
  const source = new EventSource("events");
  source.onmessage = (e) => render(JSON.parse(e.data));
  source.onerror = () => { $("updated").textContent = "connection lost: retrying"; };
});
