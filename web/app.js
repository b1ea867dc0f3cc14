// The rig console: talks to the daemon's /api/v1 (same origin), listens to /api/v1/events (SSE:
// progress, model, devices) and drives the 3D viewer. No framework: each panel is a function that
// renders from the last answer it got.

import { Viewer } from "./viewer.js";
import * as words from "./words.js";

const $ = (id) => document.getElementById(id);
const el = (tag, props = {}, ...children) => {
  const e = Object.assign(document.createElement(tag), props);
  for (const c of children) e.append(c);
  return e;
};

/** State the page keeps (also read by the browser tests). */
const state = {
  progress: null,
  running: false,
  methods: [],
  scans: [],
  // The running scan's live estimate: the last `model` event, whether it is still to be fetched,
  // how many estimates were drawn and the event of the one on screen.
  live: { scanId: null, event: null, dirty: false, fetching: false, renders: 0, shown: null },
  shownScan: null,
  // Whether the panels were started (after sign-in, where the daemon asks for one).
  booted: false,
  kind: "mesh",
};
window.scanrig = state;

class ApiError extends Error {
  constructor(status, code, message) {
    super(words.errorWords(code, message, status));
    this.status = status;
    this.code = code;
  }
}

/** fetch /api/v1`path`; throws an ApiError in words on a non-2xx answer. */
async function api(path, opts = {}) {
  if (opts.json !== undefined) {
    opts = { ...opts, headers: { "content-type": "application/json" }, body: JSON.stringify(opts.json) };
  }
  let r;
  try {
    r = await fetch("/api/v1" + path, opts);
  } catch (e) {
    throw new ApiError(0, "unreachable", "the daemon cannot be reached");
  }
  if (!r.ok) {
    const e = await r.json().catch(() => ({}));
    // The session ended (signed out elsewhere, expired, or the daemon restarted): ask again.
    if (r.status === 401 && e.error && e.error.code === "unauthorized" && state.booted) showSignIn();
    throw new ApiError(r.status, e.error && e.error.code, e.error && e.error.message);
  }
  return r;
}
const getJson = async (path) => (await api(path)).json();
const post = (path, json) => api(path, { method: "POST", json: json === undefined ? {} : json });

/** Run `f` for a button: disable it meanwhile, show the outcome in `out`. */
async function act(button, out, f, done) {
  button.disabled = true;
  out.textContent = "";
  out.classList.remove("error");
  try {
    const r = await f();
    if (done) out.textContent = typeof done === "function" ? done(r) : done;
  } catch (e) {
    out.textContent = e.message;
    out.classList.add("error");
  } finally {
    button.disabled = false;
    applyRunning();
  }
}

// ---- 3D viewer ----------------------------------------------------------------------------

const viewer = new Viewer($("viewer"), (info) => {
  if (!info) {
    $("size").textContent = "";
    return;
  }
  const mm = info.size_m.map((v) => (v * 1000).toFixed(1));
  $("size").textContent = "Size: " + mm[0] + " × " + mm[1] + " × " + mm[2] + " mm (width × depth × height), " +
    info.count.toLocaleString() + (info.kind === "mesh" ? " vertices" : info.kind === "voxels" ? " voxels" : " points") +
    (info.colours ? ", in colour" : "") + ".";
  $("viewer-title").textContent = info.title;
});

const parsePly = async (r) => Viewer.parse(await r.arrayBuffer());

/** The stored file names of a scan that serve `kind`, best first. */
function sources(scan, kind) {
  const has = (name) => !scan.outputs || scan.outputs.includes(name) || scan.outputs.includes(name.replace("model.", "mesh."));
  const id = scan.id, out = [];
  const add = (url, as, what) => out.push({ url, as, what });
  if (kind === "mesh" && has("model.ply")) {
    add(`/scans/${id}/model.ply?kind=mesh`, "mesh", "mesh");
    add(`/scans/${id}/files/model.ply`, "mesh", "mesh");
  }
  if (kind === "voxels" && has("voxels.ply")) {
    add(`/scans/${id}/model.ply?kind=voxels`, "voxels", "voxels");
    add(`/scans/${id}/files/voxels.ply`, "voxels", "voxels");
  }
  if (kind === "points") {
    if (has("cloud.ply")) {
      add(`/scans/${id}/model.ply?kind=cloud`, "points", "measured points");
      add(`/scans/${id}/files/cloud.ply`, "points", "measured points");
    }
    if (has("model.ply")) add(`/scans/${id}/model.ply?kind=mesh`, "points", "mesh vertices");
  }
  return out;
}

/** Open stored scan `scan` in the viewer as the chosen kind. */
async function openScan(scan) {
  state.shownScan = scan.id;
  state.live.scanId = null;
  const title = words.methodWords(scan.method) + " scan of " + words.dateWords(scan.created_unix, scan.created);
  $("viewer-title").textContent = "Loading " + title + "…";
  let report = scan.report;
  for (const s of sources(scan, state.kind)) {
    try {
      const g = await parsePly(await api(s.url));
      if (!g) continue;
      if (s.as === "voxels" && !(report && report.voxel_size_m)) report = (await getJson("/scans/" + scan.id)).report;
      if (state.shownScan !== scan.id) return; // another model was asked for meanwhile
      viewer.show(g, s.as, { title: title + ": " + s.what, scanId: scan.id, voxelSize: report && report.voxel_size_m });
      return;
    } catch (e) {
      if (e.status !== 404) {
        $("viewer-title").textContent = "Cannot load " + title + ": " + e.message;
        return;
      }
    }
  }
  $("viewer-title").textContent = title + " has no " + (state.kind === "points" ? "point cloud" : state.kind) + " to show.";
}

/** Fetch and show the newest live estimate (one request at a time; the latest event wins). */
async function showLive() {
  const live = state.live;
  if (live.fetching || !live.dirty || !live.scanId) return;
  live.fetching = true;
  live.dirty = false;
  const id = live.scanId, m = live.event;
  try {
    const g = await parsePly(await api(`/scans/${id}/live.ply?v=${m.version}`));
    if (g && live.scanId === id) {
      const n = g.getAttribute("position").count;
      viewer.show(g, "points", {
        live: true, scanId: id,
        title: "Live estimate while scanning: after view " + ((m.position ?? 0) + 1) + ", " + n.toLocaleString() + " points",
      });
      live.renders += 1;
      live.shown = m;
    }
  } catch (e) {
    $("viewer-title").textContent = "Live estimate unavailable: " + e.message;
  } finally {
    live.fetching = false;
  }
  showLive();
}

document.querySelectorAll('input[name="kind"]').forEach((r) => r.addEventListener("change", () => {
  state.kind = r.value;
  const scan = state.scans.find((s) => s.id === state.shownScan);
  if (scan && !state.live.scanId) openScan(scan);
}));
$("wireframe").addEventListener("change", (e) => viewer.setWireframe(e.target.checked));
$("lighting").addEventListener("change", (e) => viewer.setLighting(e.target.checked));
$("reset-view").addEventListener("click", () => viewer.frame());

// ---- status, methods, start / pause / resume / cancel ---------------------------------------

async function loadStatus() {
  try {
    const s = await getJson("/status");
    $("rig").textContent = "Rig “" + s.rig + "”, scanrig " + s.version + ".";
    if (!$("positions").placeholder) {
      $("positions").placeholder = s.defaults.positions;
      $("resolution").placeholder = s.defaults.resolution;
    }
    renderDevices(s.devices);
    if (!state.progress) renderProgress(s.progress);
  } catch (e) {
    $("rig").textContent = "Daemon unreachable: " + e.message;
  }
}

async function loadMethods() {
  try {
    const m = await getJson("/methods");
    state.methods = m.methods;
    const sel = $("method");
    sel.replaceChildren(...m.methods.map((x) => el("option", {
      value: x.method, disabled: !x.available, selected: x.method === m.default,
      textContent: words.methodWords(x.method) + (x.available ? "" : " (unavailable)"),
      title: x.missing.join("; "),
    })));
    $("unavailable").replaceChildren(...m.methods.filter((x) => !x.available).map((x) =>
      el("li", { textContent: words.methodWords(x.method) + " needs: " + x.missing.join("; ") + "." })));
  } catch (e) {
    $("unavailable").replaceChildren(el("li", { textContent: "Cannot list the methods: " + e.message }));
  }
}

$("start-form").addEventListener("submit", (ev) => {
  ev.preventDefault();
  const body = { method: $("method").value || undefined };
  if ($("positions").value) body.positions = Number($("positions").value);
  if ($("resolution").value) body.resolution = Number($("resolution").value);
  act($("start"), $("msg"), async () => {
    const meta = await (await post("/scans", body)).json();
    $("msg").textContent = "Starting scan " + meta.id + "…";
    state.running = true;
    applyRunning();
    loadHistory();
  });
});
const current = () => state.progress && state.progress.scan_id;
// What to say once the daemon accepted a pause, resume or cancel: the interim words, unless the
// event stream already told the outcome (a scan can stop before the request's answer arrives).
const interim = (text, settled) => () =>
  state.progress && settled(state.progress.status) ? words.progressWords(state.progress) : text;
$("pause").addEventListener("click", () => act($("pause"), $("msg"), () => post(`/scans/${current()}/pause`),
  interim("Pausing at the end of this view…", (s) => s !== "running")));
$("resume").addEventListener("click", () => act($("resume"), $("msg"), () => post(`/scans/${current()}/resume`),
  interim("Resuming…", (s) => s === "running")));
$("cancel").addEventListener("click", () => act($("cancel"), $("msg"), () => post(`/scans/${current()}/cancel`),
  interim("Cancelling at the end of this view…", (s) => s !== "running")));

function renderProgress(p) {
  const previous = state.progress;
  state.progress = p;
  state.running = !!p && p.status === "running";
  const bar = $("progress");
  bar.max = p && p.total ? p.total : 1;
  bar.value = p && p.total ? Math.min(p.step, p.total) : (p && p.status === "complete" ? 1 : 0);
  $("msg").textContent = words.progressWords(p);
  applyRunning();
  const changed = !previous || previous.status !== (p && p.status) || previous.scan_id !== (p && p.scan_id);
  if (changed) {
    loadHistory();
    loadCamera();
    if (!state.running) loadControl();
  }
  // A scan just finished: show its result instead of the live estimate.
  if (p && p.status === "complete" && previous && previous.scan_id === p.scan_id && previous.status === "running") {
    getJson("/scans/" + p.scan_id).then((s) => openScan({ ...s.scan, report: s.report })).catch(() => {});
  }
}

/** Enable what can be used now: manual control and starting only when no scan runs. */
function applyRunning() {
  const p = state.progress, running = state.running;
  $("control-set").disabled = running;
  $("start").disabled = running;
  $("pause").disabled = !running;
  $("resume").disabled = running || !p || !["paused", "interrupted"].includes(p.status);
  $("cancel").disabled = !p || !["running", "paused"].includes(p.status);
  document.body.classList.toggle("scanning", running);
  if (running) $("control-state").textContent = "Manual control is off while a scan runs.";
}

// ---- live camera ----------------------------------------------------------------------------

async function loadCamera() {
  try {
    const c = await getJson("/camera");
    const figures = [c.width && c.height ? c.width + " × " + c.height + " px" : null,
      c.exposure_us != null ? "exposure " + (c.exposure_us / 1000).toFixed(1) + " ms" : "exposure automatic or unknown",
      c.gain_db != null ? "gain " + c.gain_db.toFixed(1) + " dB" : "gain unknown"].filter(Boolean);
    $("camera-info").textContent = "Camera (" + c.kind + "): " + figures.join(", ") + ".";
    $("camera-note").textContent = c.streaming_paused || state.running
      ? "The picture is paused while the scan uses the camera; it comes back when the scan ends." : "";
  } catch (e) {
    $("camera-info").textContent = "Camera settings unavailable: " + e.message;
  }
}
let cameraRetry = null;
$("camera").addEventListener("load", () => { $("camera").hidden = false; });
$("camera").addEventListener("error", () => {
  $("camera").hidden = true;
  $("camera-note").textContent = "No live picture from the camera; trying again in 10 s.";
  clearTimeout(cameraRetry);
  cameraRetry = setTimeout(() => { $("camera").src = "/api/v1/camera.mjpg?t=" + Date.now(); }, 10000);
});

// ---- manual control -------------------------------------------------------------------------

function renderControl(c) {
  const angle = c.angle_deg == null ? "unknown" : c.angle_deg.toFixed(1) + "°";
  const proj = c.projector == null ? "none" : c.projector;
  if (!state.running) $("control-state").textContent = "Turntable at " + angle + "; projector: " + proj + ".";
  const toggles = (box, list, what, path) => {
    box.replaceChildren(...(list || []).map((on, k) => {
      const b = el("button", { type: "button", id: `${what}-${k}`, textContent: `${what === "light" ? "Light" : "Laser"} ${k + 1}: ${on ? "on" : "off"}` });
      b.setAttribute("aria-pressed", on ? "true" : "false");
      b.addEventListener("click", () => act(b, $("control-msg"), async () => renderControl(await (await post(path, { index: k, on: !on })).json())));
      return b;
    }));
  };
  toggles($("lights"), c.lights, "light", "/control/light");
  toggles($("lasers"), c.lasers, "laser", "/control/laser");
  $("projector").hidden = c.projector == null;
}

async function loadControl() {
  try {
    renderControl(await getJson("/control"));
  } catch (e) {
    $("control-state").textContent = "Manual control unavailable: " + e.message;
  }
}
const controlAct = (button, body, path) => act(button, $("control-msg"), async () => {
  const r = await (await post(path, body)).json();
  if (r.lights) renderControl(r); else loadControl();
});
$("turn").addEventListener("click", () => {
  const deg = Number($("turn-deg").value);
  if (!isFinite(deg)) { $("control-msg").textContent = "Type the angle to turn by, in degrees."; return; }
  controlAct($("turn"), { turn_deg: deg }, "/control/turntable");
});
$("home").addEventListener("click", () => controlAct($("home"), { home: true }, "/control/turntable"));
$("show-pattern").addEventListener("click", () => controlAct($("show-pattern"), { pattern: $("pattern").value }, "/control/projector"));
$("show-colour").addEventListener("click", () => {
  const hex = $("colour").value, rgb = [1, 3, 5].map((i) => parseInt(hex.slice(i, i + 2), 16));
  controlAct($("show-colour"), { colour: rgb }, "/control/projector");
});
$("blank").addEventListener("click", () => controlAct($("blank"), { blank: true }, "/control/projector"));

// ---- devices --------------------------------------------------------------------------------

function renderDevices(list) {
  $("devices").replaceChildren(...(list || []).map((d) => {
    const b = el("button", { type: "button", textContent: "Reconnect", id: "reconnect-" + d.name });
    b.setAttribute("aria-label", "Reconnect the " + d.name);
    b.addEventListener("click", () => act(b, $("devices-msg"), () => post(`/devices/${encodeURIComponent(d.name)}/reconnect`),
      "Reconnect of the " + d.name.replace(/_/g, " ") + " requested."));
    const cell = (label, text, className = "") => {
      const c = el("td", { textContent: text, className });
      c.dataset.label = label;
      return c;
    };
    return el("tr", {}, el("th", { scope: "row", textContent: d.name.replace(/_/g, " ") + " (" + d.kind + ")" }),
      cell("State", words.deviceStateWords(d.state), "state-" + d.state), cell("Last error", d.last_error || "none"),
      cell("Reconnects", String(d.reconnects ?? 0)), el("td", {}, b));
  }));
}

// ---- history --------------------------------------------------------------------------------

async function loadHistory() {
  try {
    const list = (await getJson("/scans")).scans || [];
    list.sort((a, b) => (b.created_unix || 0) - (a.created_unix || 0) || (b.id > a.id ? 1 : -1));
    state.scans = list;
    $("history").replaceChildren(...list.map(scanCard));
    $("history-msg").textContent = list.length ? list.length + " scan" + (list.length > 1 ? "s" : "") + " stored." : "No scan stored yet.";
    // Open the newest finished scan when nothing is shown yet.
    const done = list.find((s) => s.status === "complete");
    if (done && !state.shownScan && !state.live.scanId) openScan(done);
    for (const s of list.slice(0, 20)) if (s.report === undefined && s.status === "complete") fillFigures(s);
  } catch (e) {
    $("history-msg").textContent = "Cannot list the scans: " + e.message;
  }
}

async function fillFigures(scan) {
  try {
    const full = await getJson("/scans/" + scan.id);
    scan.report = full.report;
    const f = document.querySelector(`[data-scan="${scan.id}"] .figures`);
    if (f) f.textContent = words.figureWords(full.report).join(" · ");
  } catch (e) { /* the card keeps no figures */ }
}

function scanCard(s) {
  const id = s.id, title = words.methodWords(s.method) + ", " + words.dateWords(s.created_unix, s.created);
  const busy = s.status === "running";
  // A reprocessed scan shows its source's first view; a running one has none to show yet.
  const pictured = s.reprocess_of ? state.scans.find((x) => x.id === s.reprocess_of) : s;
  const noPicture = () => el("div", { className: "thumb none", textContent: "no picture" });
  let thumb = noPicture();
  if (pictured && pictured.status !== "running" && !pictured.reprocess_of) {
    thumb = el("img", { className: "thumb", alt: "", width: 120, height: 90, src: `/api/v1/scans/${pictured.id}/thumbnail.jpg` });
    thumb.addEventListener("error", () => thumb.replaceWith(noPicture()));
  }
  const status = words.statusWords(s.status) + (s.error ? ": " + s.error : "") + (s.reprocess_of ? " (reprocessed from " + s.reprocess_of + ")" : "");
  const out = el("p", { className: "card-msg", role: "status" });
  const open = el("button", { type: "button", textContent: "Open in 3D view", className: "open" });
  open.addEventListener("click", () => { openScan(s); $("viewer").scrollIntoView({ behavior: "smooth", block: "center" }); });
  open.disabled = s.status !== "complete";
  const links = el("p", { className: "downloads" }, "Download: ");
  const files = [["model.ply", "PLY"], ["model.stl", "STL"], ["model.obj", "OBJ"]];
  const has = (name) => !s.outputs || s.outputs.includes(name) || s.outputs.includes(name.replace("model.", "mesh."));
  if (s.status === "complete") {
    for (const [file, label] of files) if (has(file)) links.append(el("a", { href: `/api/v1/scans/${id}/files/${file}`, download: `${id}-${file}`, textContent: label }), " ");
  }
  links.append(el("a", { href: `/api/v1/scans/${id}/archive.zip`, download: `${id}.zip`, textContent: "everything (zip)" }));
  const del = el("button", { type: "button", textContent: "Delete", className: "delete", disabled: busy });
  del.addEventListener("click", () => {
    if (!window.confirm("Delete the " + title + " scan (" + id + ")? Its files are removed from disk.")) return;
    act(del, out, async () => {
      await api(`/scans/${id}`, { method: "DELETE" });
      if (state.shownScan === id) { state.shownScan = null; viewer.clear(); }
      $("history-msg").textContent = "Deleted scan " + id + ".";
      await loadHistory();
    });
  });
  const rp = reprocessForm(s, out);
  const card = el("li", { className: "card status-" + s.status }, thumb,
    el("div", { className: "card-body" },
      el("h3", { textContent: title }),
      el("p", { className: "status", textContent: status + " · " + s.positions + " positions · resolution " + s.resolution + " · id " + id }),
      el("p", { className: "figures", textContent: words.figureWords(s.report).join(" · ") }),
      links,
      el("div", { className: "buttons" }, open, del), rp, out));
  card.dataset.scan = id;
  return card;
}

function reprocessForm(s, out) {
  const details = el("details", { className: "reprocess" }, el("summary", { textContent: "Reprocess with other settings" }));
  const idp = "rp-" + s.id;
  const method = el("select", { id: idp + "-method" }, ...state.methods.map((m) =>
    el("option", { value: m.method, textContent: words.methodWords(m.method), selected: m.method === s.method })));
  const res = el("input", { id: idp + "-resolution", type: "number", min: 2, max: 4096, placeholder: String(s.resolution || ""), inputMode: "numeric" });
  const smooth = el("input", { id: idp + "-smooth", type: "number", min: 0, max: 16, placeholder: "as before", inputMode: "numeric" });
  const go = el("button", { type: "submit", textContent: "Reprocess", className: "do-reprocess" });
  const form = el("form", {},
    el("label", { htmlFor: method.id, textContent: "Method" }), method,
    el("label", { htmlFor: res.id, textContent: "Resolution (voxels)" }), res,
    el("label", { htmlFor: smooth.id, textContent: "Smoothing (voxels)" }), smooth, go);
  form.addEventListener("submit", (ev) => {
    ev.preventDefault();
    const body = { method: method.value };
    if (res.value) body.resolution = Number(res.value);
    if (smooth.value) body.smooth_radius = Number(smooth.value);
    act(go, out, async () => {
      const meta = await (await post(`/scans/${s.id}/reprocess`, body)).json();
      out.textContent = "Reprocessing as scan " + meta.id + "…";
      state.running = true;
      applyRunning();
      loadHistory();
    });
  });
  go.disabled = s.status === "running";
  details.append(form);
  return details;
}

// ---- events ---------------------------------------------------------------------------------

function listen() {
  const events = new EventSource("/api/v1/events");
  events.addEventListener("open", () => { $("link").textContent = ""; });
  events.addEventListener("error", () => { $("link").textContent = "Lost the live link to the daemon; reconnecting…"; });
  events.addEventListener("progress", (ev) => renderProgress(JSON.parse(ev.data)));
  events.addEventListener("devices", (ev) => {
    const d = JSON.parse(ev.data);
    renderDevices(Array.isArray(d) ? d : d.devices);
  });
  events.addEventListener("model", (ev) => {
    const m = JSON.parse(ev.data);
    const live = state.live;
    if (live.scanId !== m.scan_id) Object.assign(live, { scanId: m.scan_id, renders: 0, shown: null });
    state.shownScan = null;
    live.event = m;
    live.dirty = true;
    showLive();
  });
}

// ---- sign-in and start-up --------------------------------------------------------------------

/** Start every panel: the first answers, the camera stream, the event stream. */
function boot() {
  state.booted = true;
  loadStatus();
  loadMethods().then(loadHistory);
  loadControl();
  loadCamera();
  $("camera").src = "/api/v1/camera.mjpg";
  listen();
  setInterval(loadStatus, 15000);
}

/** Hide the console and ask for the daemon's token. */
function showSignIn() {
  $("console").hidden = true;
  $("sign-out").hidden = true;
  $("sign-in").hidden = false;
  $("rig").textContent = "Sign in to use this rig.";
  $("sign-in-token").focus();
}

$("sign-in-form").addEventListener("submit", (ev) => {
  ev.preventDefault();
  act($("sign-in-go"), $("sign-in-msg"), async () => {
    await post("/session", { token: $("sign-in-token").value });
    $("sign-in-token").value = "";
    // Signed in again after a lost session: start from a clean page.
    if (state.booted) return location.reload();
    $("sign-in").hidden = true;
    $("console").hidden = false;
    $("sign-out").hidden = false;
    boot();
  });
});

$("sign-out").addEventListener("click", async () => {
  await api("/session", { method: "DELETE" }).catch(() => {});
  location.reload();
});

(async function start() {
  let s = { required: false, authenticated: true };
  try {
    s = await getJson("/session");
  } catch (e) {
    $("rig").textContent = "Daemon unreachable: " + e.message;
  }
  if (s.required && !s.authenticated) return showSignIn();
  $("sign-out").hidden = !s.required;
  boot();
})();
