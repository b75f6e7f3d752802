// optitac-edge live view: polls /api/state, shows /api/frame.jpg with the fiber map and contacts drawn over it.
"use strict";

const SVG = "http://www.w3.org/2000/svg";
const token = new URLSearchParams(window.location.search).get("token") || "";
const $ = (id) => document.getElementById(id);
let layout = null;
let seq = 0;
const fiberNodes = new Map();

function el(name, attrs, parent) {
  const node = document.createElementNS(SVG, name);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, v);
  if (parent) parent.appendChild(node);
  return node;
}

function post(path) {
  return fetch(path, { method: "POST", headers: { "X-OptiTac": "1", "X-OptiTac-Token": token } });
}

function drawLayout() {
  const svg = $("overlay");
  svg.setAttribute("viewBox", `0 0 ${layout.width} ${layout.height}`);
  const fibers = el("g", { id: "fibers" }, svg);
  const ids = el("g", { id: "fiber-ids" }, svg);
  for (const f of layout.fibers) {
    if (f.dead) {
      const d = Math.max(f.r, 3);
      const g = el("g", { class: "dead", "data-fiber": f.id }, fibers);
      el("line", { x1: f.u - d, y1: f.v - d, x2: f.u + d, y2: f.v + d }, g);
      el("line", { x1: f.u - d, y1: f.v + d, x2: f.u + d, y2: f.v - d }, g);
      fiberNodes.set(f.id, g);
    } else {
      fiberNodes.set(f.id, el("circle", { class: "fiber", cx: f.u, cy: f.v, r: Math.max(f.r, 1.5), "data-fiber": f.id }, fibers));
    }
    const t = el("text", { class: "fid", x: f.u, y: f.v + 1.5, "text-anchor": "middle" }, ids);
    t.textContent = String(f.id);
  }
  for (const [u, v] of layout.unmatched) {
    const g = el("g", { class: "unmatched" }, svg);
    el("line", { x1: u - 4, y1: v, x2: u + 4, y2: v }, g);
    el("line", { x1: u, y1: v - 4, x2: u, y2: v + 4 }, g);
  }
  drawAxes(svg, layout.axes.origin, layout.axes.x, layout.axes.y, Math.max(8, layout.width / 60));
  el("g", { id: "contacts-layer" }, svg);
}

// the sensor's +x and +y from its centre (arrows), so that a press can be told from the picture
function drawAxes(svg, o, x, y, size) {
  const defs = el("defs", {}, svg);
  const m = el("marker", { id: "arrow", viewBox: "0 0 10 10", refX: "9", refY: "5", markerWidth: "5",
    markerHeight: "5", orient: "auto-start-reverse" }, defs);
  el("path", { d: "M 0 0 L 10 5 L 0 10 z", class: "axis-head" }, m);
  const mh = el("marker", { id: "arrowhead", viewBox: "0 0 10 10", refX: "9", refY: "5", markerWidth: "4",
    markerHeight: "4", orient: "auto" }, defs);  // a moving contact's arrow (drawContacts)
  el("path", { d: "M 0 0 L 10 5 L 0 10 z", class: "motion-head" }, mh);
  const g = el("g", { id: "axes", class: "axis" }, svg);
  for (const [end, name] of [[x, "+x"], [y, "+y"]]) {
    el("line", { x1: o[0], y1: o[1], x2: end[0], y2: end[1], "marker-end": "url(#arrow)" }, g);
    const dx = end[0] - o[0], dy = end[1] - o[1], n = Math.hypot(dx, dy) || 1;
    const t = el("text", { x: end[0] + (dx / n) * size, y: end[1] + (dy / n) * size + size / 3,
      "text-anchor": "middle", "font-size": size }, g);
    t.textContent = name;
  }
}

// OpenCV's inferno colour map (the snapshot's), by its anchors: the surface's colours and its scale
const INFERNO = [[0, 0, 4], [40, 11, 84], [101, 21, 110], [159, 42, 99], [212, 72, 66], [245, 125, 21],
  [250, 193, 39], [252, 255, 164]];
function inferno(v) { // v in 0..255
  const x = (Math.max(0, Math.min(255, v)) / 255) * (INFERNO.length - 1);
  const k = Math.min(Math.floor(x), INFERNO.length - 2), f = x - k;
  return INFERNO[k].map((a, i) => Math.round(a + f * (INFERNO[k + 1][i] - a)));
}

function bytes(b64) {
  const text = atob(b64);
  const out = new Uint8Array(text.length);
  for (let k = 0; k < text.length; k++) out[k] = text.charCodeAt(k);
  return out;
}

// the surface in mm (+y up) with its axes, ticks and a colour scale of its values
function drawSurface(s) {
  const canvas = $("surface");
  const ctx = canvas.getContext("2d");
  const n = s.n;
  const values = bytes(s.values);
  const img = ctx.createImageData(n, n);
  for (let row = 0; row < n; row++) {
    for (let col = 0; col < n; col++) {
      const [r, g, b] = inferno(values[row * n + col]);
      const o = ((n - 1 - row) * n + col) * 4; // +y up
      img.data[o] = r; img.data[o + 1] = g; img.data[o + 2] = b; img.data[o + 3] = 255;
    }
  }
  const tmp = document.createElement("canvas");
  tmp.width = n; tmp.height = n;
  tmp.getContext("2d").putImageData(img, 0, 0);
  const L = 34, T = 8, S = canvas.height - 40, bar = L + S + 14;
  ctx.fillStyle = "#15171a";
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  ctx.imageSmoothingEnabled = false;
  ctx.drawImage(tmp, L, T, S, S);
  const g = layout.grid, extent = (g.n - 1) * g.step_mm;
  const px = (x) => L + ((x - g.x0_mm) / extent) * S, py = (y) => T + (1 - (y - g.y0_mm) / extent) * S;
  const half = Math.floor(extent / 2 / 5) * 5 || extent / 2;
  ctx.fillStyle = "#9aa"; ctx.strokeStyle = "#9aa"; ctx.font = "10px sans-serif"; ctx.textAlign = "center";
  for (const v of [-half, 0, half]) {
    ctx.fillText(String(v), px(v), T + S + 14);
    ctx.textAlign = "right"; ctx.fillText(String(v), L - 6, py(v) + 3); ctx.textAlign = "center";
  }
  ctx.fillText("x mm", L + S - 14, T + S + 28);
  ctx.strokeStyle = "#50d2ff"; ctx.fillStyle = "#50d2ff"; ctx.lineWidth = 2;
  for (const [x, y, name] of [[0.3 * extent, 0, "+x"], [0, 0.3 * extent, "+y"]]) {
    ctx.beginPath(); ctx.moveTo(px(0), py(0)); ctx.lineTo(px(x), py(y)); ctx.stroke();
    ctx.fillText(name, px(x) + (x ? 10 : 0), py(y) - (y ? 6 : -4));
  }
  for (let k = 0; k < S; k++) { // the colour scale: max at the top, 0 at the bottom
    const [r, gg, b] = inferno(255 * (1 - k / (S - 1)));
    ctx.fillStyle = `rgb(${r},${gg},${b})`;
    ctx.fillRect(bar, T + k, 12, 1);
  }
  ctx.fillStyle = "#9aa"; ctx.textAlign = "left";
  ctx.fillText(s.max.toFixed(3), bar + 16, T + 8);
  ctx.fillText("0", bar + 16, T + S);
  ctx.fillText("darkening", bar - 8, T + S + 28);
  canvas.dataset.max = String(s.max);
}

// every fiber's gray level as a bar, on a 0..255 scale, with the dark and saturated levels to judge by
function drawLevels(levels, warn, s) {
  const canvas = $("levels");
  const ctx = canvas.getContext("2d");
  ctx.fillStyle = "#15171a";
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  const L = 34, T = 6, W = canvas.width - L - 80, H = canvas.height - 24;
  const y = (v) => T + (1 - v / 255) * H;
  ctx.fillStyle = "#9aa"; ctx.font = "10px sans-serif"; ctx.textAlign = "right";
  for (const v of [0, 128, 255]) ctx.fillText(String(v), L - 6, y(v) + 3);
  const w = W / levels.length;
  levels.forEach((v, k) => {
    const f = layout.fibers[k];
    ctx.fillStyle = f.dead ? "#eb3c3c" : warn.has(f.id) ? "#ff8c00" : "#50c850";
    ctx.fillRect(L + k * w, y(v), Math.max(w - 0.2, 0.5), y(0) - y(v));
  });
  ctx.textAlign = "left";
  for (const [v, colour, name] of [[s.saturated_level, "#eb3c3c", "saturated"], [s.dark_level, "#ff8c00", "dark"]]) {
    ctx.strokeStyle = colour; ctx.fillStyle = colour; ctx.lineWidth = 1;
    ctx.beginPath(); ctx.moveTo(L, y(v)); ctx.lineTo(L + W, y(v)); ctx.stroke();
    ctx.fillText(`${name} ${Math.round(v)}`, L + W + 6, y(v) + 3);
  }
  ctx.fillStyle = "#9aa";
  ctx.fillText(`fibers 1..${levels.length}`, L, T + H + 14);
  canvas.dataset.darkLevel = String(s.dark_level);
  canvas.dataset.saturatedLevel = String(s.saturated_level);
}

function drawContacts(contacts) {
  const layer = $("contacts-layer");
  while (layer.firstChild) layer.removeChild(layer.firstChild);
  const body = $("contacts").tBodies[0];
  body.textContent = "";
  contacts.forEach((c, k) => {
    el("polygon", { class: "contact", points: c.outline.map((p) => p.join(",")).join(" ") }, layer);
    el("circle", { class: "contact", cx: c.u, cy: c.v, r: 2 }, layer);
    if (c.arrow) {  // a moving contact: where it will be in a quarter of a second
      const [[u0, v0], [u1, v1]] = c.arrow;
      el("line", { class: c.sliding ? "arrow sliding" : "arrow", x1: u0, y1: v0, x2: u1, y2: v1,
        "marker-end": "url(#arrowhead)" }, layer);
    }
    const row = body.insertRow();
    const fmt = (v, d) => (v === null ? "–" : v.toFixed(d));
    const speed = c.vx_mm_s === null || c.vy_mm_s === null ? null : Math.hypot(c.vx_mm_s, c.vy_mm_s);
    for (const text of [String(k + 1), `${fmt(c.x_mm, 2)}, ${fmt(c.y_mm, 2)}`, `${fmt(c.major_mm, 2)} × ${fmt(c.minor_mm, 2)}`,
      `${fmt(c.angle_deg, 0)}°`, c.shape || "–", fmt(c.strength, 0), fmt(speed, 1) + (c.sliding ? " sliding" : "")]) {
      row.insertCell().textContent = text;
    }
  });
}

function show(s) {
  $("frame").src = `api/frame.jpg?seq=${s.seq}`;
  const vibration = s.vibration === null ? "–" : s.vibration.toFixed(1) + (s.vibrating ? " vibrating" : "");
  $("figures").textContent = `${s.fps.toFixed(1)} fps · frames ${s.frames} · dropped ${s.frames_dropped} · camera faults ${s.camera_errors} · light changes ${s.light_changes} · vibration ${vibration} · link ${s.link}` + (s.baseline_ready ? "" : " · taking the baseline");
  document.body.dataset.vibration = String(s.vibration);
  $("trunc").textContent = `max ${s.surface.max.toFixed(3)}, truncation level ${s.truncation}`;
  const warn = new Set([...s.dark, ...s.saturated]);
  for (const [id, node] of fiberNodes) {
    const want = warn.has(id) ? "fiber warn" : "fiber";
    if (node.tagName === "circle" && node.getAttribute("class") !== want) node.setAttribute("class", want);
  }
  $("warnings").textContent = `${s.dark.length} dark, ${s.saturated.length} saturated`;
  drawSurface(s.surface);
  drawLevels(bytes(s.levels), warn, s);
  drawContacts(s.contacts);
  $("prompt").textContent = s.orient.active ? s.orient.prompt : s.message;
  $("orient").textContent = s.orient.active ? "Cancel orientation" : "Orientation…";
  $("status").textContent = `update ${s.seq} · view updates skipped ${s.view_skipped} · frames with contact ${s.contact_frames}`;
  document.body.dataset.seq = String(s.seq);
  document.body.dataset.tns = String(s.t_ns);
  // when each update was shown (ms since the epoch), for tools/view_check.py; bounded
  const shown = (window.optitacShown = window.optitacShown || []);
  if (shown.length < 100000) shown.push([s.seq, s.t_ns, s.contacts.length, performance.timeOrigin + performance.now()]);
  document.body.dataset.contacts = String(s.contacts.length);
}

async function loop() {
  for (;;) {
    try {
      const r = await fetch(`api/state?after=${seq}`);
      if (r.ok) {
        const s = await r.json();
        if (s.seq && s.seq !== seq) { seq = s.seq; show(s); }
      } else {
        await new Promise((ok) => setTimeout(ok, 500));
      }
    } catch (e) {
      $("figures").textContent = "no connection to the view";
      await new Promise((ok) => setTimeout(ok, 1000));
    }
  }
}

async function start() {
  layout = await (await fetch("api/layout")).json();
  drawLayout();
  document.body.dataset.fibers = String(layout.fibers.length);
  $("ids").addEventListener("change", (e) => { $("fiber-ids").style.display = e.target.checked ? "" : "none"; });
  $("tare").addEventListener("click", () => post("api/tare"));
  $("orient").addEventListener("click", () => post(`api/orient?do=${$("orient").textContent.startsWith("Cancel") ? "cancel" : "start"}`));
  $("snapshot").addEventListener("click", async () => {
    const say = (text) => { // shown under the header for a few seconds
      const note = $("note");
      note.textContent = text;
      clearTimeout(note.timer);
      note.timer = setTimeout(() => { note.textContent = ""; }, 5000);
    };
    say("taking a snapshot…");
    let r;
    try {
      r = await post("api/snapshot");
    } catch (e) {
      say("snapshot failed: no connection to the view");
      return;
    }
    if (!r.ok) {
      say(`snapshot failed: ${(await r.text()).trim() || r.status}`);
      return;
    }
    const name = `optitac-snapshot-${seq}.png`;
    const a = document.createElement("a");
    a.href = URL.createObjectURL(await r.blob());
    a.download = name;
    a.click();
    say(`snapshot saved as ${name} (your browser's downloads)`);
  });
  loop();
}

start();
