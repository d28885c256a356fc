// testcell's dashboard: discovers what the cell runs from the public HTTP API, plots it live
// from WS /stream, lists every channel, and tunes blocks, scripts and scenarios.
"use strict";

const HISTORY_S = 600;           // the longest window: 10 min
const TC = window.TC = {
  ready: false, messages: 0, dropped: 0, lastSeq: 0,
  store: new Store(Math.ceil(HISTORY_S * 10 * 1.1) + 16),
  view: {window: 60, paused: false, pausedAt: 0, zoom: null, axis: "start", start: NaN, clockOffset: 0},
  plots: [], latest: new Map(), meta: new Map(), families: [], blocks: {}, paths: {},
  custom: [], messages_: [], nextPanel: 1, loadedHistory: new Set(),
  perf: {draws: 0, totalMs: 0, maxMs: 0},
};

const $ = id => document.getElementById(id);
const esc = s => String(s).replace(/[&<>"]/g, c => ({"&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;"}[c]));

// The cell's token, when it has one (TESTCELL_TOKEN): typed into the token field, kept for
// this tab (sessionStorage), sent as a bearer token and as the WebSocket's subprotocol.
const TOKEN_KEY = "testcell-token";
const token = () => sessionStorage.getItem(TOKEN_KEY);

function tokenMessage(text, kind) {
  const m = $("token-msg");
  m.className = "msg " + (kind || ""); m.textContent = text;
  $("token").classList.toggle("needed", kind === "error");
}

function setupToken() {
  $("token").value = token() || "";
  if (token()) tokenMessage("token set for this tab", "ok");
  $("token-form").onsubmit = e => {
    e.preventDefault();
    const t = $("token").value.trim();
    if (t) sessionStorage.setItem(TOKEN_KEY, t); else sessionStorage.removeItem(TOKEN_KEY);
    tokenMessage(t ? "token set for this tab" : "no token", t ? "ok" : "");
    if (!TC.ready) { location.reload(); return; }  // reads were refused: start again with it
    if (TC.ws) TC.ws.close(4000, "new token");     // the stream reconnects with it
  };
}

async function api(method, url, body, type) {
  const init = {method, headers: {}};
  if (method !== "GET") {
    // the cell refuses a change that is not JSON (415), except a script's text/plain source
    init.headers["Content-Type"] = type || "application/json";
  }
  if (body !== undefined) init.body = type ? body : JSON.stringify(body);
  if (token()) init.headers["Authorization"] = `Bearer ${token()}`;
  const r = await fetch(url, init);
  if (r.status === 401) {
    tokenMessage(token() ? "the cell refused this token: enter its token (TESTCELL_TOKEN)"
                         : "this cell needs its token (TESTCELL_TOKEN): enter it here", "error");
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
class ReadsRefused extends Error {}

async function discover() {
  const r = await api("GET", "/openapi.json");
  if (r.status === 401) throw new ReadsRefused("reads need the cell's token: enter it above");
  const spec = r.data;
  TC.paths = spec.paths || {};
  const chans = (await api("GET", "/channels")).data;
  chans.forEach(c => TC.meta.set(c.name, c));
  // the block families the cell knows (GET /families): each with blocks has /{section}
  const fams = await api("GET", "/families");
  TC.families = fams.ok ? fams.data : [];
  for (const f of TC.families) {
    TC.blocks[f.section] = f.blocks.length && TC.paths["/" + f.section] ? (await api("GET", "/" + f.section)).data : [];
  }
  const msgs = TC.paths["/messages"] ? await api("GET", "/messages") : {ok: false};
  TC.messages_ = msgs.ok ? msgs.data : [];
}

// the blocks of a family by its name ("filter", "controller", ...), as GET /{section} gave them
const blocksOf = name => { const f = TC.families.find(x => x.name === name); return f ? TC.blocks[f.section] : []; };

const unitOf = name => (TC.meta.get(name) || {}).unit || "";
const exists = name => TC.meta.has(name);

function truthOf(name, prefix) {
  // the simulator's truth for an estimate: NAME_TRUE; for PREFIX_<STATE>, <STATE>_TRUE or
  // a unique ..._<STATE>_TRUE; an _EST or _HAT suffix names the estimate, not the quantity
  const rest = prefix && name.startsWith(prefix + "_") ? name.slice(prefix.length + 1) : name;
  for (const c of new Set([name, rest, name.replace(/_(EST|HAT)$/, ""), rest.replace(/_(EST|HAT)$/, ""),
                           stem(name), stem(rest)])) {
    if (exists(c + "_TRUE")) return c + "_TRUE";
    if (exists(c + "_TRUE_0")) return c + "_TRUE_0";  // a crank-angle stream's first sample
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

function addPlot(id, title, traces, hlines, extra) {
  traces = traces.filter((t, i, a) => exists(t.name) && a.findIndex(u => u.name === t.name) === i);
  if (!traces.length) return null;
  const p = new TimePlot((extra && extra.parent) || $("plots"),
                         {id, title, traces, hlines, store: TC.store, view: TC.view, onZoom: zoom, ...(extra || {})});
  p.auto = true;  // shown only once one of its channels has had a value
  TC.plots.push(p);
  return p;
}

function buildPanels() {
  // the panels of the messages of the user's DBC files first; then one kind of panel per
  // family: filters and controllers have their own; the blocks of any other family
  // (observers, a plugin's) are plotted as models of what they estimate
  messagePanels();
  for (const fam of TC.families) {
    const blocks = TC.blocks[fam.section] || [];
    if (fam.name === "filter") filterPanels(blocks);
    else if (fam.name === "controller") controllerPanels(blocks);
    else modelPanels(fam.name, blocks);
  }
}

function messagePanels() {
  // one panel per message of a user's DBC file (--dbc): its signals, one axis per unit;
  // a message of more than three units is split into one panel per unit
  for (const m of TC.messages_.filter(x => x.user)) {
    const chans = m.channels.filter(exists), byUnit = new Map();
    for (const n of chans) {
      const u = unitOf(n);
      if (!byUnit.has(u)) byUnit.set(u, []);
      byUnit.get(u).push(n);
    }
    const title = `${m.name} (0x${m.frame_id.toString(16).toUpperCase()}, ${m.file})`;
    const opts = {parent: $("message-plots")};
    if (byUnit.size <= 3) {
      addPlot(`message-${m.name}`, title, chans.map(n => ({name: n, unit: unitOf(n)})), [], opts);
    } else {
      for (const [u, names] of byUnit) {
        addPlot(`message-${m.name}-${u || "none"}`, `${title} [${u || "no unit"}]`,
                names.map(n => ({name: n, unit: u})), [], opts);
      }
    }
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

const controllerNow = name => blocksOf("controller").find(x => x.name === name);

function controllerState(c) {
  // what the panel says of a controller: disabled (off the bus) or its mode
  const b = controllerNow(c.name) || c;
  if (b.params.enable === false) return "disabled: off the bus, the valve holds its opening";
  return b.state && b.state.mode ? `mode ${b.state.mode}` : "";
}

function controllerPanels(controllers) {
  // each controller: feedback and valve position (its inputs), demand (its outputs), setpoint;
  // not its interlock (the engine's state, a number with no unit), which its mode reports.
  // The output's axis spans the controller's whole range (0..100 %), and the panel says when
  // the controller is disabled
  for (const c of controllers) {
    const fb = c.params.feedback || c.inputs[0];
    const plotted = [fb, ...c.inputs, ...c.outputs].filter(n => n !== c.params.interlock);
    const traces = [...new Set(plotted)].map(n => ({name: n, unit: unitOf(n)}));
    const hl = c.params.setpoint === undefined ? [] : [{label: "setpoint", unit: unitOf(fb),
      value: () => { const b = controllerNow(c.name); return b ? b.params.setpoint : NaN; }}];
    const fixed = {};
    const lo = c.params.out_min, hi = c.params.out_max;
    if (Number.isFinite(lo) && Number.isFinite(hi)) for (const o of c.outputs) fixed[unitOf(o)] = [lo, hi];
    const p = addPlot(`controller-${c.name}`, `controller ${c.name} (${c.kind})`, traces, hl,
                      {fixed, banner: () => { const b = controllerNow(c.name) || c; return b.params.enable === false ? "disabled" : ""; }});
    if (p) { p.controller = c.name; p.el.classList.add("controller"); controllerTitle(p); }
  }
}

function controllerTitle(p) {
  const c = controllerNow(p.controller); if (!c) return;
  const state = controllerState(c);
  p.titleEl.textContent = `controller ${c.name} (${c.kind})` + (state ? ` — ${state}` : "");
  p.el.classList.toggle("disabled", c.params.enable === false);
  p.dirty = true;
}

async function refreshControllers() {
  const f = TC.families.find(x => x.name === "controller");
  if (!f || !(TC.blocks[f.section] || []).length) return;
  const r = await api("GET", "/" + f.section);
  if (!r.ok) return;
  TC.blocks[f.section] = r.data;
  TC.plots.filter(p => p.controller).forEach(controllerTitle);
}

// -- observers: one panel per quantity ----------------------------------------------------------
const NOT_QUANTITY = /_(EST|HAT|SD|DEFAULT|TRUE)$/;
function stem(n) { let s = n, prev; do { prev = s; s = s.replace(NOT_QUANTITY, ""); } while (s !== prev); return s; }

function tokenPrefix(names) {
  // the common prefix of names, in whole words (AIRPATH_DEF of AIRPATH_DEF_P_IM_HAT, ...)
  if (names.length < 2) return "";
  const words = names.map(n => n.split("_"));
  const out = [];
  for (let i = 0; words.every(w => i < w.length - 1 && w[i] === words[0][i]); i++) out.push(words[0][i]);
  return out.join("_");
}

const sameQuantity = (a, b) => a === b || a.endsWith("_" + b) || b.endsWith("_" + a);

function quantityGroups(o) {
  // an observer's outputs by the quantity they estimate: the name less the observer's prefix,
  // less _EST/_HAT/_SD/_DEFAULT and less a number (AFR_CYL_1_EST -> AFR_CYL, PHI_2_EST -> PHI);
  // a predicted measurement (X_HAT) joins its state (DSL_P_IM_EST with AIRPATH_DEF_P_IM_HAT);
  // the contract's confidences (_CONF) make a group of their own
  const confs = o.outputs.filter(n => /_CONF$/.test(n));
  const rest = o.outputs.filter(n => !confs.includes(n));
  const hats = rest.filter(n => /_HAT$/.test(n));
  const states = rest.filter(n => !hats.includes(n) && !/_SD$/.test(n));
  const pre = tokenPrefix(states), hatPre = hats.length > 1 ? tokenPrefix(hats) : pre;
  const core = n => {
    let q = stem(n);
    const p = hats.includes(n) ? hatPre : pre;
    if (p && q.startsWith(p + "_")) q = q.slice(p.length + 1);
    return q.replace(/_\d+$/, "");
  };
  const groups = [];
  for (const n of [...states, ...hats, ...rest.filter(x => /_SD$/.test(x))]) {
    const q = core(n);
    let g = groups.find(x => sameQuantity(x.key, q));
    if (!g) { g = {key: q, outputs: []}; groups.push(g); }
    g.outputs.push(n);
  }
  if (confs.length) groups.push({key: "confidence", outputs: confs});
  return {groups, prefix: pre};
}

function modelPanels(family, blocks) {
  // each observer (or other model): a panel per quantity with its estimates, their truth and
  // the measured inputs of that quantity (one axis per unit); a bar panel for each family of
  // numbered outputs (e.g. AFR_CYL_1_EST..AFR_CYL_4_EST)
  for (const o of blocks) {
    const {groups} = quantityGroups(o);
    // the truth's prefix: the estimates' common prefix (not the confidence's or sigmas')
    const prefix = commonPrefix(o.outputs.filter(n => !/_(CONF|SD)$/.test(n)));
    for (const g of groups) {
      const traces = [];
      for (const n of g.outputs) {
        traces.push({name: n, unit: unitOf(n), hidden: /_SD$/.test(n)});
        const t = g.key === "confidence" ? null : truthOf(n, prefix);
        if (t) traces.push({name: t, unit: unitOf(t), width: 1.8});
      }
      if (g.key !== "confidence") {
        for (const i of o.inputs) if (sameQuantity(stem(i), g.key)) traces.push({name: i, unit: unitOf(i), width: 0.8});
      }
      addPlot(`${family}-${o.name}-${g.key}`, `${family} ${o.name}: ${g.key.replace(/_/g, " ")}`, traces);
    }
    for (const fam of families(o.outputs)) {
      const bp = new BarPlot($("plots"), {id: `bars-${fam.key}`, title: `${fam.key} (${family} ${o.name})`,
        members: fam.members, unit: unitOf(fam.members[0].name), store: TC.store});
      bp.auto = true;
      TC.plots.push(bp);
    }
  }
}

function showPanelsWithData() {
  // a panel of the cell's blocks shows once one of its channels has had a value: with --no-sim
  // on a user's bus, the engine's panels stay away until its frames do come
  for (const p of TC.plots) {
    if (!p.auto) continue;
    const names = (p.traces || []).map(t => t.name).concat((p.members || []).map(m => m.name));
    const has = names.some(n => TC.store.valued.has(n) || ((TC.meta.get(n) || {}).value ?? null) !== null);
    if (p.el.hidden === has) { p.el.hidden = !has; p.dirty = true; }
  }
}

// -- custom panels: any channels, kept in the address (#panels=A,B|C) -------------------------------
function parseLayout(hash) {
  const out = {panels: [], window: null, axis: null};
  for (const part of hash.replace(/^#/, "").split("&")) {
    const [k, v] = part.split("=");
    if (v === undefined) continue;
    if (k === "panels") out.panels = v.split("|").map(p => p.split(",").filter(Boolean).map(decodeURIComponent));
    else if (k === "window") out.window = Number(v);
    else if (k === "time") out.axis = decodeURIComponent(v);
  }
  return out;
}

function layoutHash() {
  const parts = [];
  if (TC.custom.length) parts.push("panels=" + TC.custom.map(c => c.channels.map(encodeURIComponent).join(",")).join("|"));
  parts.push(`window=${TC.view.window}`, `time=${TC.view.axis}`);
  return "#" + parts.join("&");
}

function saveLayout() {
  TC.savedHash = layoutHash();
  if (location.hash !== TC.savedHash) history.replaceState(null, "", TC.savedHash);
  const sel = $("plot-target"), keep = sel.value;
  sel.innerHTML = '<option value="new">a new panel</option>' +
    TC.custom.map(c => `<option value="${c.id}">${esc(c.title)}</option>`).join("");
  sel.value = TC.custom.some(c => c.id === keep) ? keep : (TC.custom.length ? TC.custom[TC.custom.length - 1].id : "new");
}

function renderCustom(c) {
  const missing = c.channels.filter(n => !exists(n));
  const p = new TimePlot($("custom-plots"), {
    id: c.id, title: c.title + (missing.length ? ` (no such channel here: ${missing.join(", ")})` : ""),
    traces: c.channels.filter(exists).map(n => ({name: n, unit: unitOf(n)})),
    store: TC.store, view: TC.view, onZoom: zoom,
    empty: "click a channel in the table below to plot it here",
    onRemove: () => removePanel(c), onRemoveTrace: n => removeTrace(c, n)});
  p.el.classList.add("custom");
  if (c.plot) {
    c.plot.el.replaceWith(p.el);
    TC.plots[TC.plots.indexOf(c.plot)] = p;
  } else {
    TC.plots.push(p);
  }
  c.plot = p;
}

function newPanel(channels) {
  const n = TC.nextPanel++;
  const c = {id: `custom-${n}`, title: `panel ${n}`, channels: [...new Set(channels || [])], plot: null};
  TC.custom.push(c);
  renderCustom(c);
  return c;
}

function removePanel(c) {
  c.plot.el.remove();
  TC.plots.splice(TC.plots.indexOf(c.plot), 1);
  TC.custom.splice(TC.custom.indexOf(c), 1);
  saveLayout();
}

function removeTrace(c, name) {
  c.channels = c.channels.filter(n => n !== name);
  renderCustom(c); saveLayout();
}

async function loadChannelHistory(names) {
  // the history of channels the store holds only since the page loaded (the stream's ticks)
  await Promise.all(names.filter(n => exists(n) && !TC.loadedHistory.has(n)).map(async n => {
    TC.loadedHistory.add(n);
    const r = await api("GET", `/channels/${encodeURIComponent(n)}/history?seconds=${HISTORY_S}`);
    if (!r.ok) return;
    TC.store.merge(n, r.data.points.map(p => [p.time, p.value === null ? NaN : p.value]));
  }));
  setStart();
  dirtyAll();
}

async function plotChannel(name) {
  // click-to-plot: add a channel of the table to the chosen panel (or a new one)
  const target = $("plot-target").value;
  let c = TC.custom.find(x => x.id === target);
  if (!c) c = newPanel([name]);
  else if (!c.channels.includes(name)) { c.channels.push(name); renderCustom(c); }
  saveLayout();
  await loadChannelHistory([name]);
}

function applyLayout(layout) {
  // a bookmarked or shared address: its panels replace the custom ones shown
  for (const c of [...TC.custom]) { c.plot.el.remove(); TC.plots.splice(TC.plots.indexOf(c.plot), 1); }
  TC.custom = []; TC.nextPanel = 1;
  for (const chans of layout.panels) newPanel(chans);
  if (layout.window && [...$("window").options].some(o => Number(o.value) === layout.window)) {
    $("window").value = String(layout.window); TC.view.window = layout.window;
  }
  if (layout.axis === "start" || layout.axis === "clock") { $("time-axis").value = layout.axis; TC.view.axis = layout.axis; }
  saveLayout();
  dirtyAll();
  return loadChannelHistory(layout.panels.flat());
}

function setStart() {
  // "since start": the earliest sample the page holds (loaded history reaches 10 min back)
  let first = Infinity;
  for (const s of TC.store.series.values()) if (s.n && s.firstTime() < first) first = s.firstTime();
  if (Number.isFinite(first) && !(first >= TC.view.start)) { TC.view.start = first; dirtyAll(); }
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
  await loadChannelHistory(plottedChannels());
}

// -- the view: window, pause, zoom ---------------------------------------------------------
function dirtyAll() { TC.plots.forEach(p => { p.dirty = true; }); }

function zoom(range) {
  TC.view.zoom = range;
  $("unzoom").disabled = !range;
  dirtyAll();
}

function setupToolbar() {
  $("window").onchange = e => { TC.view.window = Number(e.target.value); dirtyAll(); saveLayout(); };
  $("time-axis").onchange = e => { TC.view.axis = e.target.value; dirtyAll(); saveLayout(); };
  $("new-panel").onclick = () => { const c = newPanel([]); saveLayout(); $("plot-target").value = c.id; };
  $("pause").onclick = () => {
    TC.view.paused = !TC.view.paused;
    TC.view.pausedAt = TC.store.latest;
    $("pause").textContent = TC.view.paused ? "resume" : "pause";
    dirtyAll();
  };
  $("unzoom").onclick = () => zoom(null);
  TC.view.window = Number($("window").value);
  TC.view.axis = $("time-axis").value;
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
      // clock time: bus time is seconds since the epoch when the bus stamps frames on receipt
      // (udp_multicast); else (a replayed log's own times) the wall clock now less the tick's time
      TC.view.clockOffset = m.time > 1e9 ? 0 : Date.now() / 1000 - m.time;
      for (const [n, [v, s, t]] of Object.entries(m.values)) {
        TC.latest.set(n, {value: v, status: s, time: t});
        if (m.type === "data") TC.store.push(n, m.time, s === "ok" && v !== null ? v : NaN);
        if (!TC.meta.has(n)) TC.newChannels = true;
      }
      if (m.type === "data") { TC.messages++; TC.lastSeq = m.seq; TC.dropped = m.dropped; }
      if (!Number.isFinite(TC.view.start)) setStart();
      if (!TC.view.paused && !TC.view.zoom) dirtyAll(); else TC.plots.forEach(p => { if (p.members) p.dirty = true; });
    } else if (m.type === "subscribed") {
      m.channels.forEach(c => { if (!TC.meta.has(c.name)) TC.newChannels = true; });
    } else if (m.type === "error") {
      $("stream-status").textContent = "stream: " + m.message;
    }
    streamStatus("ok");
  };
  ws.onclose = ev => {
    if (ev.code === 1008) tokenMessage(`the stream was refused (${ev.reason}): enter the cell's token`, "error");
    streamStatus("closed"); setTimeout(connect, ev.code === 4000 ? 0 : 1000);
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
    body.innerHTML = names.map(n => `<tr data-channel="${esc(n)}"><td class="plot" title="click to plot">${esc(n)}</td><td class="v"></td>` +
      `<td>${esc(TC.meta.get(n).unit || "")}</td><td></td><td>${esc(TC.meta.get(n).source)}</td><td class="v"></td></tr>`).join("");
    body.dataset.names = names.join(",");
  }
  for (const row of body.rows) {
    const l = TC.latest.get(row.dataset.channel) || TC.meta.get(row.dataset.channel);
    if (!l) continue;
    // a value table's label (VAL_) beside the value, when the channel has one
    const label = l.label ?? (TC.meta.get(row.dataset.channel) || {}).label;
    row.cells[1].textContent = fmtValue(l.value) + (label !== undefined && label !== null && l.value === (TC.meta.get(row.dataset.channel) || {}).value ? ` (${label})` : "");
    row.cells[3].textContent = l.status; row.cells[3].className = l.status;
    row.cells[5].textContent = l.time === null || l.time === undefined ? "–" : l.time.toFixed(2);
  }
}

async function refreshChannels() {
  // new channels (a script uploaded), and the labels of value tables, which the stream lacks
  if (!TC.newChannels && !TC.hasLabels) return;
  TC.newChannels = false;
  const before = TC.meta.size;
  const r = await api("GET", "/channels");
  if (r.ok) r.data.forEach(c => TC.meta.set(c.name, c));
  TC.hasLabels = [...TC.meta.values()].some(c => c.label !== undefined && c.label !== null);
  if (TC.meta.size > before) await rebuildPanels();
}

async function rebuildPanels() {
  // channels that came after the page was built (a cell still starting, a user's bus that
  // began later, a script uploaded): the panels of the blocks and messages again, with them
  for (const p of TC.plots.filter(x => x.auto)) p.el.remove();
  TC.plots = TC.plots.filter(x => !x.auto);
  buildPanels();
  for (const c of TC.custom) if (c.plot.traces.length < c.channels.filter(exists).length) renderCustom(c);
  await loadChannelHistory(plottedChannels());
  showPanelsWithData();
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
  // only the keys the running engine reads (read_by_engine), not another engine's; the trip
  // reset's two steps are the reset button's
  const keys = raw.map(x => typeof x === "string" ? {key: x} : {key: x.key || x.name, ...x})
    .filter(k => k.read_by_engine !== false && !/^ENGINE_RESET_/.test(k.signal || ""));
  if (!keys.length) return;
  const box = $("scenario"); box.hidden = false;
  box.innerHTML = "<h3>scenario</h3>";
  for (const key of keys) {
    const row = document.createElement("label"); row.className = "scenario-key";
    const range = key.minimum !== undefined && key.minimum !== null ? `${key.minimum}..${key.maximum} ` : "";
    const start = key.initial !== undefined && key.initial !== null ? ` (start ${key.initial})` : "";
    row.title = key.signal ? `${key.signal} in ${key.message || "its message"}` : "";
    row.innerHTML = `<span class="key">${esc(key.key)}</span>` +
      (key.comment ? `<span class="comment">${esc(key.comment)}</span>` : "") +
      `<input type="text" data-scenario="${esc(key.key)}" placeholder="${esc(range + (key.unit || "") + start)}">`;
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
  setupToken();
  setupToolbar();
  $("reset-trip").onclick = resetTrip;
  try {
    await discover();
  } catch (e) {
    if (!(e instanceof ReadsRefused)) throw e;
    $("health").textContent = e.message;
    return;
  }
  buildPanels();
  buildTuning();
  await Promise.all([buildScripts(), buildSimulator(), loadHistory(), health(),
                     applyLayout(parseLayout(location.hash))]);
  showPanelsWithData();
  connect();
  requestAnimationFrame(frame);
  table();
  setInterval(table, 500);
  setInterval(health, 2000);
  setInterval(refreshChannels, 2000);
  setInterval(refreshControllers, 2000);
  setInterval(showPanelsWithData, 1000);
  $("filter").oninput = table;
  $("rows").onclick = e => {
    const td = e.target.closest("td.plot");
    if (td) plotChannel(td.parentElement.dataset.channel);
  };
  // an address pasted or edited by hand: its layout replaces the custom panels
  window.addEventListener("hashchange", () => { if (location.hash !== TC.savedHash) applyLayout(parseLayout(location.hash)); });
  TC.ready = true;
}

main().catch(e => { $("health").textContent = "the page could not start: " + e; throw e; });
