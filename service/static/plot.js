// testcell's canvas plotting: a ring-buffer store of channel samples, time plots with one
// y axis per unit, and bar plots. Written for this project; no third-party code.
//
// Speed: a redraw visits only the samples inside the visible window (binary search for
// the first) and draws at most four points per pixel column and trace (first, min, max,
// last of the column), so 20 traces of 6000 samples (10 min at 10 Hz) cost one pass over
// 120k numbers and a few thousand line segments.
"use strict";

const TC_COLORS = ["#0969da", "#cf222e", "#1a7f37", "#8250df", "#bc4c00", "#0a7e8c", "#953800",
  "#6e7781", "#d4a72c", "#e85aad", "#2da44e", "#57606a", "#1f6feb", "#a40e26", "#116329",
  "#6639ba", "#fb8f44", "#3192aa", "#7d4e00", "#bf3989"];

class Series {
  // One channel's samples in a ring buffer: bus time and value (NaN where not ok).
  constructor(name, capacity) {
    this.name = name;
    this.cap = capacity;
    this.t = new Float64Array(capacity);
    this.v = new Float64Array(capacity);
    this.start = 0;   // index of the oldest sample
    this.n = 0;       // samples held
  }
  push(t, v) {
    if (this.n && t <= this.t[(this.start + this.n - 1) % this.cap]) return false;
    const k = (this.start + this.n) % this.cap;
    this.t[k] = t; this.v[k] = v;
    if (this.n < this.cap) this.n++; else this.start = (this.start + 1) % this.cap;
    return true;
  }
  at(i) { return (this.start + i) % this.cap; }
  firstTime() { return this.n ? this.t[this.start] : NaN; }
  lastTime() { return this.n ? this.t[this.at(this.n - 1)] : NaN; }
  lastValue() { return this.n ? this.v[this.at(this.n - 1)] : NaN; }
  // index (0..n) of the first sample with time >= t
  lowerBound(t) {
    let lo = 0, hi = this.n;
    while (lo < hi) { const mid = (lo + hi) >> 1; if (this.t[this.at(mid)] < t) lo = mid + 1; else hi = mid; }
    return lo;
  }
}

class Store {
  // Every channel's samples; capacity covers the longest window (10 min at 10 Hz, plus slack).
  constructor(capacity) { this.capacity = capacity; this.series = new Map(); this.latest = 0; this.valued = new Set(); }
  get(name) {
    let s = this.series.get(name);
    if (!s) { s = new Series(name, this.capacity); this.series.set(name, s); }
    return s;
  }
  push(name, t, v) {
    if (v === v) this.valued.add(name);  // a channel that has had a value (not only NaN)
    if (this.get(name).push(t, v) && t > this.latest) this.latest = t;
  }
  count(name) { const s = this.series.get(name); return s ? s.n : 0; }
  // older samples (a channel's history, loaded when it is first plotted) before those held
  merge(name, points) {
    const old = this.get(name), fresh = new Series(name, this.capacity);
    const first = old.n ? old.firstTime() : Infinity;
    for (const [t, v] of points) if (t < first) { fresh.push(t, v); if (v === v) this.valued.add(name); }
    for (let i = 0; i < old.n; i++) fresh.push(old.t[old.at(i)], old.v[old.at(i)]);
    this.series.set(name, fresh);
    if (fresh.n && fresh.lastTime() > this.latest) this.latest = fresh.lastTime();
  }
}

function clockText(t, step) {
  // a bus time in seconds since the epoch as the local clock, with the decimals the step needs
  const d = new Date(t * 1000), p = n => String(n).padStart(2, "0");
  let s = `${p(d.getHours())}:${p(d.getMinutes())}:${p(d.getSeconds())}`;
  if (step < 1) s += "." + String(d.getMilliseconds()).padStart(3, "0").slice(0, step < 0.1 ? 2 : 1);
  return s;
}

// The time axis of every plot: seconds since the start of the data (view.start, bus time),
// or the clock (bus time + view.clockOffset is seconds since the epoch)
function timeAxis(view) {
  if (view.axis === "clock") {
    const off = view.clockOffset || 0;
    return {base: -off, label: (t, step) => clockText(t + off, step), title: "clock time"};
  }
  const start = Number.isFinite(view.start) ? view.start : 0;
  const since = Number.isFinite(view.start) ? ` (start ${clockText(start + (view.clockOffset || 0), 1)})` : "";
  return {base: start, label: (t, step) => fmtTick(t - start, step), title: `seconds since start${since}`};
}

function niceStep(span, target) {
  const raw = span / Math.max(1, target), p = Math.pow(10, Math.floor(Math.log10(raw)));
  for (const m of [1, 2, 2.5, 5, 10]) if (m * p >= raw) return m * p;
  return 10 * p;
}

function stepDecimals(step) {
  // the decimals that write every multiple of a tick step exactly (0.05 -> 2, 2.5 -> 1)
  for (let d = 0; d < 9; d++) {
    const x = step * Math.pow(10, d);
    if (Math.abs(x - Math.round(x)) < 1e-6 * Math.max(1, x)) return d;
  }
  return 9;
}

function fmtTick(v, step) {
  const a = Math.abs(v);
  if (a !== 0 && (a >= 1e6 || a < 1e-4 || step < 1e-6)) return v.toExponential(2);
  return v.toFixed(stepDecimals(step));
}

function fmtNum(v) {
  const a = Math.abs(v);
  if (a === 0) return "0";
  if (a >= 1e5 || a < 1e-3) return v.toExponential(1);
  if (a >= 100) return v.toFixed(0);
  if (a >= 10) return v.toFixed(1);
  return v.toPrecision(3);
}

class TimePlot {
  // A time plot: traces [{name, unit, color, hidden}], horizontal lines [{label, unit, value()}].
  constructor(parent, opts) {
    this.store = opts.store;
    this.view = opts.view;             // shared {window, paused, zoom: null | [t0, t1]}
    this.traces = opts.traces.map((tr, i) => ({color: TC_COLORS[i % TC_COLORS.length], ...tr}));
    this.hlines = opts.hlines || [];
    this.fixed = opts.fixed || {};     // unit -> [lo, hi]: an axis that does not auto-scale
    this.banner = opts.banner || null; // () -> text drawn across the plot (e.g. "disabled"), or ""
    this.units = [...new Set([...this.traces.map(t => t.unit), ...this.hlines.map(h => h.unit)])];
    this.el = document.createElement("div");
    this.el.className = "panel";
    this.el.dataset.panel = opts.id;
    const h = document.createElement("h3");
    this.titleEl = document.createElement("span"); this.titleEl.className = "title";
    this.titleEl.textContent = opts.title; h.appendChild(this.titleEl);
    if (opts.onRemove) {
      const x = document.createElement("button"); x.type = "button"; x.className = "remove-panel";
      x.textContent = "remove panel"; x.onclick = opts.onRemove; h.appendChild(x);
    }
    this.el.appendChild(h);
    if (!this.traces.length && opts.empty) {
      const e = document.createElement("div"); e.className = "hint"; e.textContent = opts.empty; this.el.appendChild(e);
    }
    this.legend = document.createElement("div"); this.legend.className = "legend";
    this.traces.forEach(tr => {
      const item = document.createElement("span");
      item.className = "item" + (tr.hidden ? " off" : "");
      item.dataset.channel = tr.name;
      item.innerHTML = `<i style="background:${tr.color}"></i>`;
      item.appendChild(document.createTextNode(`${tr.name} [${tr.unit || "–"}]`));
      item.title = "click to show or hide";
      item.onclick = () => { tr.hidden = !tr.hidden; item.classList.toggle("off", tr.hidden); this.dirty = true; };
      if (opts.onRemoveTrace) {
        const x = document.createElement("b"); x.className = "remove-trace"; x.textContent = " ×";
        x.title = "remove from this panel";
        x.onclick = e => { e.stopPropagation(); opts.onRemoveTrace(tr.name); };
        item.appendChild(x);
      }
      this.legend.appendChild(item);
    });
    this.el.appendChild(this.legend);
    this.canvas = document.createElement("canvas");
    this.canvas.height = opts.height || 240;
    this.el.appendChild(this.canvas);
    parent.appendChild(this.el);
    this.dirty = true;
    this.lastDrawMs = 0;
    this._drag = null;
    this.canvas.addEventListener("mousedown", e => { this._drag = [e.offsetX, e.offsetX]; });
    this.canvas.addEventListener("mousemove", e => { if (this._drag) { this._drag[1] = e.offsetX; this.dirty = true; } });
    window.addEventListener("mouseup", () => {
      if (!this._drag || !this.el.isConnected) return;
      const [a, b] = this._drag; this._drag = null;
      if (Math.abs(a - b) > 4 && this._geom) {
        const g = this._geom, x0 = Math.min(a, b), x1 = Math.max(a, b);
        opts.onZoom([g.t0 + (x0 - g.left) / g.pxs, g.t0 + (x1 - g.left) / g.pxs]);
      }
      this.dirty = true;
    });
    this.canvas.addEventListener("dblclick", () => opts.onZoom(null));
  }

  range() {
    // the visible time range: the zoom, else the window ending at the newest sample
    if (this.view.zoom) return this.view.zoom;
    const end = this.view.paused ? this.view.pausedAt : this.store.latest;
    return [end - this.view.window, end];
  }

  draw() {
    const started = performance.now();
    const cv = this.canvas, dpr = window.devicePixelRatio || 1;
    const cssW = Math.max(200, this.el.clientWidth - 2), cssH = cv.height / (cv._dpr || 1);
    if (cv._cssW !== cssW || cv._dpr !== dpr) {
      cv._cssW = cssW; cv._dpr = dpr;
      cv.style.width = cssW + "px"; cv.style.height = cssH + "px";
      cv.width = Math.round(cssW * dpr); cv.height = Math.round(cssH * dpr);
    }
    const g = cv.getContext("2d");
    g.setTransform(dpr, 0, 0, dpr, 0, 0);
    g.clearRect(0, 0, cssW, cssH);
    g.font = "11px system-ui, sans-serif";
    const AX = 54, nL = Math.ceil(this.units.length / 2), nR = Math.floor(this.units.length / 2);
    const left = 8 + AX * nL, right = cssW - 8 - AX * nR, top = 8, bottom = cssH - 34;
    const [t0, t1] = this.range();
    const pxs = (right - left) / Math.max(t1 - t0, 1e-9);
    this._geom = {t0, left, pxs};
    // y ranges per unit over the visible samples
    const ranges = new Map(this.units.map(u => [u, [Infinity, -Infinity]]));
    const visible = this.traces.filter(tr => !tr.hidden);
    const spans = visible.map(tr => {
      const s = this.store.series.get(tr.name);
      if (!s || !s.n) return null;
      const i0 = Math.max(0, s.lowerBound(t0) - 1), i1 = Math.min(s.n, s.lowerBound(t1) + 1);
      const r = ranges.get(tr.unit);
      for (let i = i0; i < i1; i++) {
        const v = s.v[s.at(i)];
        if (v === v) { if (v < r[0]) r[0] = v; if (v > r[1]) r[1] = v; }
      }
      return [s, i0, i1];
    });
    for (const h of this.hlines) {
      const v = h.value(), r = ranges.get(h.unit);
      if (Number.isFinite(v)) { r[0] = Math.min(r[0], v); r[1] = Math.max(r[1], v); }
    }
    const scales = new Map();
    this.units.forEach((u, k) => {
      let [lo, hi] = ranges.get(u);
      if (this.fixed[u]) {
        // a fixed axis (a valve's 0..100 %) that still shows a value beyond it
        lo = Math.min(this.fixed[u][0], lo <= hi ? lo : Infinity); hi = Math.max(this.fixed[u][1], lo <= hi ? hi : -Infinity);
      }
      if (!(lo <= hi)) { lo = 0; hi = 1; }
      if (hi - lo < 1e-9 * Math.max(1, Math.abs(hi))) {
        const c = (lo + hi) / 2, d = Math.max(1e-6, Math.abs(c) * 0.01); lo = c - d; hi = c + d;
      }
      const pad = 0.05 * (hi - lo); lo -= pad; hi += pad;
      scales.set(u, {lo, hi, side: k % 2 ? "R" : "L", slot: k >> 1,
        y: v => bottom - (bottom - top) * (v - lo) / (hi - lo)});
    });
    // frame, grid and time axis
    g.strokeStyle = "#d0d7de"; g.lineWidth = 1; g.strokeRect(left, top, right - left, bottom - top);
    const step = niceStep(t1 - t0, Math.max(2, (right - left) / 90));
    // ticks at round seconds since start, or of the clock
    const axis = timeAxis(this.view);
    this.axisTitle = axis.title;
    g.fillStyle = "#57606a"; g.textAlign = "center"; g.textBaseline = "top";
    for (let k = Math.ceil((t0 - axis.base) / step); axis.base + k * step <= t1 + 1e-9; k++) {
      const t = axis.base + k * step, x = left + (t - t0) * pxs;
      g.strokeStyle = "#eaeef2"; g.beginPath(); g.moveTo(x, top); g.lineTo(x, bottom); g.stroke();
      g.fillText(axis.label(t, step), x, bottom + 3);
    }
    g.fillText(axis.title, (left + right) / 2, bottom + 18);
    // one y axis per unit
    for (const [u, sc] of scales) {
      const x = sc.side === "L" ? left - sc.slot * AX : right + sc.slot * AX;
      g.strokeStyle = "#8c959f"; g.beginPath(); g.moveTo(x, top); g.lineTo(x, bottom); g.stroke();
      const ys = niceStep(sc.hi - sc.lo, Math.max(2, (bottom - top) / 40));
      g.textAlign = sc.side === "L" ? "right" : "left"; g.textBaseline = "middle"; g.fillStyle = "#57606a";
      for (let v = Math.ceil(sc.lo / ys) * ys; v <= sc.hi; v += ys) {
        const y = sc.y(v);
        g.beginPath(); g.moveTo(x, y); g.lineTo(x + (sc.side === "L" ? -3 : 3), y); g.stroke();
        g.fillText(fmtTick(v, ys), x + (sc.side === "L" ? -5 : 5), y);
        if (sc.slot === 0 && sc.side === "L") { g.strokeStyle = "#f0f3f6"; g.beginPath(); g.moveTo(left, y); g.lineTo(right, y); g.stroke(); g.strokeStyle = "#8c959f"; }
      }
      g.save(); g.translate(sc.side === "L" ? x - AX + 10 : x + AX - 10, (top + bottom) / 2);
      g.rotate(-Math.PI / 2); g.textAlign = "center"; g.fillStyle = "#24292f";
      g.fillText(u || "(no unit)", 0, 0); g.restore();
    }
    // traces, decimated to first/min/max/last per pixel column
    g.save(); g.beginPath(); g.rect(left, top, right - left, bottom - top); g.clip();
    visible.forEach((tr, k) => {
      const span = spans[k];
      if (!span) return;
      const [s, i0, i1] = span, sc = scales.get(tr.unit), T = s.t, V = s.v;
      g.strokeStyle = tr.color; g.lineWidth = tr.width || 1.4; g.beginPath();
      let col = NaN, pen = false, fy = 0, mn = 0, mx = 0, ly = 0, cx = 0;
      const flush = () => {
        if (col !== col) return;
        if (pen) g.lineTo(cx, fy); else g.moveTo(cx, fy);
        if (mn !== fy) g.lineTo(cx, mn);
        if (mx !== mn) g.lineTo(cx, mx);
        g.lineTo(cx, ly); pen = true;
      };
      for (let i = i0; i < i1; i++) {
        const j = s.at(i), v = V[j];
        if (v !== v) { flush(); col = NaN; pen = false; continue; }
        const x = left + (T[j] - t0) * pxs, c = Math.floor(x), y = sc.y(v);
        if (c !== col) { flush(); col = c; cx = x; fy = mn = mx = ly = y; }
        else { if (y < mn) mn = y; if (y > mx) mx = y; ly = y; }
      }
      flush();
      g.stroke();
    });
    for (const h of this.hlines) {
      const v = h.value(); if (!Number.isFinite(v)) continue;
      const y = scales.get(h.unit).y(v);
      g.setLineDash([6, 4]); g.strokeStyle = "#24292f"; g.lineWidth = 1;
      g.beginPath(); g.moveTo(left, y); g.lineTo(right, y); g.stroke(); g.setLineDash([]);
      const below = y - 14 < top;  // a line at the top keeps its label inside the frame
      g.fillStyle = "#24292f"; g.textAlign = "left"; g.textBaseline = below ? "top" : "bottom";
      g.fillText(`${h.label} ${fmtNum(v)}`, left + 4, below ? y + 2 : y - 2);
    }
    g.restore();
    const banner = this.banner ? this.banner() : "";
    if (banner) {
      g.font = "bold 14px system-ui, sans-serif"; g.textAlign = "center"; g.textBaseline = "middle";
      const w = g.measureText(banner).width + 24, cx = (left + right) / 2, cy = (top + bottom) / 2;
      g.fillStyle = "rgba(255,255,255,.85)"; g.fillRect(cx - w / 2, cy - 14, w, 28);
      g.strokeStyle = "#9a6700"; g.strokeRect(cx - w / 2, cy - 14, w, 28);
      g.fillStyle = "#9a6700"; g.fillText(banner, cx, cy);
      g.font = "11px system-ui, sans-serif";
    }
    this.bannerText = banner;
    this.scales = scales;
    if (this._drag) {
      const [a, b] = this._drag;
      g.fillStyle = "rgba(9,105,218,.12)"; g.fillRect(Math.min(a, b), top, Math.abs(a - b), bottom - top);
    }
    this.dirty = false;
    this.lastDrawMs = performance.now() - started;
    return this.lastDrawMs;
  }
}

class BarPlot {
  // The latest value of each member of a channel family (e.g. AFR_CYL_1_EST .. AFR_CYL_4_EST).
  constructor(parent, opts) {
    this.store = opts.store; this.members = opts.members; this.unit = opts.unit;
    this.el = document.createElement("div"); this.el.className = "panel"; this.el.dataset.panel = opts.id;
    const h = document.createElement("h3"); h.textContent = opts.title; this.el.appendChild(h);
    this.canvas = document.createElement("canvas"); this.canvas.height = opts.height || 200;
    this.el.appendChild(this.canvas); parent.appendChild(this.el); this.dirty = true;
  }
  draw() {
    const started = performance.now();
    const cv = this.canvas, dpr = window.devicePixelRatio || 1;
    const cssW = Math.max(200, this.el.clientWidth - 2), cssH = cv.height / (cv._dpr || 1);
    if (cv._cssW !== cssW || cv._dpr !== dpr) {
      cv._cssW = cssW; cv._dpr = dpr; cv.style.width = cssW + "px"; cv.style.height = cssH + "px";
      cv.width = Math.round(cssW * dpr); cv.height = Math.round(cssH * dpr);
    }
    const g = cv.getContext("2d"); g.setTransform(dpr, 0, 0, dpr, 0, 0); g.clearRect(0, 0, cssW, cssH);
    g.font = "11px system-ui, sans-serif";
    const vals = this.members.map(m => { const s = this.store.series.get(m.name); return s ? s.lastValue() : NaN; });
    const fin = vals.filter(Number.isFinite);
    let lo = Math.min(0, ...fin), hi = Math.max(0, ...fin);
    if (!(hi > lo)) { lo = 0; hi = 1; }
    const pad = 0.12 * (hi - lo);  // room for the value labels over (or under) the bars
    if (hi > 0) hi += pad;
    if (lo < 0) lo -= pad;
    const left = 62, right = cssW - 10, top = 10, bottom = cssH - 30;
    const y = v => bottom - (bottom - top) * (v - lo) / (hi - lo);
    g.strokeStyle = "#8c959f"; g.beginPath(); g.moveTo(left, top); g.lineTo(left, bottom); g.stroke();
    g.fillStyle = "#57606a"; g.textAlign = "right"; g.textBaseline = "middle";
    const ys = niceStep(hi - lo, 5);
    for (let v = Math.ceil(lo / ys) * ys; v <= hi; v += ys) g.fillText(fmtTick(v, ys), left - 5, y(v));
    g.save(); g.translate(14, (top + bottom) / 2); g.rotate(-Math.PI / 2); g.textAlign = "center";
    g.fillText(this.unit || "(no unit)", 0, 0); g.restore();
    g.strokeStyle = "#d0d7de"; g.beginPath(); g.moveTo(left, y(0)); g.lineTo(right, y(0)); g.stroke();
    const w = (right - left) / this.members.length;
    this.members.forEach((m, k) => {
      const x = left + k * w + w * 0.15, v = vals[k];
      g.fillStyle = TC_COLORS[k % TC_COLORS.length];
      if (Number.isFinite(v)) g.fillRect(x, Math.min(y(0), y(v)), w * 0.7, Math.abs(y(v) - y(0)));
      g.fillStyle = "#24292f"; g.textAlign = "center"; g.textBaseline = "top";
      g.fillText(m.label, x + w * 0.35, bottom + 4);
      g.textBaseline = "bottom"; g.fillText(Number.isFinite(v) ? fmtNum(v) : "–", x + w * 0.35, Math.min(y(0), y(v) || y(0)) - 2);
    });
    this.dirty = false;
    return performance.now() - started;
  }
}
