// dffd dashboard: live video with ROI drag, live plots, status and controls. No dependencies.
"use strict";

const PLOT_WINDOW_S = 30;          // seconds of history on the plots
const STALE_AFTER_S = 1.0;         // an estimate older than this is not shown as current
const RECONNECT_MS = 1000;         // retry period of the WebSockets
const MAX_POINTS = 1800;           // points kept for the plots (60 s at 30 Hz)
const SERIES = [
  ["lpv", "#4fc3f7"], ["kf", "#ba68c8"], ["cf2", "#81c784"], ["cf1", "#ffb74d"],
];
const MEASURED_COLOR = "#ff5252";
const TRUTH_COLOR = "#ffffff";

const dash = {
  frames: 0, points: [], image: null, drag: null, status: null, commandId: 0,
  frameTimes: [],
};
window.dffd = dash;  // for tests and the curious

const $ = (id) => document.getElementById(id);
const videoCanvas = $("video");
const vctx = videoCanvas.getContext("2d");

function wsUrl(path) {
  const proto = location.protocol === "https:" ? "wss:" : "ws:";
  return `${proto}//${location.host}${path}`;
}

// -- video --------------------------------------------------------------------------------------
function connectVideo() {
  const ws = new WebSocket(wsUrl("/ws/video"));
  ws.binaryType = "blob";
  ws.onmessage = async (ev) => {
    const bitmap = await createImageBitmap(ev.data);
    if (dash.image) dash.image.close();
    dash.image = bitmap;
    if (videoCanvas.width !== bitmap.width || videoCanvas.height !== bitmap.height) {
      videoCanvas.width = bitmap.width;
      videoCanvas.height = bitmap.height;
    }
    dash.frames += 1;
    document.body.dataset.frames = String(dash.frames);
    const now = performance.now();
    dash.frameTimes.push(now);
    while (dash.frameTimes.length && now - dash.frameTimes[0] > 2000) dash.frameTimes.shift();
    $("fps").textContent = `video ${(dash.frameTimes.length / 2).toFixed(1)} fps`;
    drawVideo();
  };
  ws.onclose = () => setTimeout(connectVideo, RECONNECT_MS);
}

function drawVideo() {
  if (dash.image) vctx.drawImage(dash.image, 0, 0);
  const d = dash.drag;
  if (d) {
    vctx.strokeStyle = "#00e5ff";
    vctx.lineWidth = 2;
    vctx.setLineDash([6, 4]);
    vctx.strokeRect(d.x0, d.y0, d.x1 - d.x0, d.y1 - d.y0);
    vctx.setLineDash([]);
  }
}

// The video may be downscaled for the browser; the ROI is in the camera's pixels.
function imageScale() {
  const size = dash.status && dash.status.frame_size;
  return size ? size[0] / videoCanvas.width : 1;
}

function canvasPoint(ev) {
  const r = videoCanvas.getBoundingClientRect();
  return {
    x: Math.max(0, Math.min(videoCanvas.width, (ev.clientX - r.left) * videoCanvas.width / r.width)),
    y: Math.max(0, Math.min(videoCanvas.height, (ev.clientY - r.top) * videoCanvas.height / r.height)),
  };
}

videoCanvas.addEventListener("mousedown", (ev) => {
  const p = canvasPoint(ev);
  dash.drag = { x0: p.x, y0: p.y, x1: p.x, y1: p.y };
  ev.preventDefault();
});
window.addEventListener("mousemove", (ev) => {
  if (!dash.drag) return;
  const p = canvasPoint(ev);
  dash.drag.x1 = p.x;
  dash.drag.y1 = p.y;
  drawVideo();
});
window.addEventListener("mouseup", () => {
  const d = dash.drag;
  dash.drag = null;
  if (!d) return;
  const s = imageScale();
  const x = Math.round(Math.min(d.x0, d.x1) * s), y = Math.round(Math.min(d.y0, d.y1) * s);
  const w = Math.round(Math.abs(d.x1 - d.x0) * s), h = Math.round(Math.abs(d.y1 - d.y0) * s);
  drawVideo();
  if (w < 4 || h < 4) return;  // a click, not a box
  sendCommand({ cmd: "acquire", roi: [x, y, w, h] });
});

// -- commands -----------------------------------------------------------------------------------
async function sendCommand(command) {
  dash.commandId += 1;
  const body = JSON.stringify({ id: `web-${dash.commandId}`, ...command });
  const out = $("reply");
  out.textContent = `→ ${body}`;
  out.className = "reply";
  try {
    const response = await fetch("/api/command", {
      method: "POST", headers: { "Content-Type": "application/json" }, body,
    });
    const text = await response.text();
    let reply;
    try { reply = JSON.parse(text); } catch { reply = { ok: false, error: text }; }
    out.textContent = `→ ${body}\n← ${JSON.stringify(reply)}`;
    out.className = reply.ok ? "reply ok" : "reply error";
    dash.lastReply = reply;
  } catch (err) {
    out.textContent = `→ ${body}\n← request failed: ${err}`;
    out.className = "reply error";
  }
}

$("btn-auto").onclick = () => sendCommand({ cmd: "acquire" });
$("btn-release").onclick = () => sendCommand({ cmd: "release" });
$("btn-home").onclick = () => sendCommand({ cmd: "home" });
$("form-policy").onsubmit = (ev) => {
  ev.preventDefault();
  const command = { cmd: "set_burst_policy", policy: $("policy").value };
  const n = $("every-n").value, s = $("sigma-threshold").value;
  if (n !== "") command.every_n_frames = Number(n);
  if (s !== "") command.sigma_threshold_m = Number(s);
  sendCommand(command);
};
$("form-size").onsubmit = (ev) => {
  ev.preventDefault();
  const v = $("known-size").value;
  sendCommand({ cmd: "set_known_size", size_m: v === "" ? null : Number(v) });
};
$("btn-forget-size").onclick = () => sendCommand({ cmd: "set_known_size", size_m: null });

// -- events -------------------------------------------------------------------------------------
function connectEvents() {
  const ws = new WebSocket(wsUrl("/ws/events"));
  ws.onmessage = (ev) => {
    const msg = JSON.parse(ev.data);
    if (msg.type === "hello") {
      dash.points = msg.points;
      showStatus(msg.status);
      showRejections(msg.rejections);
    } else if (msg.type === "estimates") {
      dash.points.push(...msg.points);
      if (dash.points.length > MAX_POINTS) dash.points.splice(0, dash.points.length - MAX_POINTS);
    } else if (msg.type === "status") {
      showStatus(msg.status);
    } else if (msg.type === "rejections") {
      showRejections(msg.items);
    }
    document.body.dataset.points = String(dash.points.length);
    drawPlots();
    showDepth();
    showTrack();
  };
  ws.onclose = () => {
    $("state").textContent = "disconnected";
    $("state").className = "badge offline";
    setTimeout(connectEvents, RECONNECT_MS);
  };
}

function fmt(v, digits = 3, unit = "") {
  return v === null || v === undefined ? "–" : `${Number(v).toFixed(digits)}${unit}`;
}

function showDepth() {
  const s = dash.status;
  const last = dash.points[dash.points.length - 1];
  const age = s ? s.last_estimate_age_s : null;
  const state = s && s.status ? s.status.state : null;
  const el = $("depth");
  if (!last || last.z === null) {
    el.textContent = "no depth";
    el.className = "depth stale";
  } else {
    el.textContent = `${fmt(last.z)} m ± ${fmt(last.sigma)}`;
    const stale = age === null || age > STALE_AFTER_S || state !== "tracking";
    el.className = stale ? "depth stale" : "depth";
  }
  $("age").textContent = age === null || age === undefined
    ? "no estimate yet" : `last estimate ${fmt(age, 1)} s ago`;
}

function vec(v, scale = 1, digits = 3) {
  return v ? v.map((c) => fmt(c * scale, digits)).join(", ") : "–";
}

// The 3D tracker's state of the newest estimate (docs/tracking3d.md); dashes without a track.
function showTrack() {
  const last = dash.points[dash.points.length - 1];
  const has = Boolean(last && last.pos_sigma);
  $("track-pos").textContent = has ? vec(last.pos) : "–";
  $("track-vel").textContent = has ? vec(last.vel) : "–";
  $("track-acc").textContent = has ? vec(last.acc) : "–";
  $("track-omega").textContent = has && last.omega !== null
    ? `${fmt(last.omega, 4)} rad/s (${fmt(last.omega * 180 / Math.PI, 2)}°/s)` : "–";
  $("track-sigma").textContent = has ? vec(last.pos_sigma, 1000, 1) : "–";
  const probs = $("track-probs");
  probs.innerHTML = "";
  if (!has || !last.probs) { probs.textContent = "–"; return; }
  for (const [name, p] of Object.entries(last.probs)) {
    const div = document.createElement("div");
    div.className = "prob";
    div.dataset.model = name;
    div.innerHTML = `<span class="name">${name}</span>${meter(p, 1)}<span class="value">${fmt(p, 3)}</span>`;
    probs.appendChild(div);
  }
}

function row(name, html) { return `<tr><td>${name}</td><td>${html}</td></tr>`; }
function flag(ok, yes, no) { return ok ? `<span class="good">${yes}</span>` : `<span class="bad">${no}</span>`; }
function meter(value, limit) {
  if (!limit) return "";
  const pct = Math.max(0, Math.min(100, 100 * value / limit));
  return `<span class="meter"><span style="width:${pct}%"></span></span>`;
}

function showStatus(snap) {
  dash.status = snap;
  const body = $("status").querySelector("tbody");
  if (!snap) {
    body.innerHTML = row("daemon", "starting…");
    return;
  }
  const st = snap.status;
  $("camera").textContent = st.camera || "";
  const state = st.availability === "offline" ? "offline" : (st.state || "–");
  const sw = st.search;  // the pan/tilt search sweep of automatic acquisition, if any
  const searching = sw && sw.phase !== "waiting";
  $("state").textContent = searching ? `${state} · searching` : state;
  $("state").className = `badge ${state}`;
  $("message").textContent = snap.message || st.message || "";
  const r = st.rates || {}, ln = st.link || {}, mq = st.mqtt || {}, dr = st.drops || {};
  body.innerHTML = [
    row("state", state),
    ...(searching ? [row("search", sw.phase === "sweeping"
      ? `sweeping: view ${sw.view} of ${sw.views} (sweep ${sw.pass_number}, ${fmt(sw.elapsed_s, 0)} s)`
      : `a whole sweep found nothing; next in ${fmt(sw.next_pass_in_s, 0)} s`)] : []),
    row("last estimate", snap.last_estimate_age_s === null ? "none" : `${fmt(snap.last_estimate_age_s, 1)} s ago`),
    row("frames", `${fmt(r.frame_hz, 1)} Hz`),
    row("estimates", `${fmt(r.estimate_hz, 1)} Hz`),
    row("depth", `${fmt(r.depth_hz, 2)} Hz of ${fmt(r.depth_limit_hz, 2)} Hz limit${meter(r.depth_hz, r.depth_limit_hz)}`),
    row("bursts", `${snap.bursts_accepted} accepted, ${snap.bursts_rejected} rejected`),
    row("VISCA link", `${flag(ln.connected, "connected", "down")}; ${ln.errors ?? 0} errors, ${ln.timeouts ?? 0} timeouts, ${ln.reconnects ?? 0} reconnects; last reply ${fmt(ln.last_reply_age_s, 2)} s ago`),
    row("MQTT", `${flag(mq.connected, "connected", "disconnected")}; backlog ${mq.backlog ?? 0}, ${mq.reconnects ?? 0} reconnects`),
    row("dropped", `frames ${dr.frames ?? 0}, publish ${dr.publish_queue ?? 0}, backlog ${dr.backlog ?? 0}, log ${dr.log ?? 0}`),
    row("version", st.version || ""),
  ].join("");
}

function showRejections(items) {
  const list = $("rejections");
  list.innerHTML = "";
  for (const item of [...items].reverse()) {
    const li = document.createElement("li");
    const when = new Date(item.t * 1000).toLocaleTimeString();
    li.textContent = `${when} burst ${item.burst} [${item.focus_counts.join(", ")}]: ${item.reason}`;
    list.appendChild(li);
  }
  if (!items.length) list.innerHTML = '<li class="empty">none</li>';
}

// -- plots --------------------------------------------------------------------------------------
function drawSeries(ctx, box, points, tMax, yMin, yMax, get, color, dots = false, dashed = false) {
  const x = (t) => box.x + box.w * (1 - (tMax - t) / PLOT_WINDOW_S);
  const y = (v) => box.y + box.h * (1 - (v - yMin) / (yMax - yMin));
  ctx.strokeStyle = color;
  ctx.fillStyle = color;
  ctx.lineWidth = 1.5;
  ctx.setLineDash(dashed ? [5, 4] : []);
  ctx.beginPath();
  let pen = false;
  for (const p of points) {
    const v = get(p);
    if (v === null || v === undefined || p.t < tMax - PLOT_WINDOW_S) { pen = false; continue; }
    if (dots) { ctx.fillRect(x(p.t) - 2, y(v) - 2, 4, 4); continue; }
    if (pen) ctx.lineTo(x(p.t), y(v)); else ctx.moveTo(x(p.t), y(v));
    pen = true;
  }
  if (!dots) ctx.stroke();
  ctx.setLineDash([]);
}

function drawAxes(ctx, canvas, box, yMin, yMax) {
  ctx.fillStyle = "#1f2329";
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  ctx.strokeStyle = "#3a414a";
  ctx.fillStyle = "#8a9099";
  ctx.font = "11px sans-serif";
  ctx.lineWidth = 1;
  for (let i = 0; i <= 4; i++) {
    const v = yMin + (yMax - yMin) * i / 4;
    const yy = box.y + box.h * (1 - i / 4);
    ctx.beginPath(); ctx.moveTo(box.x, yy); ctx.lineTo(box.x + box.w, yy); ctx.stroke();
    ctx.fillText(v.toFixed(yMax - yMin < 0.5 ? 3 : 2), 4, yy + 4);
  }
  for (let s = 0; s <= PLOT_WINDOW_S; s += 5) {
    const xx = box.x + box.w * (1 - s / PLOT_WINDOW_S);
    ctx.fillText(`-${s}s`, xx - 10, box.y + box.h + 14);
  }
}

function range(points, getters, tMax) {
  let lo = Infinity, hi = -Infinity;
  for (const p of points) {
    if (p.t < tMax - PLOT_WINDOW_S) continue;
    for (const g of getters) {
      const v = g(p);
      if (v === null || v === undefined) continue;
      lo = Math.min(lo, v); hi = Math.max(hi, v);
    }
  }
  if (!isFinite(lo)) return [0, 1];
  const pad = Math.max(0.02, (hi - lo) * 0.1);
  return [lo - pad, hi + pad];
}

function drawPlots() {
  const pts = dash.points;
  const tMax = pts.length ? pts[pts.length - 1].t : 0;
  const dc = $("depth-plot"), dctx = dc.getContext("2d");
  const box = { x: 44, y: 8, w: dc.width - 52, h: dc.height - 28 };
  const getters = SERIES.map(([k]) => (p) => p.d[k]).concat([(p) => p.truth, (p) => p.d.measured]);
  const [lo, hi] = range(pts, getters, tMax);
  drawAxes(dctx, dc, box, lo, hi);
  for (const [k, color] of SERIES) drawSeries(dctx, box, pts, tMax, lo, hi, (p) => p.d[k], color);
  drawSeries(dctx, box, pts, tMax, lo, hi, (p) => p.truth, TRUTH_COLOR, false, true);
  drawSeries(dctx, box, pts, tMax, lo, hi, (p) => p.d.measured, MEASURED_COLOR, true);
  const sc = $("sigma-plot"), sctx = sc.getContext("2d");
  const sbox = { x: 44, y: 8, w: sc.width - 52, h: sc.height - 28 };
  const [slo, shi] = range(pts, [(p) => p.sigma], tMax);
  drawAxes(sctx, sc, sbox, Math.max(0, slo), shi);
  drawSeries(sctx, sbox, pts, tMax, Math.max(0, slo), shi, (p) => p.sigma, "#4fc3f7");
}

function legend() {
  const items = SERIES.map(([k, c]) => `<span style="color:${c}">— ${k}</span>`);
  items.push(`<span style="color:${MEASURED_COLOR}">■ measured</span>`);
  items.push(`<span style="color:${TRUTH_COLOR}">- - truth</span>`);
  $("legend").innerHTML = items.join("");
}

legend();
drawPlots();
connectVideo();
connectEvents();
