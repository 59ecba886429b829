// slamlens web viewer: live picture over a websocket, per-tab settings, status, plots.
// Plain script, no build step and no network beyond this server.
"use strict";

const LAYERS = ["robot", "path", "features", "lines", "ellipsoids", "legend", "labels", "health",
                "rejected"];
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
  if ((element.id === "feature" || element.id === "cluster") && element.value.includes("|")) {
    const [robot, id] = element.value.split("|");  // several robots: R|id
    change({selected_robot: robot, [element.name]: id});
    return;
  }
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
  let best = null, bestRobot = null;
  let bestDistance = 30 * canvas.width / rect.width;  // 30 screen pixels
  features.uv.forEach((uv, i) => {
    if (!uv) return;
    const d = Math.hypot(uv[0] - u, uv[1] - v);
    if (d < bestDistance) { best = features.ids[i]; bestRobot = features.robot[i]; bestDistance = d; }
  });
  if (best === null) return;
  const several = new Set(features.robot).size > 1;
  const same = app.settings && app.settings.selected_feature === best &&
    (!several || app.settings.selected_robot === bestRobot);
  if (several) {
    change(same ? {selected_feature: null, selected_robot: null}
                : {selected_feature: best, selected_robot: bestRobot});
  } else {
    change({selected_feature: same ? null : best});
  }
});

async function refreshFeatures() {
  try {
    const features = await api("/api/features");
    app.features = features;
    const select = $("feature");
    const several = new Set(features.robot).size > 1;
    const value = (i) => (several ? `${features.robot[i]}|${features.ids[i]}` : String(features.ids[i]));
    const wanted = ["", ...features.ids.map((_, i) => value(i))];
    const have = Array.from(select.options, (o) => o.value);
    if (wanted.join(",") !== have.join(",")) {
      select.innerHTML = '<option value="">none (all)</option>' + features.ids.map((id, i) =>
        `<option value="${esc(value(i))}">${several ? esc(features.robot[i]) + ": " : ""}` +
        `feature ${id}</option>`).join("");
    }
    select.value = features.selected === null ? ""
      : several ? `${features.selected_robot}|${features.selected}` : String(features.selected);
    // clusters of the view's clustering, per robot (known once a picture was clustered)
    const clusters = $("cluster");
    const options = [];
    for (const [robot, ids] of Object.entries(features.clusters || {})) {
      for (const id of [...new Set(ids.filter((c) => c !== null))].sort((a, b) => a - b)) {
        options.push([several ? `${robot}|${id}` : String(id),
                      `${several ? robot + ": " : ""}cluster ${id}`]);
      }
    }
    const wantedClusters = ["", ...options.map(([v]) => v)];
    if (wantedClusters.join(",") !== Array.from(clusters.options, (o) => o.value).join(",")) {
      clusters.innerHTML = '<option value="">none</option>' + options.map(([v, label]) =>
        `<option value="${esc(v)}">${esc(label)}</option>`).join("");
    }
    const chosen = features.selected_cluster;
    clusters.value = chosen === null ? ""
      : several ? `${features.selected_robot}|${chosen}` : String(chosen);
    // above the glyph budget the picture is an overview: say so beside the picture
    $("overview").textContent = Object.entries(features.overview || {}).map(([robot, note]) =>
      (several ? `${robot}: ` : "") + note).join(" · ");
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

function esc(text) {
  return String(text).replace(/[&<>"]/g, (c) => ({"&": "&amp;", "<": "&lt;", ">": "&gt;",
                                                    '"': "&quot;"}[c]));
}

// The robot whose verdict and plots the bottom panels show (the first one by default).
function chosenRobot() {
  const select = $("robot");
  return select.value || (app.status && app.status.robot) || "";
}

function showRobots(s) {
  const select = $("robot");
  const names = s.robots.map((r) => r.name);
  const have = Array.from(select.options, (o) => o.value);
  if (names.join(",") !== have.join(",")) {
    const keep = select.value;
    select.innerHTML = names.map((n) => `<option value="${esc(n)}">robot ${esc(n)}</option>`)
      .join("");
    if (names.includes(keep)) select.value = keep;
  }
  select.hidden = names.length < 2;
  // the top bar: one verdict per robot, in the monitor's words (the same as the legend's)
  $("verdicts").innerHTML = s.robots.map((r) => {
    const h = r.health;
    const words = h ? h.verdict_text : "no verdict yet";
    const cls = h ? `v-${h.verdict}` : "";
    const restarted = r.map_restarted ? ' <span class="restarted">map restarted</span>' : "";
    return `<span data-robot="${esc(r.name)}"><span class="sw" style="background:${r.colour}">` +
           `</span>${esc(r.name)}: <span class="${cls}">${esc(words)}</span>${restarted}</span>`;
  }).join("");
  $("robotlegend").innerHTML = s.robots.length < 2 ? "" : s.robots.map((r) =>
    `<li><span class="sw" style="background:${r.colour}"></span>robot ${esc(r.name)}: cone, ` +
    "path and (lighter) feature cones</li>").join("");
  const notes = [];
  for (const r of s.robots) {
    if (r.map_restarted) {
      notes.push(`map restarted: the estimator of robot ${r.name} began a new map ` +
                 "(the old map's path and plots were dropped)");
    }
    for (const [camera, reg] of Object.entries(r.registration || {})) {
      if (reg === "stale") notes.push(`waiting for camera ${camera} to register the new map ` +
                                      `of robot ${r.name}`);
    }
  }
  for (const note of Object.values(s.sources || {})) if (note) notes.push(note);
  $("notes").textContent = notes.join(" · ");
  $("reregister").hidden = !s.cameras.length;
}

// Every registration made (newest first, five shown): why, who asked, how far it moved.
function showRegistrations(events) {
  $("registrations").innerHTML = events.slice(0, 5).map((e) => {
    const moved = e.moved_m === null || e.moved_m === undefined ? "" :
      `: the map frame moved ${e.moved_m.toFixed(3)} m / ${(e.moved_deg || 0).toFixed(1)}°`;
    const when = new Date(e.at * 1000).toLocaleTimeString();
    return `<li class="${e.refused ? "bad" : ""}">${esc(when)} camera ${esc(e.camera)}, ` +
           `robot ${esc(e.robot)}: ${esc(e.reason)}${esc(moved)}</li>`;
  }).join("");
}

async function refreshStatus() {
  try {
    const s = await api("/api/status");
    app.status = s;
    showRobots(s);
    const parts = [s.discover ? "robots: every live estimator" : `robot ${s.robot}`,
                   `${s.view} view`];
    for (const c of s.cameras) {
      const f = c.frame;
      parts.push(`camera ${c.name}: ` + (f ? `frame age ${age(f.age_s)}, ${f.rate_hz.toFixed(1)} Hz`
                                           : "no frames") +
                 (c.registration ? `, ${c.registration.status}` : ", not registered"));
    }
    for (const r of s.robots) {
      const st = r.state;
      parts.push(st ? `${s.robots.length > 1 ? r.name + ": " : ""}state seq ${st.seq} ` +
                      `(${st.step}), age ${age(st.age_s)}, n = ${st.n}` + inputCounts(st.inputs)
                    : `${r.name}: no state yet`);
    }
    if (!s.robots.length) parts.push("no state yet");
    parts.push(`${s.fps.toFixed(1)} fps`);
    const bad = Object.entries(s.bad_messages).map(([k, n]) => `${k} ${n}`).join(", ");
    if (bad) parts.push(`<span class="bad">bad messages: ${esc(bad)}</span>`);
    $("status").innerHTML = parts.join(" · ");
    showRegistrations(s.registrations || []);
  } catch (e) {
    $("status").textContent = "viewer unreachable";
  }
}

// The estimator's input counts (docs/protocol.md): shown when any is not zero; late and
// lost inputs mean the map is not what an in-order run would have made.
function inputCounts(inputs) {
  if (!inputs) return "";
  const named = ["late", "lost", "duplicates", "waited", "reordered"]
    .filter((k) => inputs[k] > 0).map((k) => `${inputs[k]} ${k}`);
  if (!named.length) return "";
  const bad = (inputs.late || 0) + (inputs.lost || 0) > 0;
  return `, <span class="${bad ? "bad" : ""}" id="input-counts">inputs: ${esc(named.join(", "))}</span>`;
}

async function refreshHealth() {
  try {
    const robot = chosenRobot();
    const h = await api("/api/health", undefined, robot ? {robot} : undefined);
    app.health = h;
    const verdict = $("verdict");
    if (!h.latest) {
      verdict.className = "verdict";
      verdict.textContent = "no verdict yet";
      $("standing").innerHTML = "<li>none</li>";
      return;
    }
    verdict.className = `verdict v-${h.latest.verdict}`;
    verdict.textContent = h.latest.verdict_text;
    verdict.dataset.verdict = h.latest.verdict;
    const standing = h.latest.standing.map((v) => `<li>${esc(v.text)}</li>`);
    $("standing").innerHTML = standing.length ? standing.join("") : "<li>none</li>";
    const items = h.recent.slice(0, 60).map((v) => `<li>seq ${v.seq ?? v.step}: ${esc(v.text)}</li>`);
    $("violations").innerHTML = items.length ? items.join("") : "<li>none so far</li>";
  } catch (e) { /* next poll */ }
}

$("robot").addEventListener("change", () => { refreshHealth(); refreshSeries(); });

$("reregister").addEventListener("click", async () => {
  const info = $("reregisterinfo");
  const robot = chosenRobot();
  info.textContent = "asking…";
  try {
    const body = await api("/api/reregister", {method: "POST"}, robot ? {robot} : undefined);
    app.reregister = body;
    info.textContent = body.cameras.map((c) => `${c.camera}: ${c.detail}`).join("; ");
    info.className = body.answered ? "" : "bad";
    showError("");
  } catch (e) { info.textContent = ""; showError(e.message); }
});

// ---------------------------------------------------------------- plots (uPlot)
// Each plot is a uPlot chart (static/vendor/uplot): real axes with ticks, a cursor
// read-out in the legend, drag to zoom (double-click resets), every series drawn with its
// gaps bridged (NIS exists only on update states). Charts are rebuilt when their series
// change, else given new data (keeping a zoom the user made).
const charts = app.charts = {};
const AXIS = {stroke: "#aaa", grid: {stroke: "#34393b", width: 1}, ticks: {stroke: "#555"}};

function fill(colour, alpha) {
  const hex = colour.replace("#", "");
  const [r, g, b] = [0, 2, 4].map((k) => parseInt(hex.slice(k, k + 2), 16));
  return `rgba(${r},${g},${b},${alpha})`;
}

// spec: {title, ylabel, log, xs, series: [{label, values, colour, width, dash}],
//        bands: [[hiIndex, loIndex, colour]]}  (indices into spec.series)
function drawChart(id, spec) {
  const box = $(id);
  const xs = spec.xs;
  const finite = spec.series.some((s) => s.values.some((v) => v !== null && v !== undefined));
  if (!xs.length || !finite) {
    if (charts[id]) { charts[id].destroy(); delete charts[id]; }
    box.innerHTML = `<div class="empty">${esc(spec.title)}: no data yet</div>`;
    return;
  }
  const clean = (v) => (v === null || v === undefined || !isFinite(v) ||
                        (spec.log && v <= 0) ? null : v);
  const data = [xs, ...spec.series.map((s) => s.values.map(clean))];
  const key = JSON.stringify([spec.title, spec.log, spec.series.map((s) => s.label),
                              spec.bands || []]);
  const width = Math.max(300, box.clientWidth - 8);
  let chart = charts[id];
  if (chart && chart.slamlensKey === key) {
    chart.setData(data, !chart.slamlensZoomed);
    if (Math.abs(chart.width - width) > 4) chart.setSize({width, height: chart.height});
    return;
  }
  if (chart) chart.destroy();
  box.innerHTML = "";
  const opts = {
    title: spec.title, width, height: 240,
    scales: {x: {time: false}, y: spec.log ? {distr: 3, log: 10} : {}},
    axes: [{...AXIS, label: "t (s)", labelSize: 18},
           {...AXIS, label: spec.ylabel, labelSize: 18, size: 64}],
    series: [{label: "t (s)", value: (u, v) => (v === null ? "–" : v.toFixed(2))},
             ...spec.series.map((s) => ({
               label: s.label, stroke: s.colour, width: s.width || 1.5, dash: s.dash,
               spanGaps: true, points: {show: false},
               value: (u, v) => (v === null || v === undefined ? "–" : Number(v).toPrecision(3)),
             }))],
    bands: (spec.bands || []).map(([hi, lo, colour]) => ({series: [hi + 1, lo + 1],
                                                          fill: fill(colour, 0.18)})),
    cursor: {drag: {x: true, y: false}},
    legend: {live: true},
    hooks: {setSelect: [(u) => { if (u.select.width > 0) u.slamlensZoomed = true; }]},
  };
  chart = new uPlot(opts, data, box);
  chart.slamlensKey = key;
  chart.slamlensZoomed = false;
  chart.over.addEventListener("dblclick", () => { chart.slamlensZoomed = false; });
  charts[id] = chart;
}

// The monitor's statistics named PREFIX…: a line each; a statistic X with bounds X_lo /
// X_hi (for a window mean "X_window_mean": X_window_lo / _hi) gets its band filled
// between them (the 95 % χ² band) and its bounds dashed; the window mean — the running
// average — is drawn thicker.
function statSpec(stats, prefix) {
  const series = [], bands = [];
  let k = 0;
  for (const name of Object.keys(stats).sort()) {
    if (!name.startsWith(prefix) || name.endsWith("_lo") || name.endsWith("_hi")) continue;
    const colour = PLOT_COLOURS[k++ % PLOT_COLOURS.length];
    const running = name.endsWith("_window_mean");
    const label = running ? `${name} (running average)` : name;
    series.push({label, values: stats[name], colour, width: running ? 2.5 : 1.2});
    const stem = stats[name + "_lo"] ? name : name.replace(/_mean$/, "");
    if (stats[stem + "_lo"] && stats[stem + "_hi"]) {
      const hi = series.push({label: `${stem}_hi`, values: stats[stem + "_hi"], colour,
                              width: 1, dash: [5, 4]}) - 1;
      const lo = series.push({label: `${stem}_lo`, values: stats[stem + "_lo"], colour,
                              width: 1, dash: [5, 4]}) - 1;
      bands.push([hi, lo, colour]);
    }
  }
  return {series, bands};
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
    const robot = chosenRobot();
    const extra = {...(text ? {pairs: text} : {}), ...(robot ? {robot} : {})};
    const data = await api("/api/series", undefined, extra);
    app.series = data;
    const t = data.state.t;
    drawChart("plot-pairs", {
      title: "P_d size per pair", ylabel: "√λmax of P_d (m)", xs: t,
      series: data.pairs.map((p, i) => ({label: `pair ${p.label}`, values: p.values,
                                         colour: PLOT_COLOURS[i % PLOT_COLOURS.length]}))});
    const series = [], bands = [];
    data.clusters.forEach((c, i) => {
      const colour = PLOT_COLOURS[i % PLOT_COLOURS.length];
      series.push({label: `clusters ${c.label} mean`, values: c.mean, colour, width: 2});
      const hi = series.push({label: `${c.label} max`, values: c.max, colour, width: 0.8}) - 1;
      const lo = series.push({label: `${c.label} min`, values: c.min, colour, width: 0.8}) - 1;
      bands.push([hi, lo, colour]);
    });
    drawChart("plot-clusters", {title: "min / mean / max P_d size per cluster pair",
                                ylabel: "√λmax of P_d (m)", xs: t, series, bands});
    const stats = data.health.stats;
    for (const [prefix, id, title] of [
      ["nees", "plot-nees", "NEES (with truth): 95 % band, running average"],
      ["nis", "plot-nis", "NIS: 95 % band, running average"]]) {
      drawChart(id, {title, ylabel: prefix.toUpperCase() + " (log)", log: true,
                     xs: data.health.t, ...statSpec(stats, prefix)});
    }
    showStats(stats);
  } catch (e) { /* next poll */ }
}

// ---------------------------------------------------------------- start
async function start() {
  if (typeof uPlot === "undefined") showError("the plotting library did not load");
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
  window.addEventListener("resize", () => {
    for (const [id, chart] of Object.entries(charts)) {
      chart.setSize({width: Math.max(300, $(id).clientWidth - 8), height: chart.height});
    }
  });
}

$("pairs").addEventListener("change", refreshSeries);
start();
