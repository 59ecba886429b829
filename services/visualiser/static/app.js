// slamlens web viewer: live picture over a websocket, per-tab settings, status, plots.
// Plain script, no build step and no network beyond this server.
"use strict";

const LAYERS = ["robot", "path", "features", "lines", "ellipsoids", "legend", "labels", "health"];
const PLOT_COLOURS = ["#4fc3f7", "#ffb74d", "#81c784", "#e57373", "#ba68c8", "#fff176",
                      "#4db6ac", "#f06292"];

function randomId() {
  const bytes = new Uint8Array(8);
  crypto.getRandomValues(bytes);
  return Array.from(bytes, (b) => b.toString(16).padStart(2, "0")).join("");
}

// One id per browser tab (sessionStorage): each tab keeps its own view settings.
const client = (() => {
  try {
    let id = sessionStorage.getItem("slamlensClient");
    if (!id) { id = randomId(); sessionStorage.setItem("slamlensClient", id); }
    return id;
  } catch (e) {
    return randomId();
  }
})();

// State visible to tests and to the curious (window.slamlens in the console).
const app = window.slamlens = {
  client, frames: 0, seq: null, settings: null, features: null, recording: false,
  errors: 0,
};

const $ = (id) => document.getElementById(id);
const form = $("settings");
const canvas = $("video");
const ctx = canvas.getContext("2d");

function q(path, extra) {
  const params = new URLSearchParams({client, ...(extra || {})});
  return `${path}?${params}`;
}

async function api(path, options, extra) {
  const response = await fetch(q(path, extra), options);
  const body = await response.json().catch(() => ({error: response.statusText}));
  if (!response.ok) throw new Error(body.error || response.statusText);
  return body;
}

function showError(message) {
  $("error").textContent = message || "";
  if (message) app.errors += 1;
}

// ---------------------------------------------------------------- live picture
let socket = null;
let meta = null;

function connect() {
  const scheme = location.protocol === "https:" ? "wss" : "ws";
  socket = new WebSocket(`${scheme}://${location.host}${q("/ws")}`);
  socket.binaryType = "blob";
  socket.onmessage = async (event) => {
    if (typeof event.data === "string") { meta = JSON.parse(event.data); return; }
    try {
      const bitmap = await createImageBitmap(event.data);
      if (canvas.width !== bitmap.width || canvas.height !== bitmap.height) {
        canvas.width = bitmap.width;
        canvas.height = bitmap.height;
      }
      ctx.drawImage(bitmap, 0, 0);
      bitmap.close();
      app.frames += 1;
      app.seq = meta ? meta.seq : null;
      canvas.dataset.frames = String(app.frames);
      $("frameinfo").textContent =
        `frame ${app.frames} · state seq ${app.seq === null ? "–" : app.seq}`;
    } finally {
      if (socket.readyState === WebSocket.OPEN) socket.send("next");  // flow control
    }
  };
  socket.onclose = () => setTimeout(connect, 1000);
}

// ---------------------------------------------------------------- settings
function buildLayers() {
  const box = $("layers");
  for (const name of LAYERS) {
    const label = document.createElement("label");
    label.innerHTML = `<input type="checkbox" name="${name}"> ${name}`;
    box.appendChild(label);
  }
}

function bgrToCss(bgr) {
  return Array.isArray(bgr) ? `rgb(${bgr[2]},${bgr[1]},${bgr[0]})` : "";
}

function showSettings(settings) {
  app.settings = settings;
  for (const element of form.elements) {
    if (!element.name || !(element.name in settings)) continue;
    const value = settings[element.name];
    if (element.type === "checkbox") element.checked = Boolean(value);
    else if (element.dataset.log) element.value = String(Math.log10(value));
    else element.value = value === null ? "" : String(value);
  }
  $("scaleout").textContent = `×${Number(settings.scale).toFixed(2)}`;
  $("glyphmeaning").textContent = settings.glyph === "sigma"
    ? `semi-axes ${settings.sigma_k}·√λ of P_d (m) × ${Number(settings.scale).toFixed(2)}`
    : `semi-axes λ of P_d (m² read as m) × ${Number(settings.scale).toFixed(2)}`;
  const swatches = document.querySelectorAll(".legend .sw");
  const colours = [settings.colour_robot, settings.colour_lines, settings.colour_features,
                   settings.colour_ellipsoids, settings.colour_violation];
  swatches.forEach((sw, i) => { if (colours[i]) sw.style.background = bgrToCss(colours[i]); });
  $("snapshot").href = q("/snapshot.png", {download: "1"});
  $("mjpeg").href = q("/stream.mjpg");
}

async function change(changes) {
  try {
    const body = await api("/api/settings", {
      method: "POST", headers: {"Content-Type": "application/json"},
      body: JSON.stringify(changes),
    });
    showError("");
    showSettings(body.settings);
    refreshSeries();
  } catch (e) {
    showError(e.message);
    if (app.settings) showSettings(app.settings);  // put the controls back
  }
}

form.addEventListener("change", (event) => {
  const element = event.target;
  if (!element.name) return;
  let value;
  if (element.type === "checkbox") value = element.checked;
  else if (element.dataset.log) value = Math.pow(10, Number(element.value));
  else value = element.value;
  change({[element.name]: value});
});
form.addEventListener("submit", (event) => event.preventDefault());
$("reset").addEventListener("click", () => change({reset: true}));

// Click a feature in the picture: only its correlations; click it again: all pairs.
canvas.addEventListener("click", (event) => {
  const features = app.features;
  if (!features || !features.ids.length) return;
  const rect = canvas.getBoundingClientRect();
  const u = (event.clientX - rect.left) * canvas.width / rect.width;
  const v = (event.clientY - rect.top) * canvas.height / rect.height;
  let best = null;
  let bestDistance = 30 * canvas.width / rect.width;  // 30 screen pixels
  features.uv.forEach((uv, i) => {
    if (!uv) return;
    const d = Math.hypot(uv[0] - u, uv[1] - v);
    if (d < bestDistance) { best = features.ids[i]; bestDistance = d; }
  });
  if (best === null) return;
  const selected = app.settings && app.settings.selected_feature === best ? null : best;
  change({selected_feature: selected});
});

async function refreshFeatures() {
  try {
    const features = await api("/api/features");
    app.features = features;
    const select = $("feature");
    const wanted = ["", ...features.ids.map(String)];
    const have = Array.from(select.options, (o) => o.value);
    if (wanted.join(",") !== have.join(",")) {
      select.innerHTML = '<option value="">none (all)</option>' +
        features.ids.map((id) => `<option value="${id}">feature ${id}</option>`).join("");
    }
    select.value = features.selected === null ? "" : String(features.selected);
  } catch (e) { /* the next poll will try again */ }
}

// ---------------------------------------------------------------- recording
$("record").addEventListener("click", async () => {
  const button = $("record");
  try {
    if (!app.recording) {
      const info = await api("/api/record/start", {method: "POST"});
      app.recording = true;
      button.classList.add("on");
      button.textContent = "■ stop";
      $("recordinfo").textContent = `recording ${info.file}…`;
    } else {
      const info = await api("/api/record/stop", {method: "POST"});
      app.recording = false;
      button.classList.remove("on");
      button.textContent = "● record";
      $("recordinfo").innerHTML =
        `<a href="${info.url}" download>${info.file}</a> (${info.frames} frames)`;
    }
    showError("");
  } catch (e) { showError(e.message); }
});

// ---------------------------------------------------------------- status and health
function age(seconds) {
  return seconds === null || seconds === undefined ? "–" : `${seconds.toFixed(2)} s`;
}

async function refreshStatus() {
  try {
    const s = await api("/api/status");
    const parts = [`robot ${s.robot}`, `${s.view} view`];
    for (const c of s.cameras) {
      const f = c.frame;
      parts.push(`camera ${c.name}: ` + (f ? `frame age ${age(f.age_s)}, ${f.rate_hz.toFixed(1)} Hz`
                                           : "no frames") +
                 (c.registration ? `, ${c.registration.status}` : ", not registered"));
    }
    if (s.state) {
      parts.push(`state seq ${s.state.seq} (${s.state.step}), age ${age(s.state.age_s)}, ` +
                 `n = ${s.state.n}`);
    } else {
      parts.push("no state yet");
    }
    parts.push(`${s.fps.toFixed(1)} fps`);
    if (s.health) {
      parts.push(s.health.ok ? "health ok"
                             : `<span class="bad">${s.health.violations} violation(s)</span>`);
    }
    const bad = Object.entries(s.bad_messages).map(([k, n]) => `${k} ${n}`).join(", ");
    if (bad) parts.push(`<span class="bad">bad messages: ${bad}</span>`);
    $("status").innerHTML = parts.join(" · ");
  } catch (e) {
    $("status").textContent = "viewer unreachable";
  }
}

function describe(v) {
  const value = v.growth !== undefined ? `growth ${v.growth.toExponential(2)}`
                                       : `statistic ${Number(v.statistic).toFixed(2)}`;
  const bound = v.bound !== undefined ? ` (bound ${Number(v.bound).toPrecision(3)})` : "";
  const ids = v.ids && v.ids.length ? ` features ${v.ids.join("–")}` : "";
  return `seq ${v.seq ?? v.step}: ${v.kind}${ids}, ${value}${bound}` +
         (v.detail ? ` — ${v.detail}` : "");
}

async function refreshHealth() {
  try {
    const h = await api("/api/health");
    const list = $("violations");
    const ok = $("healthok");
    if (!h.latest) { ok.textContent = ""; return; }
    ok.className = h.latest.ok ? "ok" : "notok";
    ok.textContent = h.latest.ok ? `(ok at seq ${h.latest.seq})`
      : `(seq ${h.latest.seq}: suspects ${h.latest.suspects.join(", ") || "none"})`;
    const items = h.recent.slice(0, 60).map((v) => `<li>${describe(v)}</li>`);
    list.innerHTML = items.length ? items.join("") : "<li>none so far</li>";
  } catch (e) { /* next poll */ }
}

// ---------------------------------------------------------------- plots
function plot(canvasElement, title, xs, lines, bands, options) {
  const log = Boolean(options && options.log);  // log10 y axis (χ² statistics span decades)
  const ty = (y) => (y === null || y === undefined ? null
                     : log ? Math.log10(Math.max(y, 1e-4)) : y);
  lines = lines.map((line) => ({...line, values: line.values.map(ty)}));
  bands = (bands || []).map((band) => ({...band, lo: band.lo.map(ty), hi: band.hi.map(ty)}));
  const g = canvasElement.getContext("2d");
  const W = canvasElement.width, H = canvasElement.height;
  const L = 56, R = 8, T = 20, B = 20;
  g.clearRect(0, 0, W, H);
  g.fillStyle = "#ccc";
  g.font = "12px sans-serif";
  g.fillText(title, L, 13);
  const values = [];
  for (const line of lines) for (const y of line.values) if (y !== null) values.push(y);
  for (const band of bands || []) for (const y of [...band.lo, ...band.hi]) if (y !== null) values.push(y);
  const finiteX = xs.filter((x) => x !== null);
  if (!values.length || finiteX.length < 1) {
    g.fillText("no data yet", L, H / 2);
    return;
  }
  let y0 = Math.min(...values), y1 = Math.max(...values);
  if (y1 - y0 < 1e-12) { y0 -= Math.abs(y0) * 0.1 + 1e-9; y1 += Math.abs(y1) * 0.1 + 1e-9; }
  const x0 = Math.min(...finiteX), x1 = Math.max(...finiteX, x0 + 1e-9);
  const px = (x) => L + (x - x0) / (x1 - x0) * (W - L - R);
  const py = (y) => T + (1 - (y - y0) / (y1 - y0)) * (H - T - B);
  g.strokeStyle = "#555";
  g.strokeRect(L, T, W - L - R, H - T - B);
  g.fillStyle = "#999";
  const label = (y) => (log ? Math.pow(10, y) : y).toPrecision(3);
  g.fillText(label(y1), 2, T + 10);
  g.fillText(label(y0), 2, H - B);
  g.fillText(`t ${x0.toFixed(1)} … ${x1.toFixed(1)} s`, L, H - 5);
  for (const band of bands || []) {
    g.fillStyle = band.colour;
    g.globalAlpha = 0.25;
    g.beginPath();
    let started = false;
    xs.forEach((x, i) => {
      if (band.hi[i] === null) return;
      if (!started) { g.moveTo(px(x), py(band.hi[i])); started = true; } else g.lineTo(px(x), py(band.hi[i]));
    });
    for (let i = xs.length - 1; i >= 0; i--) if (band.lo[i] !== null) g.lineTo(px(xs[i]), py(band.lo[i]));
    g.closePath();
    g.fill();
    g.globalAlpha = 1;
  }
  let legendX = L + 4;
  for (const line of lines) {
    g.strokeStyle = line.colour;
    g.setLineDash(line.dash ? [5, 4] : []);
    g.lineWidth = 1.5;
    g.beginPath();
    let pen = false;
    xs.forEach((x, i) => {
      const y = line.values[i];
      if (y === null || y === undefined) { pen = false; return; }
      if (!pen) { g.moveTo(px(x), py(y)); pen = true; } else g.lineTo(px(x), py(y));
    });
    g.stroke();
    g.setLineDash([]);
    if (line.label) {
      g.fillStyle = line.colour;
      g.fillText(line.label, legendX, T + 12);
      legendX += g.measureText(line.label).width + 12;
    }
  }
}

// The monitor's statistics named PREFIX…, each with its bounds: X_lo / X_hi, or for a
// window mean "X_window_mean" the bounds "X_window_lo" / "X_window_hi".
function statLines(stats, prefix) {
  const lines = [];
  let k = 0;
  for (const name of Object.keys(stats)) {
    if (!name.startsWith(prefix) || name.endsWith("_lo") || name.endsWith("_hi")) continue;
    const colour = PLOT_COLOURS[k++ % PLOT_COLOURS.length];
    lines.push({label: name, values: stats[name], colour});
    const stem = stats[name + "_lo"] ? name : name.replace(/_mean$/, "");
    for (const suffix of ["_lo", "_hi"]) {
      if (stats[stem + suffix]) lines.push({values: stats[stem + suffix], colour, dash: true});
    }
  }
  return lines;
}

// Statistics that are not NEES or NIS (counts, largest growth…): their latest values.
function showStats(stats) {
  const parts = [];
  for (const [name, values] of Object.entries(stats)) {
    if (name.startsWith("nees") || name.startsWith("nis")) continue;
    const last = values[values.length - 1];
    if (last !== null && last !== undefined) parts.push(`${name} ${Number(last).toPrecision(3)}`);
  }
  $("stats").textContent = parts.join(" · ");
}

async function refreshSeries() {
  try {
    const text = $("pairs").value.trim();
    const data = await api("/api/series", undefined, text ? {pairs: text} : undefined);
    app.series = data;
    const t = data.state.t;
    plot($("plot-pairs"), `P_d size per pair — ${data.size}`, t,
         data.pairs.map((p, i) => ({label: p.label, values: p.values,
                                     colour: PLOT_COLOURS[i % PLOT_COLOURS.length]})));
    const lines = [], bands = [];
    data.clusters.forEach((c, i) => {
      const colour = PLOT_COLOURS[i % PLOT_COLOURS.length];
      lines.push({label: `clusters ${c.label}`, values: c.mean, colour});
      bands.push({lo: c.min, hi: c.max, colour});
    });
    plot($("plot-clusters"), "min / mean / max P_d size per cluster pair", t, lines, bands);
    const stats = data.health.stats;
    for (const [prefix, id, title] of [
      ["nees", "plot-nees", "NEES (with truth) and χ² bounds (dashed), log scale"],
      ["nis", "plot-nis", "NIS and χ² bounds (dashed), log scale"]]) {
      plot($(id), title, data.health.t, statLines(stats, prefix), [], {log: true});
    }
    showStats(stats);  } catch (e) { /* next poll */ }
}

// ---------------------------------------------------------------- start
async function start() {
  buildLayers();
  try {
    const body = await api("/api/settings");
    showSettings(body.settings);
  } catch (e) { showError(e.message); }
  connect();
  refreshStatus();
  refreshFeatures();
  refreshHealth();
  refreshSeries();
  setInterval(refreshStatus, 1000);
  setInterval(refreshFeatures, 1000);
  setInterval(refreshHealth, 1000);
  setInterval(refreshSeries, 2000);
}

$("pairs").addEventListener("change", refreshSeries);
start();
