// dyknow ui: the model of every manager, pushed by the server (server-sent events), drawn as a
// graph (units as ovals, keys as rectangles) and listed as text; actions go to the managers'
// services through POST /api/call. Everything from the network is shown with textContent.
"use strict";

const ANCHOR = "dyknow-request-anchor";
let model = { version: 0, managers: [] };
let cy = null;
const positions = new Map(); // node id -> position, so the layout stays put
let selected = null; // {manager, unit}
let userMoved = false; // once the user pans or zooms, the view is theirs

const $ = (id) => document.getElementById(id);
const el = (tag, text, attrs) => {
  const node = document.createElement(tag);
  if (text !== undefined && text !== null) node.textContent = String(text);
  for (const [k, v] of Object.entries(attrs || {})) node.setAttribute(k, v);
  return node;
};

function say(text, ok) {
  const box = $("message");
  box.textContent = text || "";
  box.className = ok ? "ok" : "";
}

async function call(manager, service, request, unit) {
  const body = { manager, service, request: request || {} };
  if (unit) body.unit = unit;
  const response = await fetch("/api/call", { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body) });
  const data = await response.json();
  if (!response.ok) throw new Error(data.message || data.error || response.statusText);
  return data.reply;
}

// ---------------------------------------------------------------- the model as ports and keys

function specOf(manager, label) {
  return (manager.specs || []).find((s) => s.label === label);
}

function directions(manager, unit) {
  // port -> "in" | "out", from the unit's spec (the request anchor is built in: in -> out)
  const spec = specOf(manager, unit.label);
  const out = {};
  for (const port of Object.keys(unit.bindings)) {
    const declared = spec ? spec.ports.find((p) => p.name === port) : null;
    out[port] = declared ? declared.direction : (port === "in" ? "in" : "out");
  }
  return out;
}

function unitState(manager, unit) {
  return unit.state;
}

function companionName(unit, port) {
  // the unit that wires a port bound to a ROS 2 topic (see dyknow/manager/ros2.py)
  return `${unit.name}.${port}.ros2`;
}

function isRos2(key) {
  // a binding to a ROS 2 topic: rmw_zenoh (ros2:) or DDS (ros2dds:)
  return key.startsWith("ros2:") || key.startsWith("ros2dds:");
}

function globToRegex(glob) {
  const escaped = glob.trim().replace(/[.+^${}()|[\]\\]/g, "\\$&").replace(/\*\*/g, "\u0000").replace(/\*/g, "[^/]*").replace(/\u0000/g, ".*");
  return new RegExp("^" + escaped + "$");
}

// ---------------------------------------------------------------- graph

function elements() {
  const filter = $("filter").value.trim().toLowerCase();
  const hide = $("hide").value.split(",").map((p) => p.trim()).filter(Boolean).map(globToRegex);
  const group = $("group").checked;
  const prefix = $("prefix").checked;
  const nodes = [];
  const edges = [];
  const keys = new Map();
  const requestKeys = new Set();
  for (const m of model.managers) for (const r of m.requests || []) requestKeys.add(r.key);
  for (const m of model.managers) {
    if (group) nodes.push({ data: { id: "manager:" + m.manager, label: m.manager }, classes: "manager" });
    // a port bound to a ROS 2 topic is wired through a companion unit <unit>.<port>.ros2 on an
    // internal key: drawn as topic -> companion -> unit (or back), the internal key left out
    const byName = new Map(m.units.map((u) => [u.name, u]));
    const companions = new Set();
    for (const u of m.units) for (const [port, key] of Object.entries(u.bindings)) if (isRos2(key) && byName.has(companionName(u, port))) companions.add(companionName(u, port));
    for (const u of m.units) {
      if (companions.has(u.name)) continue; // drawn beside the unit it serves
      const text = (u.name + " " + u.label + " " + Object.values(u.bindings).join(" ")).toLowerCase();
      if (filter && !text.includes(filter)) continue;
      const id = "unit:" + m.manager + "/" + u.name;
      const classes = ["unit", "state-" + u.state];
      if (u.protected) classes.push("protected");
      if (u.label === ANCHOR) classes.push("anchor");
      nodes.push({ data: { id, label: u.name + "\n" + u.label, parent: group ? "manager:" + m.manager : undefined, manager: m.manager, unit: u.name }, classes: classes.join(" ") });
      const dirs = directions(m, u);
      for (const [port, key] of Object.entries(u.bindings)) {
        if (hide.some((re) => re.test(key))) continue;
        const kid = "key:" + key;
        if (!keys.has(kid)) keys.set(kid, key);
        const live = ((model.stats || {})[m.manager + "/" + u.name] || {})[port] || {};
        let label = port;
        if (live.rate !== null && live.rate !== undefined) label += ` ${live.rate}/s`;
        if (dirs[port] !== "out" && live.hop_p50_us) label += ` ${(live.hop_p50_us / 1000).toFixed(2)} ms`;
        // what went missing, and why: lost on the way (gaps in the sender's numbers), dropped by the full queue
        if (live.lost) label += ` ${live.lost} lost`;
        if (live.unknown_clock) label += ` ${live.unknown_clock} clock unknown`; // their times left out of the figures
        if (live.dropped) label += ` ${live.dropped} dropped`;
        const companion = isRos2(key) ? byName.get(companionName(u, port)) : undefined;
        if (companion) {
          const cid = "unit:" + m.manager + "/" + companion.name;
          nodes.push({ data: { id: cid, label: companion.name + "\n" + companion.label, parent: group ? "manager:" + m.manager : undefined, manager: m.manager, unit: companion.name }, classes: "unit companion state-" + companion.state });
          if (dirs[port] === "out") {
            edges.push({ data: { id: id + "->" + cid, source: id, target: cid, label } });
            edges.push({ data: { id: cid + "->" + key, source: cid, target: kid, label: "ROS 2" } });
          } else {
            edges.push({ data: { id: key + "->" + cid, source: kid, target: cid, label: "ROS 2" } });
            edges.push({ data: { id: cid + "->" + id + "." + port, source: cid, target: id, label } });
          }
        } else if (dirs[port] === "out") edges.push({ data: { id: id + "->" + key, source: id, target: kid, label } });
        else edges.push({ data: { id: key + "->" + id + "." + port, source: kid, target: id, label } });
      }
    }
  }
  for (const [kid, key] of keys) {
    const parts = key.split("/");
    let parent;
    if (prefix && parts.length > 2) {
      parent = "prefix:" + parts.slice(0, 2).join("/");
      if (!nodes.some((n) => n.data.id === parent)) nodes.push({ data: { id: parent, label: parts.slice(0, 2).join("/") + "/" }, classes: "prefix" });
    }
    nodes.push({ data: { id: kid, label: key, parent, width: 12 + 6 * key.length }, classes: "key" + (requestKeys.has(key) ? " request" : "") + (isRos2(key) ? " ros2" : "") });
  }
  return { nodes, edges };
}

function drawGraph() {
  const { nodes, edges } = elements();
  if (!cy) {
    cy = cytoscape({
      container: $("graph"),
      style: [
        { selector: "node", style: { label: "data(label)", "text-wrap": "wrap", "font-size": 10, "text-valign": "center", "text-halign": "center" } },
        { selector: ".unit", style: { shape: "ellipse", width: 120, height: 44, "background-color": "#cfe8d5", "border-width": 1, "border-color": "#1a7f37" } },
        { selector: ".companion", style: { width: 96, height: 32, "font-size": 8, "background-color": "#e6f4ff", "border-color": "#0958d9" } },
        { selector: ".state-failed", style: { "background-color": "#f8c9c4", "border-color": "#c62828", "border-width": 3 } },
        { selector: ".state-stalled", style: { "background-color": "#ffe2b3", "border-color": "#b26a00", "border-width": 3 } },
        { selector: ".protected", style: { "border-style": "double", "border-width": 4 } },
        { selector: ".anchor", style: { "background-color": "#d6e4ff", "border-color": "#2f54eb" } },
        { selector: ".key", style: { shape: "round-rectangle", width: "data(width)", height: 22, padding: 6, "background-color": "#f4f4f8", "border-width": 1, "border-color": "#889", "font-family": "monospace", "font-size": 9 } },
        { selector: ".key.ros2", style: { "background-color": "#eef7ff", "border-color": "#0958d9" } },
        { selector: ".request", style: { "border-color": "#2f54eb", "border-width": 3, "background-color": "#e8efff" } },
        { selector: ".manager, .prefix", style: { "text-valign": "top", "background-opacity": 0.05, "border-style": "dashed", "font-weight": "bold" } },
        { selector: "edge", style: { width: 1.5, "curve-style": "bezier", "target-arrow-shape": "triangle", label: "data(label)", "font-size": 8, "text-rotation": "autorotate", "line-color": "#99a", "target-arrow-color": "#99a" } },
      ],
    });
    cy.on("tap", "node.unit", (event) => showUnit(event.target.data("manager"), event.target.data("unit")));
    cy.on("dragfree", "node", (event) => positions.set(event.target.id(), { ...event.target.position() }));
    for (const kind of ["wheel", "mousedown", "touchstart"]) $("graph").addEventListener(kind, () => { userMoved = true; }, { passive: true });
  }
  const wanted = new Set([...nodes, ...edges].map((e) => e.data.id));
  cy.batch(() => {
    cy.elements().filter((e) => !wanted.has(e.id())).remove();
    for (const n of nodes) {
      const existing = cy.getElementById(n.data.id);
      if (existing.nonempty()) {
        existing.classes(n.classes);
        existing.data("label", n.data.label);
        if (existing.data("parent") !== n.data.parent) existing.move({ parent: n.data.parent ?? null });
      } else {
        cy.add({ group: "nodes", data: n.data, classes: n.classes, position: positions.get(n.data.id) });
      }
    }
    for (const e of edges) {
      const existing = cy.getElementById(e.data.id);
      if (existing.empty()) cy.add({ group: "edges", data: e.data });
      else existing.data("label", e.data.label);
    }
  });
  const fresh = cy.nodes().filter((n) => !n.isParent() && !positions.has(n.id()));
  if (fresh.nonempty()) {
    const placed = cy.nodes().filter((n) => !n.isParent() && positions.has(n.id()));
    if (placed.empty()) {
      layoutLeftToRight(cy.elements(), 0, 0);
    } else if (fresh.length <= 2) {
      // one or two new nodes: beside a placed neighbour, or below everything; nothing else moves
      const box = placed.boundingBox();
      fresh.forEach((n, i) => {
        const near = n.neighborhood("node").filter((m) => positions.has(m.id()));
        const at = near.nonempty() ? near[0].position() : { x: box.x1, y: box.y2 + 60 };
        n.position({ x: at.x + 170, y: at.y + 50 * (i + 1) });
      });
    } else {
      // a new configuration: laid out on its own, right of what is there
      const box = placed.boundingBox();
      layoutLeftToRight(fresh.union(fresh.edgesWith(fresh)), box.x1, box.y2 + 80);
    }
    cy.nodes().forEach((n) => { if (!n.isParent()) positions.set(n.id(), { ...n.position() }); });
    if (!userMoved) cy.fit(undefined, 30);
  }
}

function layoutLeftToRight(eles, x0, y0) {
  // a layered layout with data flowing left to right (breadthfirst is top-down: turn it)
  eles.layout({ name: "breadthfirst", directed: true, animate: false, fit: false, spacingFactor: 1.0 }).run();
  const nodes = eles.nodes().filter((n) => !n.isParent());
  if (nodes.empty()) return;
  // its levels become columns 190 px apart, its order within a level rows 70 px apart
  const levels = [...new Set(nodes.map((n) => Math.round(n.position().y)))].sort((a, b) => a - b);
  const rows = [...new Set(nodes.map((n) => Math.round(n.position().x)))].sort((a, b) => a - b);
  nodes.forEach((n) => {
    const p = n.position();
    n.position({ x: x0 + 190 * levels.indexOf(Math.round(p.y)), y: y0 + 70 * rows.indexOf(Math.round(p.x)) });
  });
}

// ---------------------------------------------------------------- panels as text

function drawActive() {
  const body = $("units").querySelector("tbody");
  body.replaceChildren();
  for (const m of model.managers) {
    const dirsOf = (u) => directions(m, u);
    for (const u of m.units) {
      const row = el("tr", undefined, { "data-unit": u.name, "data-manager": m.manager });
      const name = el("td");
      const link = el("a", u.name, { href: "#" });
      link.addEventListener("click", (event) => { event.preventDefault(); showUnit(m.manager, u.name); });
      name.append(link);
      row.append(name, el("td", u.label), el("td", m.manager), el("td", u.state + (u.protected ? " (protected)" : ""), { class: "state-" + u.state }));
      const keys = el("td", undefined, { class: "keys" });
      const dirs = dirsOf(u);
      const live = (model.stats || {})[m.manager + "/" + u.name] || {};
      for (const [port, key] of Object.entries(u.bindings)) {
        const rate = live[port] && live[port].rate !== null && live[port].rate !== undefined ? `  (${live[port].rate}/s)` : "";
        const unknown = live[port] && live[port].unknown_clock ? `  ${live[port].unknown_clock} of a clock not known` : "";
        keys.append(el("div", (dirs[port] === "in" ? "in  " : "out ") + port + " \u2192 " + key + rate + unknown));
      }
      if (u.error) keys.append(el("div", "error: " + u.error, { class: "state-failed" }));
      row.append(keys);
      const actions = el("td");
      if (!u.protected) {
        const destroy = el("button", "destroy", { "data-action": "destroy" });
        destroy.addEventListener("click", () => act(() => call(m.manager, "destroy", { name: u.name }), `destroyed ${u.name}`));
        actions.append(destroy);
      }
      row.append(actions);
      body.append(row);
    }
  }
  if (!body.children.length) {
    const row = el("tr");
    row.append(el("td", "no unit runs", { colspan: 6, class: "muted" }));
    body.append(row);
  }
}

// each manager's estimate of the other managers' clocks: offset (theirs minus its) and uncertainty
function drawClocks() {
  const items = [];
  for (const m of model.managers) {
    for (const [peer, c] of Object.entries(m.clocks || {})) {
      if (peer === "clock" || typeof c !== "object") continue;
      items.push(el("li", `${m.manager} \u2192 ${peer}: ${c.offset_us >= 0 ? "+" : ""}${c.offset_us} \u00b5s \u00b1 ${c.uncertainty_us} \u00b5s` +
        (c.drift_ppm ? `, drift ${c.drift_ppm} ppm` : ""), { "data-manager": m.manager, "data-peer": peer }));
    }
  }
  if (!items.length) items.push(el("li", "no other manager's clock estimated", { class: "muted" }));
  $("clocks").replaceChildren(...items);
}

// managers lost and not back (as some manager knew them, or as this page's tool saw them
// leave: it watches every manager, a manager only those it follows): the latest loss of each, with its cause
function lostManagers() {
  const up = new Set(model.managers.map((m) => m.manager));
  const lost = new Map();
  const seen = [...(model.lost || []).map((l) => [l, "this page"]), ...model.managers.flatMap((m) => (m.lost || []).map((l) => [l, m.manager]))];
  for (const [l, by] of seen) {
    if (up.has(l.manager) || typeof l.since_ns !== "number") continue;
    const known = lost.get(l.manager);
    if (!known || known.since_ns < l.since_ns) lost.set(l.manager, { ...l, by });
  }
  return [...lost.values()].sort((a, b) => a.manager.localeCompare(b.manager));
}

function drawLost() {
  const now = Date.now();
  const items = lostManagers().map((l) => el("li",
    `${l.manager}: lost ${Math.max(0, Math.round((now - l.since_ns / 1e6) / 1000))} s ago (${new Date(l.since_ns / 1e6).toLocaleTimeString()}, as ${l.by} saw it): ${l.why}`,
    { "data-manager": l.manager, class: "lost" }));
  if (!items.length) items.push(el("li", "no manager lost", { class: "muted" }));
  $("lost").replaceChildren(...items);
}

// each system in a mode (a spec's <system>): its mode, since when, and why it was chosen
function drawModes() {
  const items = model.managers.flatMap((m) => (m.modes || []).map((mode) => el("li",
    `${mode.system}: ${mode.mode} since ${new Date(mode.since_ns / 1e6).toLocaleTimeString()} (manager ${m.manager}, unit ${mode.unit}): ${mode.why}`,
    { "data-system": mode.system, "data-mode": mode.mode, class: "mode" })));
  if (!items.length) items.push(el("li", "no system in a mode", { class: "muted" }));
  $("modes").replaceChildren(...items);
}

function fillManagers() {
  for (const select of document.querySelectorAll("select.managers")) {
    const current = select.value;
    select.replaceChildren(...model.managers.map((m) => el("option", m.manager, { value: m.manager })));
    if (model.managers.some((m) => m.manager === current)) select.value = current;
  }
}

function managerNamed(name) {
  return model.managers.find((m) => m.manager === name);
}

function drawLibrary() {
  const m = managerNamed($("lib-manager").value);
  const list = $("specs");
  list.replaceChildren();
  for (const s of m ? m.specs : []) {
    const item = el("li", undefined, { "data-label": s.label });
    item.append(el("strong", s.label), el("span", " ports: " + s.ports.map((p) => p.direction + " " + p.name).join(", ")));
    if (s.tags.length) item.append(el("div", "tags: " + s.tags.map((t) => t.port + " " + t.tag).join(", ")));
    const params = Object.entries(s.params || {});
    if (params.length) item.append(el("div", "params: " + params.map(([k, v]) => k + "=" + v).join(", ")));
    item.append(el("div", "priority " + s.priority + (s.constraints.length ? "; constraints: " + s.constraints.map((c) => c.measure + " " + c.op + " " + c.value).join(", ") : ""), { class: "muted" }));
    const remove = el("button", "delete");
    remove.addEventListener("click", () => act(() => call(m.manager, "remove_transformation", { label: s.label }), `deleted ${s.label}`));
    item.append(remove);
    list.append(item);
  }
}

function drawCreate() {
  const m = managerNamed($("create-manager").value);
  const select = $("create-label");
  const current = select.value;
  select.replaceChildren(...(m ? m.specs : []).map((s) => el("option", s.label, { value: s.label })));
  if (m && m.specs.some((s) => s.label === current)) select.value = current;
  drawParams();
}

function drawParams() {
  const m = managerNamed($("create-manager").value);
  const spec = m && specOf(m, $("create-label").value);
  const box = $("create-params");
  if (box.dataset.label === (spec ? m.manager + "/" + spec.label : "")) return;
  box.dataset.label = spec ? m.manager + "/" + spec.label : "";
  box.replaceChildren(el("legend", "Params"));
  for (const [name, value] of Object.entries(spec ? spec.params : {})) {
    const type = (spec.param_types || {})[name] || typeof value;
    const label = el("label", `${name} (${type}) `);
    label.append(el("input", undefined, { "data-param": name, value: value === null ? "" : String(value), "data-type": type }));
    box.append(label);
  }
}

function drawConnect() {
  const outs = [];
  const ins = [];
  for (const m of model.managers) for (const u of m.units) {
    const dirs = directions(m, u);
    for (const [port, key] of Object.entries(u.bindings)) {
      const option = { value: JSON.stringify({ manager: m.manager, unit: u.name, port, key }), text: `${m.manager}/${u.name}.${port} (${key})` };
      (dirs[port] === "out" ? outs : ins).push(option);
    }
  }
  for (const [id, options, blank] of [["connect-from", outs, "a key typed below"], ["connect-to", ins, null]]) {
    const select = $(id);
    const current = select.value;
    select.replaceChildren(...(blank ? [el("option", blank, { value: "" })] : []), ...options.map((o) => el("option", o.text, { value: o.value })));
    if ([...select.options].some((o) => o.value === current)) select.value = current;
  }
}

async function drawRequests() {
  const list = $("requests");
  list.replaceChildren();
  for (const m of model.managers) for (const r of m.requests || []) {
    const item = el("li", `${r.tag} on ${r.key} (${m.manager}): ${r.state}; ${r.labels.join(", ")}`, { "data-key": r.key });
    const release = el("button", "release");
    release.addEventListener("click", () => act(() => call(m.manager, "release", { key: r.key }), `released ${r.key}`));
    item.append(" ", release);
    list.append(item);
  }
  const events = [];
  for (const m of model.managers) {
    try {
      for (const e of await call(m.manager, "get_adaptations", {})) events.push([m.manager, e]);
    } catch (error) { /* a manager that went away */ }
  }
  $("adaptations").replaceChildren(...events.map(([manager, e]) => el("li", `${manager}: #${e.id} ${e.kind} ${e.request}: ${e.cause}; adapted in ${e.adaptation_ms} ms, recovered in ${e.recovery_ms ?? "?"} ms`)));
}

async function showUnit(manager, unit) {
  selected = { manager, unit };
  openTab("unit");
  $("unit-title").textContent = `Unit ${unit} on ${manager}`;
  const box = $("unit-detail");
  const m = managerNamed(manager);
  const info = m && m.units.find((u) => u.name === unit);
  box.replaceChildren();
  if (!info) { box.append(el("p", "no such unit any more")); return; }
  box.append(el("p", `${info.label}: ${info.state}${info.protected ? " (protected)" : ""}`));
  const table = el("table");
  for (const [port, key] of Object.entries(info.bindings)) {
    const row = el("tr");
    row.append(el("td", port), el("td", key, { class: "keys" }));
    table.append(row);
  }
  box.append(el("h3", "Bindings"), table);
  if (info.traceback) box.append(el("h3", "Traceback"), el("pre", info.traceback, { class: "errors" }));
  try {
    const stats = await call(manager, "get_statistics", {}, unit);
    box.append(el("h3", "Statistics"), el("pre", JSON.stringify(stats, null, 2)));
  } catch (error) {
    box.append(el("p", "no statistics: " + error.message, { class: "errors" }));
  }
}

// ---------------------------------------------------------------- views of the data

let viewSocket = null;
const series = new Map(); // field -> [[t, value], ...]
const COLOURS = ["#2f54eb", "#c62828", "#1a7f37", "#b26a00", "#6a1b9a", "#00838f"];

function watch(key) {
  if (viewSocket) viewSocket.close();
  series.clear();
  const stats = $("view-stats");
  const image = $("view-image");
  const plot = $("view-plot");
  let frames = 0;
  let since = performance.now();
  let last = null;
  const socket = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/api/stream?key=${encodeURIComponent(key)}`);
  socket.binaryType = "blob";
  viewSocket = socket;
  socket.onmessage = (event) => {
    if (typeof event.data !== "string") {
      const url = URL.createObjectURL(event.data);
      image.onload = () => URL.revokeObjectURL(url);
      image.src = url;
      image.hidden = false;
      return;
    }
    last = JSON.parse(event.data);
    frames += 1;
    if (last.kind === "json") addPoints(last.payload);
    else if (last.kind === "other") stats.dataset.description = last.description;
    const now = performance.now();
    if (now - since >= 1000) {
      const rate = (frames * 1000) / (now - since);
      frames = 0;
      since = now;
      stats.textContent = `${key}: ${rate.toFixed(1)} messages/s, latency ${last.latency_ms.toFixed(1)} ms, #${last.seq}` +
        (last.kind === "image" ? `, ${last.width}x${last.height}` : "") + (last.dropped ? `, ${last.dropped} skipped while busy` : "") +
        (last.kind === "other" ? `: ${last.description}` : "");
      stats.dataset.rate = rate.toFixed(2);
    }
    if (last.kind === "json") drawPlot(plot);
  };
  socket.onopen = () => { stats.textContent = `${key}: waiting for messages`; };
  socket.onclose = () => { if (viewSocket === socket) stats.textContent = "stopped"; };
}

function addPoints(payload) {
  const t = performance.now() / 1000;
  for (const [field, value] of Object.entries(payload)) {
    if (typeof value !== "number" || !Number.isFinite(value)) continue;
    if (!series.has(field) && series.size >= COLOURS.length) continue;
    const points = series.get(field) || [];
    points.push([t, value]);
    if (points.length > 300) points.shift();
    series.set(field, points);
  }
}

function drawPlot(canvas) {
  canvas.hidden = series.size === 0;
  const g = canvas.getContext("2d");
  g.clearRect(0, 0, canvas.width, canvas.height);
  let fields = [...series.keys()];
  $("view-legend").replaceChildren(...fields.map((f, i) => el("span", `■ ${f}  `, { style: `color:${COLOURS[i]}` })));
  for (const [i, field] of fields.entries()) {
    const points = series.get(field);
    if (points.length < 2) continue;
    const t0 = points[0][0], t1 = points[points.length - 1][0];
    const values = points.map((p) => p[1]);
    const lo = Math.min(...values), hi = Math.max(...values);
    g.strokeStyle = COLOURS[i];
    g.beginPath();
    points.forEach(([t, v], j) => {
      const x = ((t - t0) / Math.max(1e-9, t1 - t0)) * (canvas.width - 10) + 5;
      const y = canvas.height - 5 - ((v - lo) / Math.max(1e-9, hi - lo)) * (canvas.height - 10);
      if (j === 0) g.moveTo(x, y); else g.lineTo(x, y);
    });
    g.stroke();
  }
}

// ---------------------------------------------------------------- actions

async function act(action, done) {
  try {
    const result = await action();
    say(typeof done === "function" ? done(result) : done, true);
  } catch (error) {
    say(error.message);
  }
}

function openTab(name) {
  for (const button of document.querySelectorAll("nav button")) button.setAttribute("aria-selected", String(button.dataset.tab === name));
  for (const panel of document.querySelectorAll("[role=tabpanel]")) panel.hidden = panel.id !== "tab-" + name;
  if (name === "requests") drawRequests();
}

function wire() {
  for (const button of document.querySelectorAll("nav button")) button.addEventListener("click", () => openTab(button.dataset.tab));
  for (const id of ["filter", "hide", "group", "prefix"]) $(id).addEventListener("input", drawGraph);
  $("lib-manager").addEventListener("change", drawLibrary);
  $("create-manager").addEventListener("change", drawCreate);
  $("create-label").addEventListener("change", drawParams);
  $("lib-file").addEventListener("change", async () => { const f = $("lib-file").files[0]; if (f) $("lib-xml").value = await f.text(); });
  $("lib-import").addEventListener("click", async () => {
    $("lib-errors").textContent = "";
    const name = $("lib-file").files[0] ? $("lib-file").files[0].name : "pasted.xml";
    try {
      const reply = await call($("lib-manager").value, "add_transformation", { xml: $("lib-xml").value, path: name });
      say("imported " + reply.labels.join(", "), true);
    } catch (error) {
      $("lib-errors").textContent = error.message;
    }
  });
  $("create-form").addEventListener("submit", (event) => {
    event.preventDefault();
    const params = {};
    for (const input of $("create-params").querySelectorAll("input")) {
      const type = input.dataset.type;
      params[input.dataset.param] = ["int", "float", "number"].includes(type) ? Number(input.value) : ["bool", "boolean"].includes(type) ? input.value === "true" : input.value;
    }
    const name = $("create-name").value;
    act(() => call($("create-manager").value, "spawn", { label: $("create-label").value, name, params, protected: $("create-protected").checked }), `created ${name}`);
  });
  $("connect-form").addEventListener("submit", (event) => {
    event.preventDefault();
    const target = $("connect-to").value && JSON.parse($("connect-to").value);
    const source = $("connect-from").value && JSON.parse($("connect-from").value);
    const key = source ? source.key : $("connect-key").value.trim();
    if (!target || !key) { say("pick an input port, and an output port or a key"); return; }
    act(() => call(target.manager, "set_config", { bindings: { [target.port]: key } }, target.unit), `${target.unit}.${target.port} now reads ${key}`);
  });
  $("view-form").addEventListener("submit", (event) => { event.preventDefault(); watch($("view-key").value.trim()); });
  $("view-stop").addEventListener("click", () => { if (viewSocket) viewSocket.close(); viewSocket = null; });
  $("request-form").addEventListener("submit", (event) => {
    event.preventDefault();
    act(() => call($("request-manager").value, "request", { tag: $("request-tag").value }), (reply) => "requested: key " + reply.key).then(drawRequests);
  });
  $("measure-form").addEventListener("submit", (event) => {
    event.preventDefault();
    const raw = $("measure-value").value.trim();
    const value = raw !== "" && !Number.isNaN(Number(raw)) ? Number(raw) : raw;
    act(() => call($("request-manager").value, "measure", { name: $("measure-name").value, value }), "measured");
  });
}

function verdictName(verdict) {
  return verdict === true ? "true" : verdict === false ? "false" : "unknown";
}

function verdictRow(name, verdicts, changes, recorded, error) {
  // a strip of its verdicts (green true, red false, grey unknown, a bar where a gap was), then
  // its changes, each with the values that decided it
  const row = el("div", undefined, { class: "verdict-row" + (recorded ? " recorded" : "") });
  const strip = el("span", undefined, { class: "strip" });
  for (const [t, verdict, gap] of verdicts) {
    const cls = verdict === true ? "holds" : verdict === false ? "violated" : "unknown";
    strip.append(el("i", undefined, { class: cls + (gap ? " gap" : ""), title: `t=${Number(t).toFixed(3)} s: ${verdictName(verdict)}${gap ? " (after a gap: " + gap + ")" : ""}` }));
  }
  const falses = verdicts.filter((v) => v[1] === false).length;
  const head = el("div", undefined, { class: "verdict-head" });
  head.append(el("code", name), strip, el("span", error ? ` not checked: ${error}` : ` ${verdicts.length} ${recorded ? "cells" : "verdicts"}, ${falses} false`));
  row.append(head);
  if (changes && changes.length) {
    const details = el("details", undefined, { class: "changes" });
    details.append(el("summary", `${changes.length} change${changes.length === 1 ? "" : "s"}`));
    const list = el("ol");
    for (const [t, verdict, why] of changes.slice(-20)) {
      const item = el("li", `t=${Number(t).toFixed(3)} s: ${verdictName(verdict)}`, { class: "change " + verdictName(verdict) });
      if (why && why.length) {
        const atoms = el("ul");
        for (const atom of why) atoms.append(el("li", atom));
        item.append(atoms);
      }
      list.append(item);
    }
    details.append(list);
    if (openChanges.has(name)) details.open = true;
    details.addEventListener("toggle", () => { if (details.open) openChanges.add(name); else openChanges.delete(name); });
    row.append(details);
  }
  return row;
}

const openChanges = new Set(); // rows whose changes the user opened: kept open across redraws

function drawVerdicts() {
  // a row per monitor, requirement and foreach object (live), and per requirement and instance
  // checked over a recording (dyknow ui --requirements F --mcap M)
  const rows = [];
  const changes = model.changes || {};
  for (const [key, verdicts] of Object.entries(model.verdicts || {}).sort()) rows.push(verdictRow(key, verdicts, changes[key], false));
  const recorded = Object.entries(model.recorded || {});
  if (recorded.length) rows.push(el("h4", "Checked over the recording"));
  for (const [name, row] of recorded) rows.push(verdictRow(name, row.verdicts, row.changes, true, row.error));
  $("verdicts").replaceChildren(...(rows.length ? rows : [el("p", "no monitor or requirement")]));
}

function render() {
  fillManagers();
  drawVerdicts();
  drawGraph();
  drawActive();
  drawClocks();
  drawLost();
  drawModes();
  drawLibrary();
  drawCreate();
  drawConnect();
  if (!$("tab-requests").hidden) drawRequests();
  const keys = new Set();
  for (const m of model.managers) for (const u of m.units) for (const k of Object.values(u.bindings)) keys.add(k);
  $("known-keys").replaceChildren(...[...keys].sort().map((k) => el("option", undefined, { value: k })));
  const units = model.managers.reduce((n, m) => n + m.units.length, 0);
  const lost = lostManagers();
  $("status").textContent = `${model.managers.length} managers, ${units} units (model ${model.version})` +
    (lost.length ? `; lost: ${lost.map((l) => l.manager).join(", ")}` : "");
  document.body.dataset.version = String(model.version);
  if (units && window.dyknowFirstDraw === undefined) window.dyknowFirstDraw = performance.now(); // for benchmarks/ui.py
}

function listen() {
  const source = new EventSource("/api/events");
  source.onmessage = (event) => { model = JSON.parse(event.data); render(); };
  source.onerror = () => { $("status").textContent = "reconnecting…"; };
}

wire();
listen();
