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
  el("g", { id: "contacts-layer" }, svg);
}

function bytes(b64) {
  const text = atob(b64);
  const out = new Uint8Array(text.length);
  for (let k = 0; k < text.length; k++) out[k] = text.charCodeAt(k);
  return out;
}

function drawSurface(s) {
  const canvas = $("surface");
  const ctx = canvas.getContext("2d");
  const n = s.n;
  const values = bytes(s.values);
  const img = ctx.createImageData(n, n);
  for (let row = 0; row < n; row++) {
    for (let col = 0; col < n; col++) {
      const v = values[row * n + col];
      const o = ((n - 1 - row) * n + col) * 4; // +y up
      img.data[o] = Math.min(255, v * 2);
      img.data[o + 1] = Math.max(0, v * 2 - 255) + v / 4;
      img.data[o + 2] = v > 0 ? 80 : 30;
      img.data[o + 3] = 255;
    }
  }
  const tmp = document.createElement("canvas");
  tmp.width = n; tmp.height = n;
  tmp.getContext("2d").putImageData(img, 0, 0);
  ctx.imageSmoothingEnabled = false;
  ctx.drawImage(tmp, 0, 0, canvas.width, canvas.height);
}

function drawLevels(levels, warn) {
  const canvas = $("levels");
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  const w = canvas.width / levels.length;
  levels.forEach((v, k) => {
    ctx.fillStyle = warn.has(layout.fibers[k].id) ? "#ff8c00" : "#50c850";
    const h = (v / 255) * canvas.height;
    ctx.fillRect(k * w, canvas.height - h, Math.max(w - 0.2, 0.5), h);
  });
}

function drawContacts(contacts) {
  const layer = $("contacts-layer");
  while (layer.firstChild) layer.removeChild(layer.firstChild);
  const body = $("contacts").tBodies[0];
  body.textContent = "";
  contacts.forEach((c, k) => {
    el("polygon", { class: "contact", points: c.outline.map((p) => p.join(",")).join(" ") }, layer);
    el("circle", { class: "contact", cx: c.u, cy: c.v, r: 2 }, layer);
    const row = body.insertRow();
    const fmt = (v, d) => (v === null ? "–" : v.toFixed(d));
    for (const text of [String(k + 1), `${fmt(c.x_mm, 2)}, ${fmt(c.y_mm, 2)}`, `${fmt(c.major_mm, 2)} × ${fmt(c.minor_mm, 2)}`,
      `${fmt(c.angle_deg, 0)}°`, c.shape || "–", fmt(c.strength, 0)]) {
      row.insertCell().textContent = text;
    }
  });
}

function show(s) {
  $("frame").src = `api/frame.jpg?seq=${s.seq}`;
  $("figures").textContent = `${s.fps.toFixed(1)} fps · frames ${s.frames} · dropped ${s.frames_dropped} · camera faults ${s.camera_errors} · light changes ${s.light_changes} · link ${s.link}` + (s.baseline_ready ? "" : " · taking the baseline");
  $("trunc").textContent = `max ${s.surface.max.toFixed(3)}, truncation level ${s.truncation}`;
  const warn = new Set([...s.dark, ...s.saturated]);
  for (const [id, node] of fiberNodes) {
    const want = warn.has(id) ? "fiber warn" : "fiber";
    if (node.tagName === "circle" && node.getAttribute("class") !== want) node.setAttribute("class", want);
  }
  $("warnings").textContent = `${s.dark.length} dark, ${s.saturated.length} saturated`;
  drawSurface(s.surface);
  drawLevels(bytes(s.levels), warn);
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
    const r = await post("api/snapshot");
    if (!r.ok) return;
    const a = document.createElement("a");
    a.href = URL.createObjectURL(await r.blob());
    a.download = `optitac-snapshot-${seq}.png`;
    a.click();
  });
  loop();
}

start();
