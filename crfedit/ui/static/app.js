// crfedit ui: the page.  Plain JavaScript, no network access beyond this server.
// Each user action that ends in a new image records a User Timing measure ("crfedit:view",
// "crfedit:select", "crfedit:apply-color", ...), from the click to the image decoded on screen.
"use strict";

const $ = (id) => document.getElementById(id);
const TOKEN = document.querySelector('meta[name="crfedit-token"]').content;
const S = {
  client: Math.random().toString(36).slice(2, 12),
  info: null, state: "base", instance: 0,
  view: { azimuth: 45, elevation: 30 },
  marks: new Map(), // "instance|view" -> {fg: [], bg: []}
  undo: new Map(), // same keys -> snapshots
  copy: null, // add: {instance, view, strokes: []}
  paste: null, donorMode: false,
  tool: "fg", radius: 1.5, tint: false, drag: null,
  viewBusy: false, viewAgain: false, turnSeq: 0, turnEl: null,
  job: null, ws: null, lost: false, ownOps: 0, // ownOps: this tab's stack changes in flight (their replies update it)
  angles: new Map(), // instance -> {split: [[azimuth, elevation], ...]} of its stored views (/api/angles)
};

// ------------------------------------------------------------------------------------ server

async function api(path, body) {
  const opts = { headers: { "X-Crfedit-Token": TOKEN } };
  if (body !== undefined) {
    opts.method = "POST";
    opts.headers["Content-Type"] = "application/json";
    opts.body = JSON.stringify(body);
  }
  let resp;
  try {
    resp = await fetch(path, opts);
  } catch (e) {
    throw new Error("lost the server: is crfedit ui still running?");
  }
  if (!resp.ok) {
    let message = `the server answered ${resp.status}`;
    try { message = (await resp.json()).error || message; } catch (e) { /* not JSON */ }
    throw new Error(message);
  }
  return resp;
}

const getJson = async (path) => (await api(path)).json();
const postJson = async (path, body) => (await api(path, body)).json();

async function imageUrl(path) {
  return URL.createObjectURL(await (await api(path)).blob());
}

async function setImage(img, url) {
  const old = img.src;
  img.src = url;
  try {
    await img.decode();
  } catch (e) {
    if (img.src !== url) return;  // a newer image took its place mid-decode: not an error
    throw e;
  }
  if (old.startsWith("blob:") && old !== url) URL.revokeObjectURL(old);
}

function measure(name, start) {
  performance.measure(`crfedit:${name}`, { start, end: performance.now() });
}

// ------------------------------------------------------------------------------------ status

function showError(message) {
  $("error-text").textContent = message;
  $("error").hidden = false;
}

function clearError() { $("error").hidden = true; }

function status(text) { $("status-text").textContent = text; }

// A thumbnail image that acts as a button: reachable with Tab, chosen with Enter or Space too.
function clickable(el, fn) {
  el.addEventListener("click", fn);
  if (el.tagName === "BUTTON") return;
  el.tabIndex = 0;
  el.setAttribute("role", "button");
  el.addEventListener("keydown", (ev) => {
    if (ev.key === "Enter" || ev.key === " ") { ev.preventDefault(); fn(); }
  });
}

async function attempt(fn) {
  try {
    await fn();
  } catch (e) {
    showError(e.message.split("\n")[0]);
  }
}

// ------------------------------------------------------------------------------------ views

const viewKey = (v) => (typeof v === "string" ? v : `orbit:${v.azimuth}@${v.elevation}`);
const markKey = (instance = shownInstance(), view = S.view) => `${instance}|${viewKey(view)}`;
const shownInstance = () => (S.donorMode ? Number($("donor").value) : S.instance);

function viewQuery(view, instance) {
  const v = typeof view === "string" ? `view=${encodeURIComponent(view)}` : `az=${view.azimuth}&el=${view.elevation}`;
  return `${v}&instance=${instance}&s=${S.state}`;
}

// The strokes, the instance and the view outlive a reload of the tab (sessionStorage, this
// tab only), for this model and image size.
const storeKey = () => `crfedit:${S.info.model}:${S.info.width}x${S.info.height}`;

function saveMarks() {
  if (!S.info) return;
  const marks = [...S.marks].filter(([, m]) => m.fg.length || m.bg.length);
  try {
    sessionStorage.setItem(storeKey(), JSON.stringify({ marks, instance: S.instance, view: S.view }));
  } catch (e) { /* storage full or off: strokes live in the page only */ }
}

function restoreMarks() {
  let saved = null;
  try { saved = JSON.parse(sessionStorage.getItem(storeKey()) || "null"); } catch (e) { saved = null; }
  if (!saved || !Array.isArray(saved.marks)) return null;
  S.marks = new Map(saved.marks.filter((e) => Array.isArray(e) && e.length === 2 && e[1] && Array.isArray(e[1].fg) && Array.isArray(e[1].bg)));
  const k = Number.isInteger(saved.instance) && saved.instance >= 0 && saved.instance < S.info.instances.length ? saved.instance : 0;
  const v = saved.view;
  const stored = typeof v === "string" && ((S.info.splits[v.slice(0, v.lastIndexOf(":"))] || [])[k] || 0) > Number(v.slice(v.lastIndexOf(":") + 1));
  const view = stored || (v && typeof v === "object" && Number.isFinite(v.azimuth) && Number.isFinite(v.elevation)) ? v : null;
  return { instance: k, view };
}

function marks(key = markKey()) {
  if (!S.marks.has(key)) S.marks.set(key, { fg: [], bg: [] });
  return S.marks.get(key);
}

// Show the current view; requests while one is in flight collapse into one more.
async function showView() {
  if (S.viewBusy) { S.viewAgain = true; return; }
  S.viewBusy = true;
  const start = performance.now();
  try {
    const tint = S.tint && !S.donorMode ? "&tint=1" : "";
    await setImage($("view"), await imageUrl(`/api/view?${viewQuery(S.view, shownInstance())}${tint}`));
    measure("view", start);
    $("view").dataset.state = S.state;
    $("view-label").textContent = `${S.info.instances[shownInstance()]} · ${typeof S.view === "string" ? S.view : `orbit ${S.view.azimuth}° / ${S.view.elevation}°`}${S.donorMode ? " (donor)" : ""}`;
    redraw();
    await showCompare();
  } catch (e) {
    if (S.tint) { S.tint = false; $("tint").checked = false; }
    showError(e.message);
  } finally {
    S.viewBusy = false;
    if (S.viewAgain) { S.viewAgain = false; showView(); }
  }
}

async function showCompare() {
  const mode = $("compare").value;
  if (mode !== "off") {
    const url = await imageUrl(`/api/view?${viewQuery(S.view, shownInstance())}&state=base`);
    await setImage(mode === "wipe" ? $("before") : $("side-before"), url);
    wipe();
  }
  $("before").hidden = mode !== "wipe";
  $("wipe").hidden = mode !== "wipe";
  $("sidebox").hidden = mode !== "side";
}

function wipe() {
  $("before").style.clipPath = `inset(0 ${100 - Number($("wipe").value)}% 0 0)`;
}

// The turntable of the current instance, at the shown view's elevation (S.turnEl: a tile opens
// the view it shows).  A newer call wins: an older call's late replies (the user clicked through
// several chairs) are dropped, not drawn among the newer chair's tiles.
async function showTurntable() {
  const start = performance.now(), seq = ++S.turnSeq;
  const el = (viewAngles() || { elevation: 30 }).elevation;
  S.turnEl = el;
  const tint = S.tint ? "&tint=1" : "";
  const imgs = [...$("turntable").children];
  await Promise.all(imgs.map(async (img, i) => {
    const url = await imageUrl(`/api/view?${viewQuery({ azimuth: i * 45, elevation: el }, S.instance)}${tint}`);
    if (seq === S.turnSeq) await setImage(img, url); else URL.revokeObjectURL(url);
  }));
  if (seq === S.turnSeq) measure("turntable", start);
}

// Where a view looks from: an orbit view's own angles, a stored view's from /api/angles (null
// until they have come).
function viewAngles(view = S.view) {
  if (typeof view !== "string") return view;
  const [split, index] = [view.slice(0, view.lastIndexOf(":")), Number(view.slice(view.lastIndexOf(":") + 1))];
  const a = ((S.angles.get(shownInstance()) || {})[split] || [])[index];
  return a ? { azimuth: a[0], elevation: Math.max(-80, Math.min(80, a[1])) } : null;
}

// The sliders show where the view looks from (a stored view's angles with "≈": the orbit view
// there is at the stored views' distance, not the view itself).
function showSliders() {
  const a = viewAngles();
  if (!a) return;
  const near = typeof S.view === "string" ? "≈" : "";
  $("azimuth").value = a.azimuth; $("az-out").textContent = `${near}${a.azimuth}°`;
  $("elevation").value = a.elevation; $("el-out").textContent = `${near}${a.elevation}°`;
}

function setView(view) {
  S.view = view;
  showSliders();
  saveMarks();
  showView();
  if (typeof view === "string") followTurntable();
}

async function loadAngles(k) {
  if (!S.angles.has(k)) S.angles.set(k, await getJson(`/api/angles?instance=${k}`));
  showSliders();
  followTurntable();
}

// The turntable drawn again when the view's elevation is not the tiles' (a stored view picked,
// its angles come, the elevation slider let go): drawn at 30° before a stored view's angles had
// come, a tile opened a view at that view's elevation, not the one it showed.
function followTurntable() {
  const a = viewAngles();
  if (a && a.elevation !== S.turnEl) attempt(showTurntable);
}

function orbitFromSliders() {
  setView({ azimuth: Number($("azimuth").value), elevation: Number($("elevation").value) });
}

// ------------------------------------------------------------------------------------ canvas

// The shown view's size in pixels: the rendered PNG's own (views of a model may come in several
// sizes), else the model's first view's until the first image has loaded.
function viewSize() {
  const img = $("view");
  return img.naturalWidth ? [img.naturalWidth, img.naturalHeight] : [S.info.width, S.info.height];
}

function canvasScale() {
  const c = $("strokes");
  return c.width / viewSize()[0];
}

function redraw() {
  const c = $("strokes"), img = $("view");
  const w = img.clientWidth, dpr = window.devicePixelRatio || 1;
  if (c.width !== Math.round(w * dpr) || c.height !== Math.round(img.clientHeight * dpr)) {
    c.width = Math.round(w * dpr);
    c.height = Math.round(img.clientHeight * dpr);
  }
  const ctx = c.getContext("2d");
  ctx.clearRect(0, 0, c.width, c.height);
  saveMarks();
  const scale = canvasScale();
  if (S.donorMode) {
    Strokes.draw(ctx, S.copy ? S.copy.strokes : [], "copy", scale);
    pasteInfo();  // the hint follows the copy strokes as they are drawn, erased or undone
    return;
  }
  const m = marks();
  Strokes.draw(ctx, m.bg, "bg", scale);
  Strokes.draw(ctx, m.fg, "fg", scale);
  if ($("edit-kind").value === "add" && S.copy && S.paste) {
    const c0 = Strokes.centroid(S.copy.strokes);
    if (c0) Strokes.draw(ctx, S.copy.strokes, "copy", scale, [S.paste[0] - c0[0], S.paste[1] - c0[1]], true);
    Strokes.marker(ctx, S.paste, scale);
  }
}

function pixelAt(event) {
  const r = $("strokes").getBoundingClientRect();
  const [w, h] = viewSize();
  return [(event.clientX - r.left) / r.width * w - 0.5, (event.clientY - r.top) / r.height * h - 0.5];
}

function activeList(kind) {
  if (S.donorMode) {
    if (!S.copy || S.copy.instance !== shownInstance() || viewKey(S.copy.view) !== viewKey(S.view)) {
      S.copy = { instance: shownInstance(), view: S.view, strokes: [] };
    }
    return S.copy.strokes;
  }
  return marks()[kind];
}

function snapshot() {
  const key = S.donorMode ? "copy" : markKey();
  const state = S.donorMode ? JSON.stringify(S.copy) : JSON.stringify(marks());
  if (!S.undo.has(key)) S.undo.set(key, []);
  S.undo.get(key).push(state);
}

function undo() {
  const key = S.donorMode ? "copy" : markKey();
  const stack = S.undo.get(key);
  if (!stack || !stack.length) return;
  const state = JSON.parse(stack.pop());
  if (S.donorMode) S.copy = state; else S.marks.set(key, state);
  redraw();
}

function onDown(e) {
  if (!S.info) return;
  e.preventDefault();
  $("strokes").setPointerCapture(e.pointerId);
  const p = pixelAt(e);
  if (S.tool === "orbit") {
    S.drag = { x: e.clientX, y: e.clientY, view: viewAngles() || { azimuth: 45, elevation: 30 } };
  } else if (S.tool === "paste") {
    S.paste = p;
    pasteInfo();
    redraw();
  } else if (S.tool === "erase") {
    snapshot();
    S.drag = { erase: true, last: p };
    erase(p);
  } else {
    snapshot();
    const list = activeList(S.tool);
    list.push({ points: [p], radius: S.radius });
    S.drag = { stroke: list[list.length - 1] };
    redraw();
  }
}

function onMove(e) {
  if (!S.drag) return;
  const p = pixelAt(e);
  if (S.drag.stroke) {
    const pts = S.drag.stroke.points, last = pts[pts.length - 1];
    if (Math.hypot(p[0] - last[0], p[1] - last[1]) >= 0.35) { pts.push(p); redraw(); }
  } else if (S.drag.erase) {
    // the path between two pointer events too: a quick swipe's events lie pixels apart
    const [x0, y0] = S.drag.last, n = Math.max(1, Math.ceil(Math.hypot(p[0] - x0, p[1] - y0) / Math.max(0.5, S.radius)));
    for (let i = 1; i <= n; i++) erase([x0 + (p[0] - x0) * i / n, y0 + (p[1] - y0) * i / n], i === n);
    S.drag.last = p;
  } else if (S.drag.view) {
    const az = Math.round(((S.drag.view.azimuth - (e.clientX - S.drag.x) * 0.5) % 360 + 360) % 360);
    const el = Math.round(Math.max(-80, Math.min(80, S.drag.view.elevation + (e.clientY - S.drag.y) * 0.4)));
    if (az !== S.view.azimuth || el !== S.view.elevation) setView({ azimuth: az, elevation: el });
  }
}

function onUp() { S.drag = null; }

function erase(p, draw = true) {
  const r = S.radius;
  if (S.donorMode) {
    if (S.copy) S.copy.strokes = S.copy.strokes.filter((s) => !Strokes.touches(s, p, r));
  } else {
    const m = marks();
    m.fg = m.fg.filter((s) => !Strokes.touches(s, p, r));
    m.bg = m.bg.filter((s) => !Strokes.touches(s, p, r));
  }
  if (draw) redraw();
}

function clearStrokes() {
  snapshot();
  if (S.donorMode) S.copy = null; else S.marks.set(markKey(), { fg: [], bg: [] });
  redraw();
}

// ------------------------------------------------------------------------------------ set-up

function refreshThumb(k) {
  const img = $("instances").querySelector(`img[data-k="${k}"]`);
  if (img) attempt(async () => setImage(img, await imageUrl(`/api/thumb?instance=${k}&s=${S.state}`)));
}

function refreshInstances() {
  for (const img of $("instances").querySelectorAll("img")) refreshThumb(Number(img.dataset.k));
}

function pickInstance(k) {
  S.instance = k;
  $("instance-select").value = k;
  for (const img of $("instances").children) img.classList.toggle("current", Number(img.dataset.k) === k);
  S.tint = false;
  $("tint").checked = false;
  buildSplitViews();
  showSliders();
  showView();
  attempt(() => loadAngles(k));
  attempt(showTurntable);
}

function buildSplitViews() {
  const box = $("split-views");
  box.replaceChildren();
  for (const [split, counts] of Object.entries(S.info.splits)) {
    const n = counts[S.instance] || 0;
    if (!n) continue;
    const det = document.createElement("details");
    const sum = document.createElement("summary");
    sum.textContent = `${split} views (${n})`;
    det.append(sum);
    const list = document.createElement("div");
    list.className = "thumbs small";
    const photos = S.info.photos.includes(split);
    for (let i = 0; i < n; i++) {
      const el = document.createElement(photos ? "img" : "button");
      if (!photos) el.textContent = i;
      el.title = `${split}:${i}`;
      clickable(el, () => setView(`${split}:${i}`));
      list.append(el);
    }
    det.addEventListener("toggle", () => {
      if (!det.open || !photos) return;
      [...list.children].forEach((img, i) => {
        if (!img.src) attempt(async () => setImage(img, await imageUrl(`/api/photo?instance=${S.instance}&split=${split}&index=${i}`)));
      });
    }, { once: false });
    det.append(list);
    box.append(det);
  }
}

function toggleDonor() {
  S.donorMode = !S.donorMode;
  $("draw-donor").textContent = S.donorMode ? "Back to the instance" : "Draw on donor";
  if (S.donorMode) {  // the target's view is kept for the way back; the donor opens where its copy was drawn
    S.targetView = S.view;
    if (S.copy) S.view = S.copy.view;
  } else {
    S.tool = "paste"; document.querySelector('input[name="tool"][value="paste"]').checked = true;
    if (S.targetView !== undefined) S.view = S.targetView;  // back to the view the paste goes on
  }
  pasteInfo();
  showSliders();
  showView();
}

function connect() {
  const ws = new WebSocket(`ws://${location.host}/api/ws?token=${encodeURIComponent(TOKEN)}&client=${S.client}`);
  S.ws = ws;
  ws.onopen = () => {
    if (S.lost) { S.lost = false; clearError(); }
    status("ready");
  };
  ws.onmessage = (ev) => attempt(() => onJobMessage(JSON.parse(ev.data)));
  ws.onclose = () => {
    if (S.job) { S.job = null; busy(false); }
    S.lost = true;
    status("lost the server");
    showError("lost the server: is crfedit ui still running? (retrying)");
    setTimeout(retry, 2000);
  };
}

// Reconnect while the server is away; a server that answers but refuses this page's token is
// another one (crfedit ui started again prints a new URL): say so and stop retrying.
async function retry() {
  let resp = null;
  try { resp = await fetch("/api/state", { headers: { "X-Crfedit-Token": TOKEN } }); } catch (e) { /* still away */ }
  if (resp && resp.status === 403) {
    status("another server");
    showError("crfedit ui was started again: this page's session token is the old one's; open the URL it printed now");
    return;
  }
  if (resp && resp.ok) { connect(); return; }
  setTimeout(retry, 2000);
}

async function start() {
  S.info = await getJson("/api/state");
  S.state = S.info.state;
  $("model-name").textContent = S.info.model;
  const names = S.info.instances;
  for (const id of ["instance-select", "donor", "shape-from", "color-from"]) {
    const sel = $(id);
    if (id === "shape-from" || id === "color-from") sel.append(new Option("—", ""));
    names.forEach((n, k) => sel.append(new Option(n, k)));
  }
  $("donor").value = names.length > 1 ? 1 : 0;
  names.slice(0, 48).forEach((n, k) => {
    const img = document.createElement("img");
    img.dataset.k = k;
    img.title = n;
    clickable(img, () => pickInstance(k));
    $("instances").append(img);
  });
  for (let i = 0; i < 8; i++) {
    const img = document.createElement("img");
    img.title = `orbit ${i * 45}°`;
    clickable(img, () => setView({ azimuth: i * 45, elevation: S.turnEl ?? 30 }));  // the view the tile shows
    $("turntable").append(img);
  }
  S.radius = Math.max(1, Math.round(S.info.width / 48 * 4) / 4);  // on the slider's 0.25 steps, so it can be chosen again
  $("radius").max = Math.max(8, S.info.width / 8);
  $("radius").value = S.radius;
  $("radius-out").textContent = `${S.radius.toFixed(2)} px`;
  renderStack(S.info.stack);
  connect();
  const restored = restoreMarks();
  if (restored && restored.view) S.view = restored.view;
  pickInstance(restored ? restored.instance : 0);
  refreshInstances();
}

function wire() {
  $("azimuth").addEventListener("input", orbitFromSliders);
  $("elevation").addEventListener("input", orbitFromSliders);
  $("elevation").addEventListener("change", followTurntable);  // let go: the tiles at the new elevation
  $("instance-select").addEventListener("change", () => pickInstance(Number($("instance-select").value)));
  document.querySelectorAll('input[name="tool"]').forEach((r) => r.addEventListener("change", () => { S.tool = r.value; }));
  $("radius").addEventListener("input", () => { S.radius = Number($("radius").value); $("radius-out").textContent = `${S.radius.toFixed(2)} px`; });
  $("undo").addEventListener("click", undo);
  $("clear").addEventListener("click", clearStrokes);
  document.addEventListener("keydown", (e) => {  // a text field keeps its own Ctrl+Z (undo of the typing)
    const typing = e.target instanceof HTMLElement && e.target.matches("input[type=text], input[type=number], input:not([type]), textarea");
    if ((e.ctrlKey || e.metaKey) && e.key === "z" && !typing) { e.preventDefault(); undo(); }
  });
  const c = $("strokes");
  c.addEventListener("pointerdown", onDown);
  c.addEventListener("pointermove", onMove);
  c.addEventListener("pointerup", onUp);
  c.addEventListener("pointercancel", onUp);
  $("compare").addEventListener("change", () => attempt(showCompare));
  $("wipe").addEventListener("input", wipe);
  $("select").addEventListener("click", () => attempt(doSelect));
  $("clear-selection").addEventListener("click", () => attempt(async () => {
    await postJson("/api/select/clear", { instance: S.instance });
    S.tint = false; $("tint").checked = false;
    $("selection-info").textContent = "";
    await showView();
  }));
  // showView turns the tint off again when there is no selection to show; the turntable follows it
  $("tint").addEventListener("change", () => attempt(async () => { S.tint = $("tint").checked; await showView(); await showTurntable(); }));
  $("edit-kind").addEventListener("change", () => {
    for (const d of document.querySelectorAll(".kind")) d.hidden = d.dataset.kind !== $("edit-kind").value;
    if (S.donorMode && $("edit-kind").value !== "add") toggleDonor();
    redraw();
  });
  $("draw-donor").addEventListener("click", toggleDonor);
  $("donor").addEventListener("change", () => {
    if (S.copy && S.copy.instance !== Number($("donor").value)) {  // the copy strokes belong to the other chair
      S.copy = null; S.paste = null;
      pasteInfo();
      redraw();
    }
    if (S.donorMode) showView();
  });
  $("apply").addEventListener("click", () => attempt(doApply));
  $("cancel").addEventListener("click", () => attempt(() => postJson("/api/cancel", {})));
  $("bake").addEventListener("click", () => attempt(bake));
  $("shell").addEventListener("click", () => attempt(copyShell));
  $("error-close").addEventListener("click", clearError);
  window.addEventListener("resize", redraw);
  // the view's size changes without the window's too (compare side by side on and off): the
  // canvas follows it, or strokes were drawn stretched until the window was resized
  if (window.ResizeObserver) new ResizeObserver(() => { if (S.info) redraw(); }).observe($("view"));
}

document.addEventListener("DOMContentLoaded", () => { wire(); attempt(start); });
