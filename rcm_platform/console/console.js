/* The RCM platform console (CONTRACTS §9): plain JavaScript, no library, no other origin.
 *
 * State arrives pushed on one event stream (/console/api/events, Server-Sent Events read through fetch so that
 * an RDAPI token can go in the Authorization header): a "snapshot" first, then "patch"es with what changed (robots
 * and servers by changed row: applyRows).
 * Forms call the RDAPI itself and show its "reason" beside them. Everything users named is rendered with
 * textContent / createElement, never innerHTML.
 */
"use strict";

const state = { robots: [], servers: [], logics: {}, spaces: {}, seq: 0, at: 0, details: {} };
const ui = { view: "overview", robot: null, topic: "", stream: null, topicStream: null, rowCache: new Map(),
             robotNames: "" };
const TOKEN_KEY = "rcmp_console_token";

// -- small DOM helpers ---------------------------------------------------------------------------------------
function $(id) { return document.getElementById(id); }
function el(tag, attrs, ...children) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attrs || {})) {
    if (value === null || value === undefined || value === false) continue;
    if (key === "class") node.className = value;
    else if (key === "text") node.textContent = String(value);
    else node.setAttribute(key, value === true ? "" : String(value));
  }
  for (const child of children) {
    if (child === null || child === undefined) continue;
    node.appendChild(typeof child === "string" ? document.createTextNode(child) : child);
  }
  return node;
}
function badge(word, kind) { return el("span", { class: "state state-" + kind, text: word }); }
function yesNo(value, yes, no) { return value ? badge(yes, "yes") : badge(no, "no"); }
function stateBadge(s) { return badge(s || "unknown", ["running", "starting", "stopping", "exited", "failed"].includes(s) ? s : "no"); }
function localTime(seconds) { return seconds ? new Date(seconds * 1000).toLocaleString() : ""; }
function replaceChildren(node, children) {
  while (node.firstChild) node.removeChild(node.firstChild);
  for (const child of children) node.appendChild(child);
}
/* Make `children` the element children of `node`, moving only what is not in place already (a long table whose
   one row changed costs one replaced row, not the whole table). */
function placeChildren(node, children) {
  const keep = new Set(children);
  for (const child of Array.from(node.children)) if (!keep.has(child)) node.removeChild(child);
  children.forEach((child, i) => { if (node.children[i] !== child) node.insertBefore(child, node.children[i] || null); });
}

// -- RDAPI calls ---------------------------------------------------------------------------------------------
function token() { try { return sessionStorage.getItem(TOKEN_KEY) || ""; } catch (e) { return ""; } }
function headers(extra) {
  const h = Object.assign({}, extra || {});
  if (token()) h["Authorization"] = "Bearer " + token();
  return h;
}
function askForToken(reason) {
  $("token-box").hidden = false;
  $("token-error").textContent = reason || "";
  $("token-input").focus();
}
async function rdapi(path, body) {
  const options = body === undefined ? { headers: headers() }
    : { method: "POST", headers: headers({ "Content-Type": "application/json" }), body: JSON.stringify(body) };
  let response;
  try {
    response = await fetch(path, options);
  } catch (e) {
    return { result: "ERROR", reason: "the master did not answer: " + e.message };
  }
  let answer;
  try { answer = await response.json(); } catch (e) {
    answer = { result: "ERROR", reason: "the master answered HTTP " + response.status + " without JSON" };
  }
  if (response.status === 401) askForToken(answer.reason);
  return answer;
}

// -- the event stream ----------------------------------------------------------------------------------------
function setLive(kind, text) {
  const live = $("live");
  live.className = "live live-" + kind;
  live.textContent = text;
}

/* Read a Server-Sent Events response body: calls onEvent(name, data) per event; resolves when it ends. */
async function readEvents(response, onEvent, isCurrent) {
  const reader = response.body.getReader();
  const decoder = new TextDecoder();
  let buffer = "";
  for (;;) {
    const { value, done } = await reader.read();
    if (done || !isCurrent()) { try { reader.cancel(); } catch (e) { /* already closed */ } return; }
    buffer += decoder.decode(value, { stream: true });
    let cut;
    while ((cut = buffer.indexOf("\n\n")) >= 0) {
      const block = buffer.slice(0, cut);
      buffer = buffer.slice(cut + 2);
      let name = "message";
      const data = [];
      for (const line of block.split("\n")) {
        if (line.startsWith("event: ")) name = line.slice(7);
        else if (line.startsWith("data: ")) data.push(line.slice(6));
      }
      if (data.length) onEvent(name, JSON.parse(data.join("\n")));
    }
  }
}

function openStream() {
  const id = {};
  ui.stream = id;
  const detail = ui.view === "robot" && ui.robot ? "?ss_name=" + encodeURIComponent(ui.robot) : "";
  const controller = new AbortController();
  id.abort = () => controller.abort();
  setLive("connecting", "connecting…");
  fetch("/console/api/events" + detail, { headers: headers(), signal: controller.signal, cache: "no-store" })
    .then(async (response) => {
      if (response.status === 401) {
        const answer = await response.json().catch(() => ({}));
        setLive("down", "token needed");
        askForToken(answer.reason);
        return "token";
      }
      if (!response.ok) throw new Error("HTTP " + response.status);
      setLive("ok", "live");
      await readEvents(response, onEvent, () => ui.stream === id);
      return "ended";
    })
    .catch((e) => (e.name === "AbortError" ? "aborted" : "error"))
    .then((how) => {
      if (ui.stream !== id || how === "token" || how === "aborted") return;
      setLive("down", "reconnecting…");
      setTimeout(() => { if (ui.stream === id) openStream(); }, 1000);
    });
}
function restartStream() {
  if (ui.stream && ui.stream.abort) ui.stream.abort();
  ui.stream = null;
  openStream();
}

/* A list of rows named by pi_name after a patch's part for it: a whole list as it is (the snapshot's form), or
   {changed, gone[, order]}: gone rows dropped, changed ones replaced where they are, new ones appended in the
   order of `changed`; `order`, when there, names every row in order. */
function applyRows(rows, patch) {
  if (Array.isArray(patch)) return patch;
  const byName = new Map(rows.map((r) => [r.pi_name, r]));
  for (const gone of patch.gone || []) byName.delete(gone);
  for (const [name, row] of Object.entries(patch.changed || {})) byName.set(name, row);
  if (patch.order) return patch.order.filter((n) => byName.has(n)).map((n) => byName.get(n));
  return Array.from(byName.values());
}

function onEvent(name, data) {
  if (name === "snapshot") {
    Object.assign(state, { robots: data.robots, servers: data.servers, logics: data.logics, spaces: data.spaces });
  } else if (name === "patch") {
    if (data.robots) state.robots = applyRows(state.robots, data.robots);
    if (data.servers) state.servers = applyRows(state.servers || [], data.servers);
    for (const key of ["logics", "spaces"]) {
      if (!data[key]) continue;
      for (const gone of data[key].gone) delete state[key][gone];
      Object.assign(state[key], data[key].changed);
    }
  } else if (name === "detail") {
    state.details[data.ss_name] = data.detail;
    renderRobot();
    return;
  } else {
    return;
  }
  state.seq = data.seq;
  state.at = data.at;
  render();
}

// -- rendering -----------------------------------------------------------------------------------------------
function render() {
  const began = performance.now();
  const updated = $("updated");
  updated.textContent = localTime(state.at);
  updated.setAttribute("datetime", new Date(state.at * 1000).toISOString());
  if (state.seq) document.body.dataset.seq = String(state.seq);
  renderRobots();
  renderServers();
  renderLogics();
  renderRobot();
  document.body.dataset.renderMs = (performance.now() - began).toFixed(1);
}

function robotRow(r) {
  const link = el("a", { href: robotHash(r.pi_name, ""), text: r.pi_name });
  return el("tr", { "data-name": r.pi_name },
    el("td", {}, link), el("td", { text: r.service_logic || "" }),
    el("td", {}, yesNo(r.connected, "connected", "not connected")),
    el("td", {}, yesNo(r.paired, "paired", "not paired")),
    el("td", { text: r.server || "" }), el("td", { text: r.address || "" }));
}

function renderRobots() {
  const filter = $("robots-filter").value.trim().toLowerCase();
  const rows = [];
  const seen = new Set();
  for (const r of state.robots) {
    seen.add(r.pi_name);
    if (filter && !r.pi_name.toLowerCase().includes(filter)) continue;
    // a patch replaces a changed row's object and keeps the others: the same object is the same row
    let cached = ui.rowCache.get(r.pi_name);
    if (!cached || (cached.data !== r && JSON.stringify(cached.data) !== JSON.stringify(r))) {
      cached = { data: r, row: robotRow(r) };
      ui.rowCache.set(r.pi_name, cached);
    }
    cached.data = r;
    rows.push(cached.row);
  }
  for (const name of Array.from(ui.rowCache.keys())) if (!seen.has(name)) ui.rowCache.delete(name);
  placeChildren($("robots").tBodies[0], rows);
  const connected = state.robots.filter((r) => r.connected).length;
  const paired = state.robots.filter((r) => r.paired).length;
  $("robots-count").textContent = `(${state.robots.length} provisioned, ${connected} connected, ${paired} paired)`;
  $("robots-empty").hidden = state.robots.length > 0;
  const names = state.robots.map((r) => r.pi_name);
  if (names.join("\n") !== ui.robotNames) {
    ui.robotNames = names.join("\n");
    replaceChildren($("robot-names"), names.map((n) => el("option", { value: n })));
  }
}

function renderServers() {
  $("servers-section").hidden = !state.servers || state.servers.length === 0;
  replaceChildren($("servers").tBodies[0], (state.servers || []).map((s) => el("tr", { "data-name": s.pi_name },
    el("td", { text: s.pi_name }), el("td", {}, yesNo(s.connected, "connected", "not connected")),
    el("td", { text: s.address || "" }),
    el("td", { text: (s.service_spaces || []).length + " / " + (s.max_service_spaces ?? "?") }))));
}

function itemText(kind, item) {
  if (kind === "node") return `${item.sn_name}: rosrun ${item.sn_package} ${item.sn_type} ${item.sn_params || ""} (side ${item.sn_side})`;
  return `${item.sl_name}: roslaunch ${item.sl_package} ${item.sl_file_launcher} ${item.sl_params || ""} (side ${item.sl_side})`;
}

function renderLogics() {
  const names = Object.keys(state.logics);
  $("logics-count").textContent = `(${names.length})`;
  replaceChildren($("logic-names"), names.map((n) => el("option", { value: n })));
  replaceChildren($("logics"), names.map((name) => {
    const logic = state.logics[name];
    const items = [...logic.sn_list.map((i) => el("li", { text: "node " + itemText("node", i) })),
                   ...logic.sl_list.map((i) => el("li", { text: "launcher " + itemText("launcher", i) }))];
    return el("div", { class: "logic", "data-name": name },
      el("h3", {}, name, el("span", { class: "count", text: ` ROS master on the ${logic.ss_side === "R" ? "robot" : "server"} side` })),
      items.length ? el("ul", {}, ...items) : el("p", { class: "empty", text: "no items" }));
  }));
}

function renderRobot() {
  if (ui.view !== "robot") return;
  const name = ui.robot;
  $("rv-name").textContent = name;
  const robot = state.robots.find((r) => r.pi_name === name);
  const space = state.spaces[name];
  const summary = [];
  const add = (term, value) => summary.push(el("dt", { text: term }), el("dd", {}, value));
  if (!robot) add("provisioned", badge("not provisioned", "no"));
  else {
    add("service logic", robot.service_logic || "");
    add("connected", yesNo(robot.connected, "connected", "not connected"));
    add("paired", yesNo(robot.paired, "paired", "not paired"));
    if (robot.server) add("server", robot.server);
    if (robot.address) add("address", robot.address);
  }
  if (space) {
    if (space.ros_master_uri) add("ROS master", space.ros_master_uri);
    if (space.public_ip) add("public_ip", space.public_ip);
    if (space.inbound_port) add("inbound_port", String(space.inbound_port));
    if (space.reason) add("why not paired", el("span", { class: "error", text: space.reason }));
  }
  replaceChildren($("rv-summary"), summary);
  $("rv-no-space").hidden = !!space;
  const rows = [];
  if (space) {
    for (const l of space.r_launchers) rows.push(itemRow(l.sl_name, "launcher", l));
    for (const n of space.r_nodes) rows.push(itemRow(n.sn_name, n.launcher ? "node of " + n.launcher : "node", n));
  }
  replaceChildren($("rv-items").tBodies[0], rows);
  const detail = state.details[name];
  const logs = [];
  if (detail && space) {
    for (const item of detail.items) {
      const title = `${item.kind} ${item.name} on ${item.i_name}`;
      logs.push(el("div", { class: "log", "data-item": item.name }, el("h4", { text: "log of " + title }),
        item.tail !== undefined ? el("pre", { text: item.tail || "(no output yet)" })
          : el("p", { class: "empty", text: `its log is on ${item.i_name}` })));
    }
  }
  replaceChildren($("rv-logs"), logs);
}

function itemRow(name, kind, item) {
  return el("tr", { "data-item": name },
    el("td", { text: name }), el("td", { text: kind }), el("td", { text: item.i_name || "" }),
    el("td", {}, stateBadge(item.state)), el("td", { class: "error", text: item.error || "" }));
}

// -- the live topic view -------------------------------------------------------------------------------------
const plot = { samples: [], type: "", kind: "" };

function stopTopic() {
  if (ui.topicStream && ui.topicStream.abort) ui.topicStream.abort();
  ui.topicStream = null;
}

function openTopic() {
  stopTopic();
  if (ui.view !== "robot") return;
  const id = {};
  ui.topicStream = id;
  const controller = new AbortController();
  id.abort = () => controller.abort();
  plot.samples = [];
  plot.kind = "";
  drawPlot();
  let url = "/console/api/topic?ss_name=" + encodeURIComponent(ui.robot);
  if (ui.topic) url += "&topic=" + encodeURIComponent(ui.topic);
  $("topic-status").textContent = ui.topic ? "waiting for " + ui.topic + "…" : "looking for topics…";
  fetch(url, { headers: headers(), signal: controller.signal, cache: "no-store" })
    .then(async (response) => {
      if (!response.ok) {
        const answer = await response.json().catch(() => ({}));
        $("topic-status").textContent = answer.reason || ("HTTP " + response.status);
        if (response.status === 401) askForToken(answer.reason);
        return response.status === 404 ? "retry" : "stop";
      }
      await readEvents(response, onTopicEvent, () => ui.topicStream === id);
      return "retry";
    })
    .catch((e) => (e.name === "AbortError" ? "stop" : "retry"))
    .then((how) => {
      if (how === "retry" && ui.topicStream === id) setTimeout(() => { if (ui.topicStream === id) openTopic(); }, 2000);
    });
}

function onTopicEvent(name, data) {
  if (name === "topics") {
    const select = $("topic-select");
    const options = [el("option", { value: "", text: "choose a topic…" })];
    for (const [topic, type] of data.topics) options.push(el("option", { value: topic, text: `${topic} (${type})` }));
    replaceChildren(select, options);
    showTopicChoice();
    if (!ui.topic) $("topic-status").textContent = `${data.topics.length} topic(s) in the service space`;
  } else if (name === "samples") {
    plot.type = data.type || "";
    plot.samples = data.samples.slice();
    drawPlot();
  } else if (name === "sample") {
    plot.type = data.type;
    plot.samples.push(data.sample);
    if (plot.samples.length > 600) plot.samples.splice(0, plot.samples.length - 600);
    drawPlot();
  } else if (name === "gone") {
    $("topic-status").textContent = data.reason;
  }
}

/* Samples whose numbers are not finite arrive as the strings "NaN", "Infinity", "-Infinity" (the stream is strict
   JSON); they are counted, not drawn. */
const finitePoint = (s) => Number.isFinite(s.x) && Number.isFinite(s.y);
const finiteValue = (s) => Number.isFinite(s.value);

function drawPlot() {
  const canvas = $("topic-canvas");
  const text = $("topic-text");
  const last = plot.samples[plot.samples.length - 1];
  canvas.dataset.samples = String(plot.samples.length);
  if (!last) { canvas.hidden = true; text.hidden = true; return; }
  let skipped = 0;
  if (last.text !== undefined) {
    canvas.hidden = true;
    text.hidden = false;
    text.textContent = last.text;
  } else {
    const trail = last.x !== undefined;
    const drawable = plot.samples.filter(trail ? finitePoint : finiteValue);
    skipped = plot.samples.filter((s) => (trail ? s.x : s.value) !== undefined).length - drawable.length;
    text.hidden = drawable.length > 0;
    canvas.hidden = drawable.length === 0;
    if (drawable.length === 0) text.textContent = "no finite value yet (the topic sends NaN or Infinity)";
    else if (trail) drawTrail(canvas, drawable); else drawLine(canvas, drawable);
  }
  canvas.dataset.last = JSON.stringify(last);
  canvas.dataset.skipped = String(skipped);
  $("topic-status").textContent = `${ui.topic} (${plot.type}): ${plot.samples.length} sample(s), last at ` +
    new Date(last.t * 1000).toLocaleTimeString() + (skipped ? `; ${skipped} not drawn (NaN or Infinity)` : "");
}

/* The plot's geometry, in CSS pixels: the canvas's backing store is its CSS box times the screen's pixel ratio,
   so text drawn at PLOT_FONT_PX is that size on screen. */
const PLOT_FONT_PX = 14;
const PLOT_PAD = { left: 64, right: 18, top: 14, bottom: 52 };
const TRAIL_MARGIN_PX = 28;   // room around a trail for the robot's marker and heading

function plotContext(canvas) {
  const ratio = window.devicePixelRatio || 1;
  const w = Math.max(1, canvas.clientWidth), h = Math.max(1, canvas.clientHeight);
  if (canvas.width !== Math.round(w * ratio) || canvas.height !== Math.round(h * ratio)) {
    canvas.width = Math.round(w * ratio);
    canvas.height = Math.round(h * ratio);
  }
  const ctx = canvas.getContext("2d");
  ctx.setTransform(ratio, 0, 0, ratio, 0, 0);
  ctx.clearRect(0, 0, w, h);
  const area = { x: PLOT_PAD.left, y: PLOT_PAD.top, w: Math.max(1, w - PLOT_PAD.left - PLOT_PAD.right),
                 h: Math.max(1, h - PLOT_PAD.top - PLOT_PAD.bottom) };
  return { ctx, w, h, area };
}

/* Tick positions every 1, 2 or 5 times a power of ten, about `count` of them over [lo, hi]. */
function ticks(lo, hi, count) {
  const raw = (hi - lo) / Math.max(1, count);
  const power = Math.pow(10, Math.floor(Math.log10(raw)));
  const step = [1, 2, 5, 10].map((m) => m * power).find((s) => s >= raw) || 10 * power;
  const digits = Math.max(0, -Math.floor(Math.log10(step) + 1e-9));
  const out = [];
  for (let v = Math.ceil(lo / step - 1e-9) * step; v <= hi + step * 1e-9; v += step) {
    out.push({ value: v, label: (Math.abs(v) < step / 2 ? 0 : v).toFixed(digits) });
  }
  return out;
}

/* Axes, grid and labels for the ranges x [x0, x1] and y [y0, y1] filling `area`; returns the mapping. The ranges
   and scales are kept on the canvas (data-axes) for whoever checks the drawing. */
function axes(canvas, plotted, xRange, yRange, xTitle, yTitle) {
  const { ctx, area } = plotted;
  const [x0, x1] = xRange, [y0, y1] = yRange;
  const sx = area.w / (x1 - x0), sy = area.h / (y1 - y0);
  const px = (x) => area.x + (x - x0) * sx, py = (y) => area.y + area.h - (y - y0) * sy;
  const font = `${PLOT_FONT_PX}px ${getComputedStyle(canvas).fontFamily || "sans-serif"}`;
  ctx.font = font;
  ctx.lineWidth = 1;
  ctx.strokeStyle = "#e3e7ec";
  ctx.fillStyle = "#3d4450";
  ctx.textAlign = "center";
  ctx.textBaseline = "top";
  const xTicks = ticks(x0, x1, Math.max(2, Math.floor(area.w / 80)));
  for (const t of xTicks) {
    ctx.beginPath(); ctx.moveTo(px(t.value), area.y); ctx.lineTo(px(t.value), area.y + area.h); ctx.stroke();
    ctx.fillText(t.label, px(t.value), area.y + area.h + 6);
  }
  ctx.textAlign = "right";
  ctx.textBaseline = "middle";
  const yTicks = ticks(y0, y1, Math.max(2, Math.floor(area.h / 60)));
  for (const t of yTicks) {
    ctx.beginPath(); ctx.moveTo(area.x, py(t.value)); ctx.lineTo(area.x + area.w, py(t.value)); ctx.stroke();
    ctx.fillText(t.label, area.x - 8, py(t.value));
  }
  ctx.strokeStyle = "#9aa4b1";
  ctx.strokeRect(area.x, area.y, area.w, area.h);
  ctx.textAlign = "center";
  ctx.textBaseline = "bottom";
  ctx.fillText(xTitle, area.x + area.w / 2, plotted.h - 4);
  ctx.save();
  ctx.translate(14, area.y + area.h / 2);
  ctx.rotate(-Math.PI / 2);
  ctx.textBaseline = "middle";
  ctx.fillText(yTitle, 0, 0);
  ctx.restore();
  canvas.dataset.axes = JSON.stringify({
    font, x: { min: x0, max: x1, pxPerUnit: sx, title: xTitle, ticks: xTicks.map((t) => t.label) },
    y: { min: y0, max: y1, pxPerUnit: sy, title: yTitle, ticks: yTicks.map((t) => t.label) } });
  return { ctx, px, py, area };
}

function drawTrail(canvas, pts) {
  const xs = pts.map((p) => p.x), ys = pts.map((p) => p.y);
  const plotted = plotContext(canvas);
  // one scale for both axes (a circle is drawn as a circle): the trail, with room for the robot's marker around
  // it, fills the plot along one axis; the other axis shows more of the plane around the trail
  const minX = Math.min(...xs), maxX = Math.max(...xs), minY = Math.min(...ys), maxY = Math.max(...ys);
  const spanX = Math.max(maxX - minX, 0.5), spanY = Math.max(maxY - minY, 0.5);
  const room = 2 * TRAIL_MARGIN_PX;
  const scale = Math.min(Math.max(1, plotted.area.w - room) / spanX, Math.max(1, plotted.area.h - room) / spanY);
  const cx = (minX + maxX) / 2, cy = (minY + maxY) / 2;
  const halfW = plotted.area.w / scale / 2, halfH = plotted.area.h / scale / 2;
  const { ctx, px, py, area } = axes(canvas, plotted, [cx - halfW, cx + halfW], [cy - halfH, cy + halfH],
                                     "x (m)", "y (m)");
  ctx.save();
  ctx.beginPath();
  ctx.rect(area.x, area.y, area.w, area.h);
  ctx.clip();
  ctx.strokeStyle = "#0a58ca";
  ctx.lineWidth = 2.5;
  ctx.lineJoin = "round";
  ctx.beginPath();
  pts.forEach((p, i) => (i ? ctx.lineTo(px(p.x), py(p.y)) : ctx.moveTo(px(p.x), py(p.y))));
  ctx.stroke();
  const last = pts[pts.length - 1];
  ctx.fillStyle = "#c62828";
  ctx.beginPath();
  ctx.arc(px(last.x), py(last.y), 7, 0, 2 * Math.PI);
  ctx.fill();
  if (Number.isFinite(last.theta)) {
    ctx.strokeStyle = "#c62828";
    ctx.beginPath();
    ctx.moveTo(px(last.x), py(last.y));
    ctx.lineTo(px(last.x) + 20 * Math.cos(last.theta), py(last.y) - 20 * Math.sin(last.theta));
    ctx.stroke();
  }
  ctx.restore();
}

function drawLine(canvas, pts) {
  const newest = pts[pts.length - 1].t;
  const xs = pts.map((p) => p.t - newest), ys = pts.map((p) => p.value);
  let x0 = Math.min(...xs), y0 = Math.min(...ys), y1 = Math.max(...ys);
  if (-x0 < 1) x0 = -1;
  if (y1 - y0 < 1e-9) { y0 -= 1; y1 += 1; }
  const margin = (y1 - y0) * 0.05;
  const { ctx, px, py, area } = axes(canvas, plotContext(canvas), [x0, 0], [y0 - margin, y1 + margin],
                                     "time (s, 0 = newest sample)", "value");
  ctx.save();
  ctx.beginPath();
  ctx.rect(area.x, area.y, area.w, area.h);
  ctx.clip();
  ctx.strokeStyle = "#0a58ca";
  ctx.lineWidth = 2.5;
  ctx.beginPath();
  pts.forEach((p, i) => (i ? ctx.lineTo(px(xs[i]), py(p.value)) : ctx.moveTo(px(xs[i]), py(p.value))));
  ctx.stroke();
  ctx.restore();
}

// -- forms ---------------------------------------------------------------------------------------------------
let itemCounter = 0;
function addItemRow(kind) {
  const prefix = kind === "node" ? "sn" : "sl";
  const fields = kind === "node" ? ["sn_name", "sn_package", "sn_type", "sn_params"]
    : ["sl_name", "sl_package", "sl_file_launcher", "sl_params"];
  const n = ++itemCounter;
  const row = el("div", { class: "item-row", "data-kind": kind });
  for (const field of fields) {
    const id = `item${n}-${field}`;
    row.appendChild(el("label", { for: id }, field, el("input", { id, name: field, autocomplete: "off" })));
  }
  const sideId = `item${n}-${prefix}_side`;
  row.appendChild(el("label", { for: sideId }, `${prefix}_side`,
    el("select", { id: sideId, name: `${prefix}_side` }, el("option", { value: "S", text: "S (server)" }),
      el("option", { value: "R", text: "R (robot)" }))));
  const remove = el("button", { type: "button", class: "secondary", text: `Remove this ${kind}` });
  remove.addEventListener("click", () => row.remove());
  row.appendChild(remove);
  $(kind === "node" ? "sn-rows" : "sl-rows").appendChild(row);
  row.querySelector("input").focus();
}

function formBody(form) {
  if (form.id === "provision-logic") {
    const body = { slg_name: form.elements.slg_name.value.trim(), ss_side: form.elements.ss_side.value,
                   sn_list: [], sl_list: [] };
    for (const row of form.querySelectorAll(".item-row")) {
      const item = {};
      for (const input of row.querySelectorAll("input, select")) item[input.name] = input.value.trim();
      body[row.dataset.kind === "node" ? "sn_list" : "sl_list"].push(item);
    }
    return body;
  }
  const body = {};
  for (const input of form.querySelectorAll("input, select")) body[input.name] = input.value.trim();
  return body;
}

async function submitForm(event) {
  event.preventDefault();
  const form = event.currentTarget;
  const error = form.querySelector(".form-error");
  const ok = form.querySelector(".form-ok");
  error.textContent = "";
  ok.textContent = "";
  const button = form.querySelector("button[type=submit]");
  button.disabled = true;
  try {
    const answer = await rdapi(form.dataset.path, formBody(form));
    if (answer.result === "OK") {
      ok.textContent = String(answer.reason);
      if (form.id === "provision-logic") { replaceChildren($("sn-rows"), []); replaceChildren($("sl-rows"), []); }
      form.reset();
    } else {
      error.textContent = String(answer.reason);
    }
  } finally {
    button.disabled = false;
  }
}

// -- navigation ----------------------------------------------------------------------------------------------
/* Where the address points: the overview (#/), or a robot's page (#/robot/NAME), optionally with the topic to
   show (#/robot/NAME?topic=/pose), so that a link can open a robot's page on its plot. */
function parseHash(hash) {
  const match = hash.match(/^#\/robot\/([^?]+)(?:\?(.*))?$/);
  if (!match) return { view: "overview", robot: null, topic: "" };
  let robot;
  try { robot = decodeURIComponent(match[1]); } catch (e) { robot = match[1]; }
  const topic = new URLSearchParams(match[2] || "").get("topic") || "";
  return { view: "robot", robot, topic: topic.startsWith("/") ? topic : "" };
}
function robotHash(robot, topic) {
  const query = topic ? "?topic=" + encodeURIComponent(topic).replace(/%2F/g, "/") : "";
  return "#/robot/" + encodeURIComponent(robot) + query;
}

function showTopicChoice() {
  const select = $("topic-select");
  if (ui.topic && !Array.from(select.options).some((o) => o.value === ui.topic)) {
    select.appendChild(el("option", { value: ui.topic, text: ui.topic }));
  }
  select.value = ui.topic;
}

function route() {
  const where = parseHash(location.hash);
  const changed = where.view !== ui.view || where.robot !== ui.robot;
  const topicChanged = where.topic !== ui.topic;
  ui.view = where.view;
  ui.robot = where.robot;
  ui.topic = where.topic;
  $("overview").hidden = ui.view !== "overview";
  $("robot-view").hidden = ui.view !== "robot";
  if (changed || !ui.stream) {
    if (changed) replaceChildren($("topic-select"), [el("option", { value: "", text: "choose a topic…" })]);
    showTopicChoice();
    restartStream();
    if (ui.view === "robot") openTopic(); else stopTopic();
  } else if (topicChanged && ui.view === "robot") {
    showTopicChoice();
    openTopic();
  }
  render();
}

function chooseTopic(topic) {
  ui.topic = topic;
  history.replaceState(null, "", robotHash(ui.robot, topic));   // the address names what is shown
  openTopic();
}

function start() {
  for (const form of document.querySelectorAll("form.rdapi-form")) form.addEventListener("submit", submitForm);
  $("add-node").addEventListener("click", () => addItemRow("node"));
  $("add-launcher").addEventListener("click", () => addItemRow("launcher"));
  $("robots-filter").addEventListener("input", renderRobots);
  $("topic-select").addEventListener("change", (e) => chooseTopic(e.target.value));
  if (window.ResizeObserver) new ResizeObserver(() => { if (!$("topic-canvas").hidden) drawPlot(); }).observe($("topic-canvas"));
  $("topic-form").addEventListener("submit", (e) => e.preventDefault());
  $("token-form").addEventListener("submit", (e) => {
    e.preventDefault();
    try { sessionStorage.setItem(TOKEN_KEY, $("token-input").value.trim()); } catch (err) { /* private mode */ }
    $("token-input").value = "";
    $("token-box").hidden = true;
    restartStream();
    if (ui.view === "robot") openTopic();
  });
  window.addEventListener("hashchange", route);
  // a page the browser keeps for "back" (its back/forward cache) would hold its streams open, and a browser
  // opens only six connections to one server: close them when the page is hidden, open them again on return
  window.addEventListener("pagehide", () => {
    stopTopic();
    if (ui.stream && ui.stream.abort) ui.stream.abort();
    ui.stream = null;
  });
  window.addEventListener("pageshow", (event) => {
    if (!event.persisted) return;
    restartStream();
    if (ui.view === "robot") openTopic();
  });
  route();
}

document.addEventListener("DOMContentLoaded", start);
