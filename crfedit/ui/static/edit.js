// crfedit ui: Select, the edits and the edit stack (loaded after app.js, which holds the state S).
"use strict";

// ------------------------------------------------------------------------------------ select and edit

function scribbledViews(instance) {
  const out = [];
  for (const [key, m] of S.marks) {
    const [inst, vkey] = [Number(key.split("|")[0]), key.slice(key.indexOf("|") + 1)];
    if (inst !== instance || (!m.fg.length && !m.bg.length)) continue;  // a view with keep strokes alone holds back what it shows
    const view = vkey.startsWith("orbit:") ? parseOrbit(vkey) : vkey;
    out.push({ view, fg: Strokes.toJson(m.fg), bg: Strokes.toJson(m.bg) });
  }
  return out;
}

function parseOrbit(key) {
  const [az, el] = key.slice(6).split("@").map(Number);
  return { azimuth: az, elevation: el };
}

async function doSelect() {
  const start = performance.now();
  status("selecting…");
  const kind = $("edit-kind").value;  // recolours select a little more (one material): crfedit.edit.selection.options_for
  const body = { instance: S.instance, views: scribbledViews(S.instance) };
  if (kind === "color" || kind === "remove" || kind === "add") body.kind = kind;
  let info;
  try {
    info = await postJson("/api/select", body);
  } finally {
    status("ready");  // a refused selection (an empty scribble) leaves no "selecting…" behind
  }
  S.tint = true;
  $("tint").checked = true;
  $("selection-info").textContent = `${info.selected_cells} of ${info.occupied_cells} occupied cells selected from ${info.views} view(s) (${info.seconds.toFixed(2)} s)`
    + info.summaries.map(([label, line]) => `; ${label}: ${line}`).join("");  // select's lines (crfedit.edit.selection.SUMMARIES)
  await showView();
  measure("select", start);
  clearError();
  status("ready");
  await showTurntable();
}

function pasteInfo() {
  const c0 = S.copy && Strokes.centroid(S.copy.strokes);
  $("paste-info").textContent = !c0 ? "Scribble the part on the donor first (Draw on donor)."
    : !S.paste ? "Now click where to paste it (paste tool)."
      : `pasted ${Math.round(S.paste[0] - c0[0])}, ${Math.round(S.paste[1] - c0[1])} px from where it was drawn`;
}

function editBody() {
  const kind = $("edit-kind").value;
  const body = { client: S.client, kind, instance: S.instance, view: S.view, seed: Number($("seed").value) };
  const steps = Number($("steps").value);
  if (steps !== 100) body.steps = steps;
  if ($("method").value && kind !== "add" && kind !== "transfer") body.method = $("method").value;
  if (kind === "color" || kind === "remove") {
    body.views = scribbledViews(S.instance);
    if (kind === "color") body.color = $("color").value;
  } else if (kind === "add") {
    const c0 = S.copy && Strokes.centroid(S.copy.strokes);
    body.donor = S.copy ? S.copy.instance : Number($("donor").value);  // the chair the copy strokes were drawn on
    if (c0) {
      body.donor_view = S.copy.view;
      body.copy = Strokes.toJson(S.copy.strokes);
    }
    if (c0 && S.paste) body.offset = [Math.round(S.paste[0] - c0[0]), Math.round(S.paste[1] - c0[1])];
    body.bg = Strokes.toJson(marks().bg);
  } else {
    const sf = $("shape-from").value, cf = $("color-from").value;
    body.shape_from = sf === "" ? null : Number(sf);
    body.color_from = cf === "" ? null : Number(cf);
  }
  return body;
}

async function doApply() {
  if (S.donorMode) toggleDonor();
  if (!S.ws || S.ws.readyState !== WebSocket.OPEN) throw new Error("lost the server: is crfedit ui still running?");
  const body = editBody();
  const start = performance.now();
  clearError();  // an earlier edit's error (a Cancel) is not this one's
  // A job that fails (or finishes) at once can report on the socket before this reply names it:
  // its messages wait in S.early and are read once S.job is set (else the page stayed busy).
  S.early = [];
  let reply;
  try {
    reply = await postJson("/api/edit", body);
  } catch (e) {
    S.early = null;
    throw e;
  }
  const early = S.early;
  S.early = null;
  S.job = { id: reply.job, kind: body.kind, start, steps: reply.steps, instance: body.instance, view: viewKey(body.view) };
  busy(true);
  status(`${body.kind}: starting…`);
  for (const msg of early) await onJobMessage(msg);
}

function busy(on) {
  $("apply").disabled = on;
  $("cancel").hidden = !on;
  $("progress").hidden = !on;
  if (on) $("progress").value = 0;
}

// The stack changed in another tab (or this one): follow the server's stack and state.
async function followStack(msg) {
  if (S.ownOps > 0) return;  // this tab's own change: its reply updates the page
  renderStack(msg.stack);
  if (msg.state === S.state) return;
  S.state = msg.state;
  await showView();
  await showTurntable();
  refreshInstances();
}

async function onJobMessage(msg) {
  if (msg.type === "stack") return followStack(msg);
  if (S.early && !S.job) {  // an Apply is waiting for its reply: this may be its job's message
    S.early.push(msg);
    return;
  }
  if (!S.job || msg.job !== S.job.id) {  // another tab's edit: say so while it runs (this tab's Apply would be refused)
    if (msg.type === "progress") {
      S.other = msg.job;
      status(`another tab's ${msg.kind || "edit"}: step ${msg.step} of ${msg.steps}`);
    } else if (msg.job !== undefined && msg.job === S.other) {
      S.other = null;
      status("ready");
    }
    if (msg.type === "done" && msg.stack) await followStack(msg);
    return;
  }
  if (msg.type === "progress") {
    $("progress").value = msg.step / msg.steps;
    status(`${S.job.kind}: step ${msg.step} of ${msg.steps}`);
    return;
  }
  const job = S.job;
  S.job = null;
  busy(false);
  if (msg.type === "cancelled") {  // what the user asked for: a status line, not the error banner
    status(msg.message);
    return;
  }
  if (msg.type !== "done") {
    status("ready");
    showError(msg.message);
    return;
  }
  clearError();
  S.state = msg.state;
  S.tint = false;
  $("tint").checked = false;
  if (job.kind === "color" || job.kind === "remove" || job.kind === "add") {  // the selection shown was of the state before
    $("selection-info").textContent = job.kind === "add"
      ? "The addition is applied; its copy strokes and paste point are cleared; Select to see a selection on the edited chair."
      : `The ${job.kind === "color" ? "recolour" : "removal"} is applied; `
        + "its strokes are cleared (Ctrl+Z on a view brings them back); Select again to see a selection on the edited chair.";
  } else {
    $("selection-info").textContent = "The transfer is applied; Select to see a selection on the edited chair.";
  }
  if (msg.warning) $("selection-info").textContent += ` Warning: ${msg.warning}.`;  // e.g. an addition that lost part of the part
  if (job.kind === "color" || job.kind === "remove") clearUsedStrokes(job.instance);
  if (job.kind === "add") {  // the copy and the paste point were used: a second Apply would paste the part again
    S.copy = null; S.paste = null;
    pasteInfo();
    redraw();
  }
  // The edit's render is of the view it was made on: shown only if that view is still on screen
  // (the user may have turned to another view or chair while it ran), else the view on screen
  // is rendered again in the new state.
  if (msg.image && !S.donorMode && S.instance === job.instance && viewKey(S.view) === job.view) {
    await setImage($("view"), msg.image);
    $("view").dataset.state = S.state;
  } else {
    await showView();
  }
  measure(`apply-${job.kind}`, job.start);
  status(`${job.kind} applied in ${msg.seconds.toFixed(2)} s`);
  renderStack(msg.stack);
  await showCompare();
  await showTurntable();
  refreshThumb(job.instance);
}

// An applied recolour or removal used every stroke of its instance (scribbledViews): they are
// cleared, each view's undo keeping them, so the next edit does not take them in again.
function clearUsedStrokes(instance) {
  for (const [key, m] of S.marks) {
    if (Number(key.split("|")[0]) !== instance || (!m.fg.length && !m.bg.length)) continue;
    if (!S.undo.has(key)) S.undo.set(key, []);
    S.undo.get(key).push(JSON.stringify(m));
    S.marks.set(key, { fg: [], bg: [] });
  }
  redraw();
}

// ------------------------------------------------------------------------------------ stack

function kb(n) { return n < 1000 ? `${n} B` : n < 1e6 ? `${(n / 1000).toFixed(1)} KB` : `${(n / 1e6).toFixed(1)} MB`; }  // decimal, as the CLI prints sizes

function renderStack(rows) {
  const ol = $("stack");
  ol.replaceChildren();
  for (const row of rows) {
    const li = document.createElement("li");
    li.dataset.id = row.id;
    const on = document.createElement("input");
    on.type = "checkbox"; on.checked = row.enabled; on.className = "toggle"; on.title = "on / off";
    on.addEventListener("change", () => attempt(async () => {
      try {
        await stackOp("/api/stack/toggle", { id: row.id, enabled: on.checked });
      } catch (err) {
        on.checked = !on.checked;  // refused (an edit is running, the server said no): the box shows the stack as it is
        throw err;
      }
    }));
    const text = document.createElement("span");
    text.textContent = `${row.kind} · ${row.instance} · ${kb(row.bytes)} · ${row.seconds.toFixed(2)} s — ${row.label}`;
    const up = button("↑", !row.up, () => stackOp("/api/stack/move", { id: row.id, to: row.position - 1 }));
    const down = button("↓", !row.down, () => stackOp("/api/stack/move", { id: row.id, to: row.position + 1 }));
    const held = "the neighbouring edit changes the same tensors (same chair and modules): their order matters";
    up.title = row.up ? "move up" : row.position === 1 ? "first in the stack" : held;  // positions count from 1
    down.title = row.down ? "move down" : row.position === rows.length ? "last in the stack" : held;
    const save = button("Save", false, async () => {
      const r = await postJson("/api/stack/save", { id: row.id });
      $("saved").textContent = r.again ? `${r.path} already holds this edit (nothing written again)` : `saved ${r.path}`;
    });
    const dl = document.createElement("a");
    dl.textContent = "Download";
    dl.href = `/api/stack/download?id=${row.id}&token=${encodeURIComponent(TOKEN)}`;
    dl.download = row.name;
    li.append(on, text, up, down, save, dl);
    ol.append(li);
  }
}

function button(label, disabled, fn) {
  const b = document.createElement("button");
  b.textContent = label;
  b.disabled = disabled;
  b.addEventListener("click", () => attempt(fn));
  return b;
}

async function stackOp(path, body) {
  if (S.job) throw new Error("an edit is running: wait for it or press Cancel");
  S.ownOps += 1;
  let r;
  try {
    r = await postJson(path, body);
  } finally {
    S.ownOps -= 1;
  }
  S.state = r.state;
  renderStack(r.stack);
  clearError();
  await showView();
  await showTurntable();
  refreshInstances();
}

async function bake() {
  const r = await postJson("/api/bake", {});
  $("saved").textContent = r.again ? `${r.model} already holds this stack, baked (nothing written again)`
    : `baked ${r.model} (from ${r.edits.length} edit file(s) saved beside it)`;
}

async function copyShell() {
  const text = await (await api("/api/shell")).text();
  const area = $("shell-text");
  area.value = text;
  area.hidden = false;
  try { await navigator.clipboard.writeText(text); status("copied the shell commands"); } catch (e) { area.select(); }
}
