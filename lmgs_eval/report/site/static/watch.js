// The Watch page: players in lockstep on one clock, frame stepping, error maps, metric curves with a cursor.
// The ground truth's video (or, without one, the first video) is the clock; the others follow it and are
// re-aligned whenever they drift by more than half a frame.
"use strict";

const data = JSON.parse(document.getElementById("watch-data").textContent);
const fps = data.fps;
const nFrames = data.n_frames || 1;
const figures = Array.from(document.querySelectorAll("#players figure.player"));
const videos = () => Array.from(document.querySelectorAll("#players video"));
const master = () => document.querySelector("#players video.clock") || videos()[0] || null;
const playBtn = document.getElementById("play");
const seekBar = document.getElementById("seek");
const frameNo = document.getElementById("frame-no");
const metricSel = document.getElementById("metric");
const svg = document.getElementById("curves");
let playing = false;

function frameOf(t) { return Math.min(nFrames - 1, Math.max(0, Math.floor(t * fps + 1e-3))); }
function timeOf(frame) { return (frame + 0.5) / fps; }  // mid-frame: decoders show that frame there

function seekAll(frame) {
  const t = timeOf(Math.min(nFrames - 1, Math.max(0, frame)));
  const waits = videos().map((v) => new Promise((resolve) => {
    if (Math.abs(v.currentTime - t) < 1e-4) { resolve(); return; }
    v.addEventListener("seeked", () => resolve(), { once: true });
    v.currentTime = t;
  }));
  update(frame);
  return Promise.all(waits);
}

async function play() {
  const m = master();
  if (!m) return;
  if (m.ended || frameOf(m.currentTime) >= nFrames - 1) await seekAll(0);
  const t = m.currentTime;
  videos().forEach((v) => { if (Math.abs(v.currentTime - t) > 0.5 / fps) v.currentTime = t; });
  playing = true;
  playBtn.textContent = "⏸ Pause";
  await Promise.all(videos().map((v) => v.play().catch(() => undefined)));
  requestAnimationFrame(tick);
}

function pause() {
  playing = false;
  playBtn.textContent = "▶ Play";
  videos().forEach((v) => { v.pause(); v.playbackRate = 1; });
  const m = master();
  if (m) seekAll(frameOf(m.currentTime));  // land every player on the same frame
}

// While playing, a follower that drifts is nudged by its playback rate (a seek stalls a video and makes it drift
// more); only a follower far off (after a stall) is moved by a seek.
const HARD = 0.25;  // seconds
function tick() {
  const m = master();
  if (!m) return;
  const t = m.currentTime;
  for (const v of videos()) {
    if (v === m) continue;
    const drift = v.currentTime - t;
    if (!playing || m.paused) {
      v.playbackRate = 1;
      if (Math.abs(drift) > 0.5 / fps) v.currentTime = t;
    } else if (Math.abs(drift) > HARD) {
      v.currentTime = t + 0.05;  // it resumes a little later: land slightly ahead
      v.playbackRate = 1;
    } else {
      v.playbackRate = Math.abs(drift) > 0.25 / fps ? Math.min(1.5, Math.max(0.5, 1 - drift * 4)) : 1;
    }
    if (playing && v.paused && !m.paused) v.play().catch(() => undefined);
  }
  update(frameOf(t));
  if (m.ended) { pause(); return; }
  if (playing) requestAnimationFrame(tick);
}

function update(frame) {
  seekBar.value = String(frame);
  frameNo.textContent = `frame ${frame} / ${nFrames - 1}`;
  readout(frame);
  const cur = document.getElementById("cursor");
  if (cur) {
    const x = xOf(frame);
    cur.setAttribute("x1", x.toFixed(1));
    cur.setAttribute("x2", x.toFixed(1));
    cur.dataset.frame = String(frame);
  }
}

// the chosen metric of every shown player at the cursor's frame, under the curves
function readout(frame) {
  const box = document.getElementById("readout");
  const key = metricSel.value;
  if (!box || !key) return;
  const meta = data.metrics[key];
  const parts = [];
  shown().forEach((p) => {
    const vs = p.curves[key];
    if (!vs || !drawable(p, key)) return;
    const i = frame - Math.floor((nFrames - vs.length) / 2);
    const v = i >= 0 && i < vs.length ? vs[i] : null;
    parts.push(`${p.label} ${v === null ? "–" : v.toFixed(meta.digits)}`);
  });
  box.textContent = parts.length ? `frame ${frame}, ${meta.label}: ${parts.join(" · ")}` : "";
}

// ------------------------------------------------------------------ curves
const PAD_L = 48, PAD_R = 10, PAD_T = 10, PAD_B = 22, VW = 900, VH = 220;
function xOf(frame) { return PAD_L + (frame / Math.max(1, nFrames - 1)) * (VW - PAD_L - PAD_R); }
// per-window metrics have fewer items than frames: item i is drawn at its window's centre frame
function itemFrame(i, n) { return i + Math.floor((nFrames - n) / 2); }
const COLOURS = ["#555", "#2ca02c", "#1f77b4", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#bcbd22", "#ff7f0e"];

function shown() {
  const on = new Set(Array.from(document.querySelectorAll("#chooser input:checked")).map((i) => i.value));
  return data.players.filter((p) => on.has(p.id));
}

// a series worth drawing: some values, and for the ground truth not one constant (its PSNR of identical frames)
function drawable(p, key) {
  const vs = (p.curves[key] || []).filter((v) => v !== null);
  if (!vs.length) return false;
  return !(p.gt && vs.every((v) => v === vs[0]));
}

function drawCurves() {
  const key = metricSel.value;
  const ns = "http://www.w3.org/2000/svg";
  svg.innerHTML = "";
  if (!key) {
    const t = document.createElementNS(ns, "text");
    Object.entries({ x: 450, y: 110, "text-anchor": "middle", class: "tick" }).forEach(([k, v]) => t.setAttribute(k, v));
    t.textContent = "no per-frame metric values in these records";
    svg.appendChild(t);
    return;
  }
  const series = shown().filter((p) => drawable(p, key));
  const vals = series.flatMap((p) => p.curves[key].filter((v) => v !== null));
  if (!vals.length) return;
  let lo = Math.min(...vals), hi = Math.max(...vals);
  if (hi - lo < 1e-12) { lo -= 1; hi += 1; }
  const yOf = (v) => PAD_T + (hi - v) / (hi - lo) * (VH - PAD_T - PAD_B);
  const add = (tag, attrs, text) => {
    const el = document.createElementNS(ns, tag);
    for (const [k, v] of Object.entries(attrs)) el.setAttribute(k, v);
    if (text !== undefined) el.textContent = text;
    svg.appendChild(el);
    return el;
  };
  const meta = data.metrics[key];
  for (const v of [lo, (lo + hi) / 2, hi]) {
    add("line", { x1: PAD_L, x2: VW - PAD_R, y1: yOf(v), y2: yOf(v), class: "grid" });
    add("text", { x: PAD_L - 4, y: yOf(v) + 4, class: "tick", "text-anchor": "end" }, v.toFixed(meta.digits));
  }
  add("text", { x: VW - PAD_R, y: VH - 6, class: "tick", "text-anchor": "end" }, `frame (${meta.label} ${meta.higher ? "↑" : "↓"})`);
  series.forEach((p) => {
    const k = data.players.indexOf(p);
    const vs = p.curves[key];
    const pts = [];
    vs.forEach((v, i) => { if (v !== null) pts.push(`${xOf(itemFrame(i, vs.length)).toFixed(1)},${yOf(v).toFixed(1)}`); });
    const line = add("polyline", { points: pts.join(" "), class: "curve", stroke: COLOURS[k % COLOURS.length], "data-id": p.id });
    const title = document.createElementNS(ns, "title");
    title.textContent = p.label;
    line.appendChild(title);
  });
  const cur = add("line", { id: "cursor", x1: PAD_L, x2: PAD_L, y1: PAD_T, y2: VH - PAD_B, class: "cursor" });
  cur.dataset.frame = "0";
  const m = master();
  update(m ? frameOf(m.currentTime) : Number(seekBar.value));
  drawLegend(series);
  drawWorst(key);
}

function drawLegend(series) {
  figures.forEach((f) => {
    const k = data.players.findIndex((p) => p.id === f.dataset.id);
    f.style.borderTopColor = COLOURS[k % COLOURS.length];
  });
}

// the worst frames of each method for the chosen metric, one click from the players
function drawWorst(key) {
  const meta = data.metrics[key];
  document.querySelectorAll(".worst").forEach((box) => {
    const p = data.players.find((q) => q.id === box.dataset.id);
    box.innerHTML = "";
    const vs = p && p.curves[key];
    if (!vs || !vs.some((v) => v !== null)) { box.textContent = `no per-frame ${meta.label}`; return; }
    const idx = vs.map((v, i) => [v, i]).filter((x) => x[0] !== null);
    idx.sort((a, b) => (meta.higher ? a[0] - b[0] : b[0] - a[0]));
    box.append(`worst ${meta.label}: `);
    idx.slice(0, 5).forEach(([v, i]) => {
      const b = document.createElement("button");
      b.type = "button";
      b.className = "jump";
      const f = itemFrame(i, vs.length);
      b.dataset.frame = String(f);
      b.textContent = `#${f} (${v.toFixed(meta.digits)})`;
      b.addEventListener("click", () => { if (playing) pause(); seekAll(f); });
      box.append(b, " ");
    });
  });
}

// ------------------------------------------------------------------ wiring
function setErrorMap(on) {
  figures.forEach((f) => {
    const main = f.querySelector("video.main"), err = f.querySelector("video.err");
    if (!main || !err) return;
    err.hidden = !on;
    main.hidden = on;
  });
}

function setChosen() {
  const on = new Set(Array.from(document.querySelectorAll("#chooser input:checked")).map((i) => i.value));
  figures.forEach((f) => { f.hidden = !on.has(f.dataset.id); });
  drawCurves();
}

const keys = data.order.filter((k) => data.players.some((p) => drawable(p, k)));
keys.forEach((k) => {
  const o = document.createElement("option");
  o.value = k;
  o.textContent = data.metrics[k].label;
  metricSel.appendChild(o);
});
metricSel.addEventListener("change", drawCurves);
playBtn.addEventListener("click", () => (playing ? pause() : play()));
document.getElementById("back").addEventListener("click", () => { if (playing) pause(); seekAll(Number(seekBar.value) - 1); });
document.getElementById("fwd").addEventListener("click", () => { if (playing) pause(); seekAll(Number(seekBar.value) + 1); });
seekBar.addEventListener("input", () => { if (playing) pause(); seekAll(Number(seekBar.value)); });
const errBox = document.getElementById("errmap");
if (errBox) errBox.addEventListener("change", (e) => setErrorMap(e.target.checked));
document.getElementById("sound").addEventListener("change", (e) => { const m = master(); if (m) m.muted = !e.target.checked; });
document.getElementById("chooser").addEventListener("change", setChosen);
document.addEventListener("keydown", (e) => {
  if (e.target.tagName === "INPUT" && e.target.type === "range") return;
  if (e.key === "ArrowLeft") document.getElementById("back").click();
  else if (e.key === "ArrowRight") document.getElementById("fwd").click();
  else if (e.key === " " && e.target === document.body) { e.preventDefault(); playBtn.click(); }
});
svg.addEventListener("click", (e) => {
  const r = svg.getBoundingClientRect();
  const x = (e.clientX - r.left) / r.width * VW;
  const f = Math.round((x - PAD_L) / (VW - PAD_L - PAD_R) * (nFrames - 1));
  if (playing) pause();
  seekAll(Math.min(nFrames - 1, Math.max(0, f)));
});
videos().forEach((v) => v.addEventListener("timeupdate", () => { if (!playing && v === master()) update(frameOf(v.currentTime)); }));
if (!videos().length) { playBtn.disabled = true; document.getElementById("controls").classList.add("novideo"); }
setChosen();
update(0);
window.lmgsWatch = { seekAll, play, pause, frameOf, master, videos, isPlaying: () => playing };
