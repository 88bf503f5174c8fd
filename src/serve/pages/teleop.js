// The teleoperation page: frames arrive as binary WebSocket messages (a 32-byte header, then a
// JPEG); keyboard, mouse, gamepad and WebXR controllers become per-dimension command velocities
// through the embodiment's mapping file, sent as {"type": "control"} messages.
"use strict";
const params = new URLSearchParams(location.search);
const $ = (id) => document.getElementById(id);
const view = $("view"), ctx = view.getContext("2d");

let ws = null, mapping = null, width = 0, velocity = [], held = new Set(), mouse = null;
// A multi-view model's frames are one canvas of several cameras (capabilities.views): the main
// camera is drawn into #view, the others into their own canvases below it.
let tiling = null, extraViews = [];
let frameTimes = [], latencies = [], framesShown = 0, recording = false, xrSession = null;
// keyLatencies: per key press, ms from the keydown to the first drawn frame whose step saw it.
window.dojo = { frames: 0, lastSeq: -1, lastLatencyMs: null, keyLatencies: [], ready: null, errors: [], recorded: null };
let keyDownAt = null;
// ?record=1: every session is recorded from its start frame, so it can be replayed (dojo serve-check).
const recordFromStart = params.get("record") === "1";

function log(text) { $("log").textContent = text; if (text) window.dojo.errors.push(text); }

async function init() {
  let caps = await (await fetch("/api/capabilities")).json();
  while (!caps.ready) {  // the models are still loading
    $("status").textContent = "models loading";
    await new Promise((r) => setTimeout(r, 1000));
    caps = await (await fetch("/api/capabilities")).json();
  }
  $("status").textContent = "idle";
  for (const m of caps.models) $("model").add(new Option(`${m.name} (${m.kind})`, m.name));
  for (const e of caps.episodes) $("episode").add(new Option(e, e));
  window.dojo.capabilities = caps;
  if (caps.views) {
    tiling = caps.views;
    const n = tiling.cameras.length;
    tiling.columns = tiling.layout === "side_by_side" ? n : tiling.layout === "stack" ? 1 : Math.ceil(Math.sqrt(n));
    tiling.rows = Math.ceil(n / tiling.columns);
    for (const camera of tiling.cameras.slice(1)) {
      const figure = document.createElement("figure"), canvas = document.createElement("canvas");
      canvas.width = tiling.view_width; canvas.height = tiling.view_height;
      const caption = document.createElement("figcaption");
      caption.textContent = camera;
      figure.append(canvas, caption);
      $("more-views").append(figure);
      extraViews.push(canvas.getContext("2d"));
    }
  }
  const slot = (caps.models[0] && caps.models[0].action_slots[0]) || null;
  if (slot) {
    const r = await fetch(`/${slot.slot}.mapping.json`);
    if (r.ok) mapping = await r.json();
  }
  if (mapping) {
    for (const d of mapping.dims) {
      const row = $("keys").insertRow();
      row.insertCell().textContent = d.name;
      row.insertCell().textContent = (d.keys || []).map((k) => k.replace("Key", "")).join(" / ");
    }
    const home = $("keys").insertRow();
    home.insertCell().textContent = "home (the start pose)";
    home.insertCell().textContent = "H";
  }
  if (navigator.xr && window.isSecureContext) {
    navigator.xr.isSessionSupported("immersive-vr").then((ok) => { $("xr").hidden = !ok; });
  }
}

function send(message) { if (ws && ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify(message)); }

function start() {
  if (ws) ws.close();
  const proto = location.protocol === "https:" ? "wss:" : "ws:";
  ws = new WebSocket(`${proto}//${location.host}/ws`);
  ws.binaryType = "arraybuffer";
  $("status").textContent = "connecting";
  ws.onopen = async () => {
    const file = $("image").files[0];
    const start = { type: "start", mode: "live", model: $("model").value, episode: $("episode").value, seed: 0 };
    if (recordFromStart) {
      start.record = true; recording = true; $("record").textContent = "Stop recording";
    }
    if (file) { ws.send(await file.arrayBuffer()); start.image = true; }
    send(start);
  };
  ws.onmessage = (event) => {
    if (typeof event.data === "string") return onText(JSON.parse(event.data));
    onFrame(event.data);
  };
  const socket = ws;  // events of a socket replaced by a newer start are ignored
  ws.onclose = (e) => {
    if (socket !== ws) return;
    $("status").textContent = "closed" + (e.reason ? ": " + e.reason : "");
    setButtons(false);
  };
  ws.onerror = () => log("connection failed (is the session cap reached?)");
}

function onText(m) {
  if (m.type === "ready") {
    width = (m.command || []).length;
    velocity = new Array(width).fill(0);
    view.width = tiling ? m.width / tiling.columns : m.width;
    view.height = tiling ? m.height / tiling.rows : m.height;
    frameIntervalMs = 1000 / (m.fps || 10);
    framesPerStep = m.actions_per_step || 4;
    playout = [];
    $("status").textContent = `${m.model}, ${m.mode}` + (m.episode ? `, ${m.episode}` : "");
    window.dojo.ready = m;
    setButtons(true);
    log("");
  } else if (m.type === "error") {
    log(m.message);
  } else if (m.type === "recorded") {
    window.dojo.recorded = m.path; log(""); $("status").textContent = "recorded " + m.path;
  }
}

// Frames of one step arrive together; a playout queue shows them at the stream's frame rate
// (skipping ahead when it holds more than two steps, so the view never lags behind).
let playout = [], frameIntervalMs = 100, lastDrawn = 0, framesPerStep = 4;
async function onFrame(buffer) {
  const header = new DataView(buffer, 0, 32);
  if (String.fromCharCode(...new Uint8Array(buffer, 0, 4)) !== "DJF1") return;
  const seq = header.getUint32(4, true), clientT = header.getFloat64(16, true);
  const bitmap = await createImageBitmap(new Blob([new Uint8Array(buffer, 32)], { type: "image/jpeg" }));
  // Decoding can finish out of order: keep the queue sorted by sequence number.
  let at = playout.length;
  while (at > 0 && playout[at - 1].seq > seq) --at;
  playout.splice(at, 0, { seq, clientT, bitmap });
  const cap = 2 * framesPerStep;
  if (playout.length > cap) for (const dropped of playout.splice(0, playout.length - cap)) dropped.bitmap.close();
}

function drawNext(now) {
  requestAnimationFrame(drawNext);
  if (!playout.length || now - lastDrawn < frameIntervalMs) return;
  // Keep the frame clock steady (a 60 Hz display showing 40 frames/s), but never run behind it.
  lastDrawn = Math.max(lastDrawn + frameIntervalMs, now - frameIntervalMs);
  // Half a step more behind than one step's burst: skip ahead (latency over smoothness).
  while (playout.length > framesPerStep + Math.ceil(framesPerStep / 2)) playout.shift().bitmap.close();
  const { seq, clientT, bitmap } = playout.shift();
  if (tiling) {  // each camera's part of the canvas into its own view
    const w = bitmap.width / tiling.columns, h = bitmap.height / tiling.rows;
    [ctx, ...extraViews].forEach((c, i) => c.drawImage(bitmap, (i % tiling.columns) * w,
      Math.floor(i / tiling.columns) * h, w, h, 0, 0, c.canvas.width, c.canvas.height));
  } else {
    ctx.drawImage(bitmap, 0, 0, view.width, view.height);
  }
  bitmap.close();
  frameTimes.push(now);
  while (frameTimes.length && frameTimes[0] < now - 2000) frameTimes.shift();
  if (clientT > 0) { latencies.push(now - clientT); if (latencies.length > 30) latencies.shift(); }
  if (keyDownAt !== null && clientT >= keyDownAt) {
    if (window.dojo.keyLatencies.length < 10000) window.dojo.keyLatencies.push(now - keyDownAt);
    keyDownAt = null;
  }
  framesShown++;
  window.dojo.frames = framesShown; window.dojo.lastSeq = seq;
  window.dojo.lastLatencyMs = latencies.length ? latencies[latencies.length - 1] : null;
}

setInterval(() => {
  $("fps").textContent = `${(frameTimes.length / 2).toFixed(1)} frames/s`;
  const mean = latencies.length ? latencies.reduce((a, b) => a + b) / latencies.length : null;
  $("latency").textContent = mean === null ? "— ms input→frame" : `${mean.toFixed(0)} ms input→frame`;
  $("frames").textContent = `${framesShown} frames`;
}, 250);

// Inputs -> velocity: keys (negative, positive), mouse drag, gamepad axes and buttons, WebXR
// controllers' gamepads. Sent on change and every 100 ms while moving (the echoed "t" is the
// clock that input-to-frame latency is measured against).
function computeVelocity() {
  const v = new Array(width).fill(0);
  if (!mapping) return v;
  const pads = [...(navigator.getGamepads ? navigator.getGamepads() : [])].filter(Boolean);
  if (xrSession) for (const source of xrSession.inputSources) if (source.gamepad) pads.push(source.gamepad);
  mapping.dims.forEach((d, i) => {
    const dim = d.index !== undefined ? d.index : i;
    if (dim >= width) return;
    let u = 0;
    if (d.keys) { if (held.has(d.keys[0])) u -= 1; if (held.has(d.keys[1])) u += 1; }
    if (mouse && d.mouse) u += Math.max(-1, Math.min(1, (d.mouse === "x" ? mouse.dx : -mouse.dy) / 40));
    for (const pad of pads) {
      if (d.gamepad_axis !== undefined && pad.axes.length > d.gamepad_axis) {
        const a = pad.axes[d.gamepad_axis];
        if (Math.abs(a) > 0.15) u += d.gamepad_axis % 2 ? -a : a;
      }
      if (d.gamepad_buttons) {
        const [neg, pos] = d.gamepad_buttons;
        if (pad.buttons[neg] && pad.buttons[neg].pressed) u -= 1;
        if (pad.buttons[pos] && pad.buttons[pos].pressed) u += 1;
      }
    }
    v[dim] = Math.max(-1, Math.min(1, u)) * d.rate;
  });
  return v;
}

let lastSent = "";
function pumpControls() {
  if (window.dojo.ready && ws && ws.readyState === WebSocket.OPEN) {
    const v = computeVelocity();
    const key = JSON.stringify(v);
    const moving = v.some((x) => x !== 0);
    if (key !== lastSent || moving) {
      send({ type: "control", velocity: v, t: performance.now() });
      lastSent = key;
    }
  }
}
setInterval(pumpControls, 100);
// H: back to the session's start command (the arm returns to the start pose; the stream goes on).
const kHomeKey = "KeyH";
document.addEventListener("keydown", (e) => {
  if (held.has(e.code)) return;
  held.add(e.code);
  keyDownAt = performance.now();
  if (e.code === kHomeKey && window.dojo.ready && window.dojo.ready.command)
    send({ type: "command", value: window.dojo.ready.command, t: keyDownAt });
  pumpControls();
});
document.addEventListener("keyup", (e) => { held.delete(e.code); pumpControls(); });
view.addEventListener("mousedown", (e) => { mouse = { x0: e.clientX, y0: e.clientY, dx: 0, dy: 0 }; });
window.addEventListener("mousemove", (e) => { if (mouse) { mouse.dx = e.clientX - mouse.x0; mouse.dy = e.clientY - mouse.y0; } });
window.addEventListener("mouseup", () => { mouse = null; pumpControls(); });

function setButtons(on) { $("reset").disabled = !on; $("record").disabled = !on; }
$("start").onclick = start;
$("reset").onclick = () => send({ type: "reset" });
$("record").onclick = () => {
  recording = !recording;
  send({ type: "record", on: recording });
  $("record").textContent = recording ? "Stop recording" : "Record";
};
$("xr").onclick = async () => {
  xrSession = await navigator.xr.requestSession("immersive-vr");
  xrSession.addEventListener("end", () => { xrSession = null; });
};
requestAnimationFrame(drawNext);
init().catch((e) => log("cannot load capabilities: " + e));
