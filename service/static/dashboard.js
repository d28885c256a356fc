// testcell's dashboard: discovers what the cell runs from the public HTTP API, plots it live
// from WS /stream, lists every channel, and tunes blocks, scripts and scenarios.
"use strict";

const HISTORY_S = 600;           // the longest window: 10 min
const TC = window.TC = {
  ready: false, messages: 0, dropped: 0, lastSeq: 0,
  store: new Store(Math.ceil(HISTORY_S * 10 * 1.1) + 16),
  view: {window: 60, paused: false, pausedAt: 0, zoom: null},
  plots: [], latest: new Map(), meta: new Map(), families: [], blocks: {}, paths: {},
  perf: {draws: 0, totalMs: 0, maxMs: 0},
};

const $ = id => document.getElementById(id);
const esc = s => String(s).replace(/[&<>"]/g, c => ({"&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;"}[c]));

// The cell's token, when it has one (TESTCELL_TOKEN): asked for once, kept for this tab.
const TOKEN_KEY = "testcell-token";
const token = () => sessionStorage.getItem(TOKEN_KEY);

async function api(method, url, body, type, retried) {
  const init = {method, headers: {}};
  if (method !== "GET") {
    // the cell refuses a change that is not JSON (415), except a script's text/plain source
    init.headers["Content-Type"] = type || "application/json";
  }
  if (body !== undefined) init.body = type ? body : JSON.stringify(body);
  if (token()) init.headers["Authorization"] = `Bearer ${token()}`;
  const r = await fetch(url, init);
  if (r.status === 401 && !retried) {
    const t = prompt("This cell needs its token (TESTCELL_TOKEN):");
    if (t) { sessionStorage.setItem(TOKEN_KEY, t.trim()); return api(method, url, body, type, true); }
  }
  const text = await r.text();
  let data = text;
  try { data = JSON.parse(text); } catch (e) { /* plain text */ }
  return {ok: r.ok, status: r.status, data};
}

function errorText(data) {
  // the server's words for a refused request: FastAPI's detail list, or a plain detail
  if (data && Array.isArray(data.detail)) {
    return data.detail.map(d => `${(d.loc || []).filter(x => x !== "body").join(".") || "request"}: ${d.msg}`).join("; ");
  }
  if (data && data.detail) return String(data.detail);
  return typeof data === "string" ? data : JSON.stringify(data);
}

// -- discovery and panels -----------------------------------------------------------------
async function discover() {
  const spec = (await api("GET", "/openapi.json")).data;
  TC.paths = spec.paths || {};
  const chans = (await api("GET", "/channels")).data;
  chans.forEach(c => TC.meta.set(c.name, c));
  // the block families the cell knows (GET /families): each with blocks has /{section}
  const fams = await api("GET", "/families");
  TC.families = fams.ok ? fams.data : [];
  for (const f of TC.families) {
    TC.blocks[f.section] = f.blocks.length && TC.paths["/" + f.section] ? (await api("GET", "/" + f.section)).data : [];
  }
}

// the blocks of a family by its name ("filter", "controller", ...), as GET /{section} gave them
const blocksOf = name => { const f = TC.families.find(x => x.name === name); return f ? TC.blocks[f.section] : []; };

const unitOf = name => (TC.meta.get(name) || {}).unit || "";
const exists = name => TC.meta.has(name);

function truthOf(name, prefix) {
  // the simulator's truth for an estimate: NAME_TRUE; for PREFIX_<STATE>, <STATE>_TRUE or
  // a unique ..._<STATE>_TRUE; an _EST or _HAT suffix names the estimate, not the quantity
  const rest = prefix && name.startsWith(prefix + "_") ? name.slice(prefix.length + 1) : name;
  for (const c of new Set([name, rest, name.replace(/_(EST|HAT)$/, ""), rest.replace(/_(EST|HAT)$/, "")])) {
    if (exists(c + "_TRUE")) return c + "_TRUE";
  }
  const base = rest.replace(/_(EST|HAT)$/, "");
  const hits = [...TC.meta.keys()].filter(n => n.endsWith("_" + base + "_TRUE"));
  return hits.length === 1 ? hits[0] : null;
}

function commonPrefix(names) {
  if (!names.length) return "";
  let p = names[0];
  for (const n of names) while (!n.startsWith(p)) p = p.slice(0, -1);
  return p.replace(/_+$/, "");
}

function families(names) {
  // channels that differ only in a number: AFR_CYL_1_EST .. AFR_CYL_4_EST -> AFR_CYL_#_EST
  const fam = new Map();
  for (const n of names) {
    const m = n.match(/^(.*?)_(\d+)((?:_.*)?)$/);
    if (!m) continue;
    const key = `${m[1]}_#${m[3]}`;
    if (!fam.has(key)) fam.set(key, []);
    fam.get(key).push({name: n, label: m[2], k: Number(m[2])});
  }
  return [...fam.entries()].filter(([, ms]) => ms.length >= 2)
    .map(([key, ms]) => ({key, members: ms.sort((a, b) => a.k - b.k)}));
}

function addPlot(id, title, traces, hlines) {
  traces = traces.filter((t, i, a) => exists(t.name) && a.findIndex(u => u.name === t.name) === i);
  if (!traces.length) return null;
  const p = new TimePlot($("plots"), {id, title, traces, hlines, store: TC.store, view: TC.view, onZoom: zoom});
  TC.plots.push(p);
  return p;
}

function buildPanels() {
  // one kind of panel per family: filters and controllers have their own; the blocks of any
  // other family (observers, a plugin's) are plotted as models of what they estimate
  for (const fam of TC.families) {
    const blocks = TC.blocks[fam.section] || [];
    if (fam.name === "filter") filterPanels(blocks);
    else if (fam.name === "controller") controllerPanels(blocks);
    else modelPanels(fam.name, blocks);
  }
}

function filterPanels(blocks) {
  // raw against moving average against Kalman against truth, per filtered input (each bank)
  const byInput = new Map();
  for (const f of blocks) {
    if (f.inputs.length !== 1) continue;
    if (!byInput.has(f.inputs[0])) byInput.set(f.inputs[0], []);
    byInput.get(f.inputs[0]).push(f.name);
  }
  for (const [input, filters] of byInput) {
    const u = unitOf(input);
    const scripts = [...TC.meta.values()].filter(c => c.name.startsWith(input + "_") && !filters.includes(c.name)
      && !c.name.endsWith("_TRUE") && c.unit === u && c.source !== "bus").map(c => c.name);
    addPlot(`filters-${input}`, `${input}: raw, filters and truth`, [
      {name: input, unit: u, width: 0.8},
      ...filters.map(n => ({name: n, unit: unitOf(n)})),
      {name: input + "_TRUE", unit: unitOf(input + "_TRUE"), width: 1.8},
      ...scripts.map(n => ({name: n, unit: u, hidden: true})),
    ]);
  }
}

function controllerPanels(controllers) {
  // each controller: feedback and valve position (its inputs), demand (its outputs), setpoint;
  // not its interlock (the engine's state, a number with no unit), which its mode reports
  for (const c of controllers) {
    const fb = c.params.feedback || c.inputs[0];
    const plotted = [fb, ...c.inputs, ...c.outputs].filter(n => n !== c.params.interlock);
    const traces = [...new Set(plotted)].map(n => ({name: n, unit: unitOf(n)}));
    const hl = c.params.setpoint === undefined ? [] : [{label: "setpoint", unit: unitOf(fb),
      value: () => { const b = blocksOf("controller").find(x => x.name === c.name); return b ? b.params.setpoint : NaN; }}];
    addPlot(`controller-${c.name}`, `controller ${c.name} (${c.kind})`, traces, hl);
  }
}

function modelPanels(family, blocks) {
  // each observer (or other model): its outputs grouped by unit, with their truth and
  // same-unit inputs; a bar panel for each family of numbered outputs
  for (const o of blocks) {
    // the estimates' common prefix; the contract's confidence and sigma bands (NAME_CONF,
    // X_SD) are named after the observer, not after a state, so they do not count
    const prefix = commonPrefix(o.outputs.filter(n => !/_(CONF|SD)$/.test(n)));
    const units = new Map();
    for (const n of o.outputs) {
      const u = unitOf(n);
      if (!units.has(u)) units.set(u, []);
      units.get(u).push(n);
    }
    for (const [u, outs] of units) {
      const traces = [];
      for (const n of outs) {
        traces.push({name: n, unit: u});
        const t = truthOf(n, prefix);
        if (t && unitOf(t) === u) traces.push({name: t, unit: u, width: 1.8});
      }
      for (const i of o.inputs) if (unitOf(i) === u) traces.push({name: i, unit: u, width: 0.8});
      addPlot(`${family}-${o.name}-${u || "none"}`, `${family} ${o.name}${u ? " [" + u + "]" : ""}`, traces);
    }
    for (const fam of families(o.outputs)) {
      const bp = new BarPlot($("plots"), {id: `bars-${fam.key}`, title: `${fam.key} (${family} ${o.name})`,
        members: fam.members, unit: unitOf(fam.members[0].name), store: TC.store});
      TC.plots.push(bp);
    }
  }
}

function plottedChannels() {
  const names = new Set();
  for (const p of TC.plots) {
    (p.traces || []).forEach(t => names.add(t.name));
    (p.members || []).forEach(m => names.add(m.name));
  }
  return [...names];
}

async function loadHistory() {
  await Promise.all(plottedChannels().map(async n => {
    const r = await api("GET", `/channels/${encodeURIComponent(n)}/history?seconds=${HISTORY_S}`);
    if (!r.ok) return;
    for (const p of r.data.points) TC.store.push(n, p.time, p.value === null ? NaN : p.value);
  }));
}

// -- the view: window, pause, zoom ---------------------------------------------------------
function dirtyAll() { TC.plots.forEach(p => { p.dirty = true; }); }

function zoom(range) {
  TC.view.zoom = range;
  $("unzoom").disabled = !range;
  dirtyAll();
}

function setupToolbar() {
  $("window").onchange = e => { TC.view.window = Number(e.target.value); dirtyAll(); };
  $("pause").onclick = () => {
    TC.view.paused = !TC.view.paused;
    TC.view.pausedAt = TC.store.latest;
    $("pause").textContent = TC.view.paused ? "resume" : "pause";
    dirtyAll();
  };
  $("unzoom").onclick = () => zoom(null);
  TC.view.window = Number($("window").value);
}

function frame() {
  for (const p of TC.plots) {
    if (!p.dirty) continue;
    const ms = p.draw();
    TC.perf.draws++; TC.perf.totalMs += ms; TC.perf.maxMs = Math.max(TC.perf.maxMs, ms);
  }
  requestAnimationFrame(frame);
}

// -- the stream ----------------------------------------------------------------------------
function connect() {
  // the token goes in a subprotocol (token.<TOKEN>), never in the URL: access logs record URLs
  const ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/stream`,
                           token() ? [`token.${token()}`] : []);
  TC.ws = ws;
  ws.onopen = () => { ws.send(JSON.stringify({subscribe: ["*"]})); };
  ws.onmessage = ev => {
    const m = JSON.parse(ev.data);
    if (m.type === "data" || m.type === "snapshot") {
      for (const [n, [v, s, t]] of Object.entries(m.values)) {
        TC.latest.set(n, {value: v, status: s, time: t});
        if (m.type === "data") TC.store.push(n, m.time, s === "ok" && v !== null ? v : NaN);
        if (!TC.meta.has(n)) TC.newChannels = true;
      }
      if (m.type === "data") { TC.messages++; TC.lastSeq = m.seq; TC.dropped = m.dropped; }
      if (!TC.view.paused && !TC.view.zoom) dirtyAll(); else TC.plots.forEach(p => { if (p.members) p.dirty = true; });
    } else if (m.type === "subscribed") {
      m.channels.forEach(c => { if (!TC.meta.has(c.name)) TC.meta.set(c.name, c); });
    } else if (m.type === "error") {
      $("stream-status").textContent = "stream: " + m.message;
    }
    streamStatus("ok");
  };
  ws.onclose = ev => {
    if (ev.code === 1008 && !TC.askedToken) {  // refused: reads need the cell's token
      TC.askedToken = true;
      const t = prompt(`The stream was refused (${ev.reason}). The cell's token:`);
      if (t) sessionStorage.setItem(TOKEN_KEY, t.trim());
    }
    streamStatus("closed"); setTimeout(connect, 1000);
  };
}

function streamStatus(state) {
  const el = $("stream-status");
  if (state === "closed") { el.textContent = "stream: disconnected, retrying…"; el.className = "stale"; return; }
  el.className = TC.dropped ? "stale" : "ok";
  el.textContent = `stream: ${TC.messages} ticks` + (TC.dropped ? `, ${TC.dropped} dropped (too slow)` : "");
}

// -- health and the channel table ------------------------------------------------------------
async function health() {
  const r = await api("GET", "/health");
  if (!r.ok) return;
  const h = r.data;
  $("health").textContent = `bus ${h.bus} · ${h.frames_per_s.toFixed(0)} frames/s · bus time ` +
    `${h.bus_time === null ? "–" : h.bus_time.toFixed(1)} s · decode errors ` +
    Object.entries(h.decode_errors).map(([k, v]) => `${k} ${v}`).join(", ");
  $("trip").hidden = !h.trip;
  if (h.trip) $("trip-text").textContent = `engine tripped: ${h.trip.reason} (since bus time ${h.trip.since.toFixed(1)} s)`;
}

// the two-step trip reset: the operator confirms, then the page sends the request and, with
// the challenge it returns, the confirm (the simulator wants both within 2 s)
async function resetTrip() {
  const msg = $("reset-msg");
  if (!window.confirm("Reset the engine trip? The simulator clears it only if its cause has cleared " +
                      "(back-pressure below the limit).")) return;
  const r = await api("POST", "/engine/reset", {});
  if (!r.ok) { msg.className = "msg error"; msg.textContent = `refused (${r.status}): ${errorText(r.data)}`; return; }
  const c = await api("POST", "/engine/reset/confirm", {challenge: r.data.challenge});
  msg.className = c.ok ? "msg ok" : "msg error";
  msg.textContent = c.ok ? "reset sent (request and confirm)" : `refused (${c.status}): ${errorText(c.data)}`;
  setTimeout(health, 500);
}

function fmtValue(v) { return v === null || v === undefined ? "–" : Math.abs(v) >= 1e5 || (v !== 0 && Math.abs(v) < 1e-3) ? v.toExponential(3) : Number(v.toPrecision(5)).toString(); }

function table() {
  const body = $("rows"), pat = $("filter").value.trim();
  const re = pat ? new RegExp("^" + pat.split("*").map(s => s.replace(/[.+?^${}()|[\]\\]/g, "\\$&")).join(".*"), "i") : null;
  const names = [...TC.meta.keys()].sort().filter(n => !re || re.test(n));
  if (body.dataset.names !== names.join(",")) {
    body.innerHTML = names.map(n => `<tr data-channel="${esc(n)}"><td>${esc(n)}</td><td class="v"></td>` +
      `<td>${esc(TC.meta.get(n).unit || "")}</td><td></td><td>${esc(TC.meta.get(n).source)}</td><td class="v"></td></tr>`).join("");
    body.dataset.names = names.join(",");
  }
  for (const row of body.rows) {
    const l = TC.latest.get(row.dataset.channel) || TC.meta.get(row.dataset.channel);
    if (!l) continue;
    row.cells[1].textContent = fmtValue(l.value);
    row.cells[3].textContent = l.status; row.cells[3].className = l.status;
    row.cells[5].textContent = l.time === null || l.time === undefined ? "–" : l.time.toFixed(2);
  }
}

async function refreshChannels() {
  if (!TC.newChannels) return;
  TC.newChannels = false;
  const r = await api("GET", "/channels");
  if (r.ok) r.data.forEach(c => TC.meta.set(c.name, c));
}

// -- tuning: every block of every family the cell has -------------------------------------------
function shown(v) { return typeof v === "string" ? v : JSON.stringify(v); }

function parseInput(text) {
  try { return JSON.parse(text); } catch (e) { return text; }
}

function tuningCard(section, b) {
  const div = document.createElement("div");
  div.className = "block"; div.dataset.block = b.name; div.dataset.section = section;
  div.innerHTML = `<span class="name">${esc(b.name)}</span> <span class="kind">${esc(b.kind)} · ` +
    `${esc(b.inputs.join(", "))} → ${esc(b.outputs.length > 3 ? b.outputs.length + " outputs" : b.outputs.join(", "))}</span>`;
  const fields = {};
  for (const [p, v] of Object.entries(b.params)) {
    const row = document.createElement("label"); row.className = "param";
    const input = document.createElement("input");
    if (typeof v === "boolean") { input.type = "checkbox"; input.checked = v; } else { input.type = "text"; input.value = shown(v); }
    if (typeof v === "string" && TC.meta.has(v)) input.setAttribute("list", "channel-names");  // e.g. feedback
    input.name = p; input.dataset.param = p;
    const applied = document.createElement("span"); applied.className = "applied"; applied.dataset.applied = p;
    applied.textContent = `applied: ${shown(v)}`;
    const cell = document.createElement("span"); cell.appendChild(input); cell.appendChild(applied);
    row.appendChild(document.createTextNode(p)); row.appendChild(cell);
    div.appendChild(row);
    fields[p] = {input, applied, value: v};
  }
  const btn = document.createElement("button"); btn.type = "button"; btn.textContent = "apply"; btn.className = "apply";
  const msg = document.createElement("span"); msg.className = "msg";
  div.appendChild(btn); div.appendChild(msg);
  btn.onclick = async () => {
    const changes = {};
    for (const [p, f] of Object.entries(fields)) {
      const now = f.input.type === "checkbox" ? f.input.checked : parseInput(f.input.value);
      if (JSON.stringify(now) !== JSON.stringify(f.value)) changes[p] = now;
    }
    if (!Object.keys(changes).length) { msg.className = "msg"; msg.textContent = "nothing changed"; return; }
    const r = await api("PATCH", `/${section}/${encodeURIComponent(b.name)}`, changes);
    if (r.ok) {
      for (const [p, v] of Object.entries(r.data.params)) {
        const f = fields[p]; if (!f) continue;
        f.value = v; f.applied.textContent = `applied: ${shown(v)}`;
        if (f.input.type === "checkbox") f.input.checked = v; else f.input.value = shown(v);
      }
      const i = TC.blocks[section].findIndex(x => x.name === b.name);
      if (i >= 0) TC.blocks[section][i] = r.data;
      msg.className = "msg ok"; msg.textContent = `applied: ${Object.keys(changes).join(", ")}`;
      dirtyAll();
    } else {
      msg.className = "msg error"; msg.textContent = `refused (${r.status}): ${errorText(r.data)}`;
    }
  };
  return div;
}

function buildTuning() {
  const root = $("tuning");
  const names = document.createElement("datalist"); names.id = "channel-names";
  for (const n of [...TC.meta.keys()].sort()) names.appendChild(new Option(n));
  root.appendChild(names);
  for (const {section} of TC.families) {
    if (!(TC.blocks[section] || []).length) continue;
    const h = document.createElement("h3"); h.textContent = section; root.appendChild(h);
    TC.blocks[section].forEach(b => root.appendChild(tuningCard(section, b)));
  }
}

// -- scripts -----------------------------------------------------------------------------------
function gutter(bad) {
  const lines = $("script-text").value.split("\n").length;
  $("script-text").rows = Math.max(14, lines + 1);
  $("script-gutter").innerHTML = Array.from({length: lines}, (_, i) =>
    bad && bad.has(i + 1) ? `<span class="bad" data-line="${i + 1}">${i + 1}</span>` : String(i + 1)).join("\n");
}

async function buildScripts() {
  const r = await api("GET", "/scripts");
  if (!r.ok) { $("scripts-box").hidden = true; return; }
  const pick = $("script-pick");
  for (const s of r.data) pick.add(new Option(`${s.name} (${s.dialect})`, s.name));
  pick.onchange = async () => {
    if (!pick.value) return;
    const s = await api("GET", `/scripts/${encodeURIComponent(pick.value)}`);
    if (s.ok) { $("script-name").value = pick.value; $("script-text").value = s.data.source; gutter(); }
  };
  $("script-file").onchange = async e => {
    const f = e.target.files[0]; if (!f) return;
    $("script-name").value = f.name; $("script-text").value = await f.text(); gutter();
  };
  $("script-text").oninput = () => gutter();
  $("script-upload").onclick = uploadScript;
  gutter();
}

async function uploadScript() {
  const name = $("script-name").value.trim(), out = $("script-result"), list = $("script-errors");
  list.innerHTML = "";
  const r = await api("PUT", `/scripts/${encodeURIComponent(name)}`, $("script-text").value, "text/plain");
  if (r.ok) {
    out.className = "ok"; out.textContent = `${r.data.name}: ${r.status === 201 ? "created" : "replaced"}, ` +
      `${r.data.outputs.length} outputs`;
    gutter(); TC.newChannels = true;
    return;
  }
  out.className = "invalid"; out.textContent = errorText(r.data);
  const bad = new Set();
  for (const e of (r.data && r.data.errors) || []) {
    bad.add(e.line);
    const li = document.createElement("li"); li.dataset.line = e.line;
    li.textContent = `line ${e.line}, column ${e.column}: ${e.message}` + (e.expected ? ` (expected ${e.expected})` : "");
    list.appendChild(li);
  }
  gutter(bad);
}

// -- simulator and scenario --------------------------------------------------------------------
async function buildSimulator() {
  const r = await api("GET", "/simulator");
  const el = $("simulator");
  if (!r.ok) { el.textContent = "no simulator information"; return; }
  const s = r.data;
  el.innerHTML = s.running
    ? `engine <b>${esc(s.engine || "default")}</b>, duty cycle <b>${esc(s.duty || "default")}</b>, ` +
      `speed ×${esc(s.speed)}, seed ${esc(s.seed)}<br><span class="hint">the cycle is chosen when the cell ` +
      `starts (<code>testcell up --engine … --duty …</code>); the API cannot change it while it runs</span>`
    : "no simulator runs in this cell (frames come from the bus)";
  // scenario changes: only when the API lists scenario keys (GET /scenario)
  if (!(TC.paths["/scenario"] && TC.paths["/scenario"].get && TC.paths["/scenario"].post)) return;
  const k = await api("GET", "/scenario");
  if (!k.ok) return;
  const raw = Array.isArray(k.data) ? k.data : (k.data.keys || Object.keys(k.data));
  const keys = raw.map(x => typeof x === "string" ? {key: x} : {key: x.key || x.name, ...x});
  if (!keys.length) return;
  const box = $("scenario"); box.hidden = false;
  box.innerHTML = "<h3>scenario</h3>";
  for (const key of keys) {
    const row = document.createElement("label"); row.className = "param";
    const range = key.minimum !== undefined && key.minimum !== null ? `${key.minimum}..${key.maximum} ` : "";
    const start = key.initial !== undefined && key.initial !== null ? ` (start ${key.initial})` : "";
    row.title = key.comment || key.signal || "";
    row.innerHTML = `${esc(key.key)}<span><input type="text" data-scenario="${esc(key.key)}" ` +
      `placeholder="${esc(range + (key.unit || "") + start)}"></span>`;
    box.appendChild(row);
  }
  const btn = document.createElement("button"); btn.type = "button"; btn.textContent = "send";
  const msg = document.createElement("span"); msg.className = "msg";
  box.appendChild(btn); box.appendChild(msg);
  btn.onclick = async () => {
    const body = {};
    box.querySelectorAll("input[data-scenario]").forEach(i => { if (i.value.trim()) body[i.dataset.scenario] = parseInput(i.value); });
    const r2 = await api("POST", "/scenario", body);
    msg.className = r2.ok ? "msg ok" : "msg error";
    msg.textContent = r2.ok ? `sent: ${JSON.stringify(body)}` : `refused (${r2.status}): ${errorText(r2.data)}`;
  };
}

// -- the synthetic redraw benchmark (benchmarks/bench_dashboard.py) ----------------------------
TC.bench = (traces, seconds, rateHz, draws) => {
  const store = new Store(Math.ceil(seconds * rateHz) + 8);
  const names = Array.from({length: traces}, (_, k) => `BENCH_${k}`);
  for (let i = 0; i < seconds * rateHz; i++) {
    const t = i / rateHz;
    names.forEach((n, k) => store.push(n, t, Math.sin(t / (5 + k)) * 100 + k * 20 + Math.random() * 10));
  }
  const host = document.createElement("div"); host.style.width = "1200px"; document.body.appendChild(host);
  const view = {window: seconds, paused: false, zoom: null};
  const p = new TimePlot(host, {id: "bench", title: "bench", store, view, onZoom: () => {},
    traces: names.map((n, k) => ({name: n, unit: k % 2 ? "mmH2O" : "%"}))});
  const ms = [];
  for (let i = 0; i < draws; i++) {
    store.push(names[0], store.latest + 1 / rateHz, 0);  // a new sample per redraw, as live
    ms.push(p.draw());
  }
  host.remove();
  ms.sort((a, b) => a - b);
  return {traces, points: seconds * rateHz, draws, mean_ms: ms.reduce((a, b) => a + b, 0) / ms.length,
          median_ms: ms[ms.length >> 1], max_ms: ms[ms.length - 1]};
};

// -- start ---------------------------------------------------------------------------------------
async function main() {
  setupToolbar();
  $("reset-trip").onclick = resetTrip;
  await discover();
  buildPanels();
  buildTuning();
  await Promise.all([buildScripts(), buildSimulator(), loadHistory(), health()]);
  connect();
  requestAnimationFrame(frame);
  table();
  setInterval(table, 500);
  setInterval(health, 2000);
  setInterval(refreshChannels, 2000);
  $("filter").oninput = table;
  TC.ready = true;
}

main().catch(e => { $("health").textContent = "the page could not start: " + e; throw e; });
