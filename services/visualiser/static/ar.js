// slamlens AR page: this device's rear camera, each frame sent to the viewer, which has it
// registered (slamlens registration --source browser) and answers it with the chosen
// robot's overlay drawn on it. Plain script, no build step and no network beyond this server.
"use strict";

const LAYERS = ["robot", "path", "features", "lines", "ellipsoids", "legend", "labels", "health",
                "rejected"];
const STALE_MS = 3000;  // a frame unanswered this long is given up

function randomId(bytes) {
  const b = new Uint8Array(bytes);
  crypto.getRandomValues(b);
  return Array.from(b, (x) => x.toString(16).padStart(2, "0")).join("");
}

const client = (() => {
  try {
    let id = sessionStorage.getItem("slamlensArClient");
    if (!id) { id = randomId(8); sessionStorage.setItem("slamlensArClient", id); }
    return id;
  } catch (e) {
    return randomId(8);
  }
})();

// What the page did, for tests and the curious (window.slamlensAr in the console).
const ar = window.slamlensAr = {
  client, camera: null, robot: null, sent: 0, answered: 0, overlays: 0, refused: 0,
  latencies: [], overlayLatencies: [], last: null, errors: 0, cameraError: null,
  timings: [],  // per answer with an overlay: ms taking+encoding, in the viewer, decoding+showing
  notes: {},  // why answers came without an overlay: note → how many
  width: 0, height: 0, settings: null,
};

const $ = (id) => document.getElementById(id);
const view = $("arview");
const vctx = view.getContext("2d");
const video = $("camera");
const grab = document.createElement("canvas");
const gctx = grab.getContext("2d");
const params = new URLSearchParams(location.search);
// frames sent and not answered yet (flow control): ?inflight=1…4, 2 by default
const MAX_INFLIGHT = Math.min(4, Math.max(1, Number(params.get("inflight")) || 2));
// tag → {taken, sent}: performance.now() when its frame was taken, and went on the socket
const inflight = new Map();
let socket = null;
let header = null;
let nextTag = 1;
let fresh = false;  // the video has a frame not sent yet
let answeredAt = [];

function showError(message) {
  $("arerror").textContent = message || "";
  if (message) ar.errors += 1;
}

async function api(path, options) {
  const response = await fetch(path, options);
  const body = await response.json().catch(() => ({error: response.statusText}));
  if (!response.ok) throw new Error(body.error || response.statusText);
  return body;
}

// ---------------------------------------------------------------- settings
function buildLayers() {
  for (const name of LAYERS) {
    const label = document.createElement("label");
    label.innerHTML = `<input type="checkbox" name="${name}"> ${name}`;
    $("arlayers").appendChild(label);
  }
}

function showSettings(settings) {
  ar.settings = settings;
  for (const element of $("arsettings").elements) {
    if (!element.name || !(element.name in settings)) continue;
    if (element.type === "checkbox") element.checked = Boolean(settings[element.name]);
    else element.value = String(settings[element.name]);
  }
}

async function change(changes) {
  try {
    const body = await api(`/api/ar/settings?client=${client}`, {
      method: "POST", headers: {"Content-Type": "application/json"},
      body: JSON.stringify(changes)});
    showSettings(body.settings);
    showError("");
  } catch (e) {
    showError(e.message);
    if (ar.settings) showSettings(ar.settings);
  }
}

function cameraName(base) {
  const asked = params.get("camera");
  if (asked) return asked;
  const key = `slamlensArCamera:${base}`;
  try {
    let name = localStorage.getItem(key);
    if (!name) { name = `${base}-${randomId(3)}`; localStorage.setItem(key, name); }
    return name;
  } catch (e) {
    return `${base}-${randomId(3)}`;
  }
}

async function loadSettings() {
  const body = await api(`/api/ar/settings?client=${client}`);
  ar.camera = cameraName(body.camera);
  $("camname").value = ar.camera;
  const select = $("robot");
  select.innerHTML = "";
  for (const name of body.robots) {
    const option = document.createElement("option");
    option.value = option.textContent = name;
    select.appendChild(option);
  }
  ar.robot = params.get("robot") || body.robots[0] || null;
  if (ar.robot) select.value = ar.robot;
  showSettings(body.settings);
}

// ---------------------------------------------------------------- the camera
async function startCamera() {
  if (video.srcObject) video.srcObject.getTracks().forEach((t) => t.stop());
  try {
    video.srcObject = await navigator.mediaDevices.getUserMedia({audio: false, video: {
      facingMode: {ideal: "environment"}, width: {ideal: 1280}, height: {ideal: 720}}});
    await video.play();
    ar.cameraError = null;
  } catch (e) {
    ar.cameraError = `${e.name}: ${e.message}`;
    $("arstatus").textContent = `no camera: ${ar.cameraError} (the page must be opened over ` +
      "https, or on this machine, and allowed to use the camera)";
    return;
  }
  watchFrames();
}

function watchFrames() {
  if ("requestVideoFrameCallback" in HTMLVideoElement.prototype) {
    const onFrame = () => { fresh = true; pump(); video.requestVideoFrameCallback(onFrame); };
    video.requestVideoFrameCallback(onFrame);
  } else {
    setInterval(() => { fresh = true; pump(); }, 33);
  }
}

function sendWidth() {
  return Math.max(160, Number($("sendwidth").value) || 1280);
}

async function send() {
  const vw = video.videoWidth, vh = video.videoHeight;
  const w = Math.min(vw, sendWidth()) & ~1;
  const h = Math.round(vh * w / vw) & ~1;
  if (grab.width !== w || grab.height !== h) { grab.width = w; grab.height = h; }
  const tag = nextTag++;
  const times = {taken: performance.now(), sent: undefined};
  inflight.set(tag, times);
  fresh = false;
  gctx.drawImage(video, 0, 0, w, h);
  const quality = Number($("sendquality").value) || 0.8;
  const blob = await new Promise((resolve) => grab.toBlob(resolve, "image/jpeg", quality));
  if (!blob || !socket || socket.readyState !== WebSocket.OPEN) { inflight.delete(tag); return; }
  socket.send(JSON.stringify({tag}));
  socket.send(blob);
  times.sent = performance.now();
  ar.sent += 1;
  ar.width = w;
  ar.height = h;
}

function pump() {
  const now = performance.now();
  for (const [tag, t] of inflight) if (now - t.taken > STALE_MS) inflight.delete(tag);
  if (!fresh || !socket || socket.readyState !== WebSocket.OPEN || !video.videoWidth) return;
  if (inflight.size >= MAX_INFLIGHT) return;
  send();
}

// ---------------------------------------------------------------- the viewer's answers
function connect() {
  const scheme = location.protocol === "https:" ? "wss" : "ws";
  const query = new URLSearchParams({client, camera: ar.camera, robot: ar.robot || ""});
  socket = new WebSocket(`${scheme}://${location.host}/ar/ws?${query}`);
  socket.binaryType = "blob";
  socket.onopen = () => { inflight.clear(); $("arstatus").textContent = `camera ${ar.camera}`; };
  socket.onmessage = onMessage;
  socket.onclose = () => {
    $("arstatus").textContent = `camera ${ar.camera}: not connected (is the name taken, ` +
      "or the viewer gone?); retrying";
    setTimeout(connect, 2000);
  };
}

async function onMessage(event) {
  if (typeof event.data === "string") {
    const message = JSON.parse(event.data);
    if (message.refused !== undefined) {
      ar.refused += 1;
      inflight.delete(message.tag);
      showError(`frame refused: ${message.refused}`);
      pump();
    } else {
      header = message;
    }
    return;
  }
  const meta = header;
  header = null;
  const arrived = performance.now();
  const bitmap = await createImageBitmap(event.data);
  if (view.width !== bitmap.width || view.height !== bitmap.height) {
    view.width = bitmap.width;
    view.height = bitmap.height;
  }
  vctx.drawImage(bitmap, 0, 0);
  bitmap.close();
  const shown = performance.now();
  ar.answered += 1;
  view.dataset.answered = String(ar.answered);
  if (meta) {
    const {taken, sent} = inflight.get(meta.tag) || {};
    inflight.delete(meta.tag);
    ar.last = meta;
    if (meta.overlay) ar.overlays += 1;
    else ar.notes[meta.note] = (ar.notes[meta.note] || 0) + 1;
    if (taken !== undefined) {
      ar.latencies.push(shown - taken);
      if (meta.overlay) ar.overlayLatencies.push(shown - taken);
      if (meta.overlay && sent !== undefined) {
        ar.timings.push({encode: sent - taken, server: meta.server_ms, draw: meta.draw_ms,
                         show: shown - arrived, total: shown - taken});
        if (ar.timings.length > 600) ar.timings.shift();
      }
      if (ar.latencies.length > 600) ar.latencies.shift();
      if (ar.overlayLatencies.length > 600) ar.overlayLatencies.shift();
    }
    $("arnote").textContent = meta.note || "";
  }
  answeredAt.push(shown);
  answeredAt = answeredAt.filter((t) => shown - t < 2000);
  const last = ar.latencies.length ? ar.latencies[ar.latencies.length - 1] : null;
  $("arstatus").textContent = `camera ${ar.camera} · robot ${ar.robot} · ` +
    `${(answeredAt.length / 2).toFixed(1)} fps · ` +
    `${last === null ? "–" : last.toFixed(0)} ms · ${meta && meta.status ? meta.status : ""}`;
  pump();
}

// ---------------------------------------------------------------- controls
function wire() {
  $("arsettings").addEventListener("change", (event) => {
    const el = event.target;
    if (el.id === "camname") {
      ar.camera = el.value.trim();
      try { localStorage.setItem(`slamlensArCamera:${ar.camera.split("-")[0]}`, ar.camera); }
      catch (e) { /* private mode */ }
      if (socket) socket.close();
      return;
    }
    if (el.id === "robot") { ar.robot = el.value; if (socket) socket.close(); return; }
    if (!el.name || el.id === "sendwidth" || el.id === "sendquality") return;
    change({[el.name]: el.type === "checkbox" ? el.checked : el.value});
  });
  $("restart").addEventListener("click", startCamera);
  $("reset").addEventListener("click", () => change({reset: true}));
  $("photo").addEventListener("click", () => {
    if (!video.videoWidth) return;
    const c = document.createElement("canvas");
    c.width = Math.min(video.videoWidth, sendWidth()) & ~1;
    c.height = Math.round(video.videoHeight * c.width / video.videoWidth) & ~1;
    c.getContext("2d").drawImage(video, 0, 0, c.width, c.height);
    c.toBlob((blob) => {
      const a = document.createElement("a");
      a.href = URL.createObjectURL(blob);
      a.download = `slamlens-${ar.camera}-${Date.now()}.png`;
      a.click();
      setTimeout(() => URL.revokeObjectURL(a.href), 10000);
    }, "image/png");
  });
}

(async () => {
  buildLayers();
  wire();
  try {
    await loadSettings();
  } catch (e) {
    showError(`cannot reach the viewer: ${e.message}`);
    return;
  }
  connect();
  await startCamera();
})();
