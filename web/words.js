// Human words for what the daemon reports in codes: statuses, stages, methods, device states,
// error codes, durations and figures. Every text the page shows about a scan goes through here.

const STATUS = {
  running: "Scanning",
  paused: "Paused",
  complete: "Finished",
  failed: "Failed",
  cancelled: "Cancelled",
  interrupted: "Interrupted (can be resumed)",
};

const METHOD = {
  "space-carving": "Silhouette carving",
  "shadow-carving": "Shadow carving",
  "voxel-coloring": "Voxel colouring",
  "space-carving-photo": "Photo-consistent carving",
  "depth-fusion": "Depth camera fusion",
  laser: "Laser line",
  "structured-light": "Structured light",
};

const DEVICE_STATE = {
  connected: "Connected",
  disconnected: "Disconnected",
  reconnecting: "Reconnecting…",
  failed: "Failed",
};

const ERROR = {
  scan_running: "Refused: a scan is running. Manual control comes back when it ends.",
  busy: "Refused: another scan is running.",
  wrong_state: "Refused: the scan is not in a state that allows this.",
  not_found: "Not found.",
  unauthorized: "Refused: this daemon needs an access token; sign in again.",
  wrong_token: "That is not this daemon's access token.",
  cross_origin: "Refused: the console session may only be used from the rig's own page.",
  disconnected: "The device is not connected.",
  timeout: "The rig did not answer in time.",
};

/** "Finished", "Scanning"... for a scan status code (the code itself if unknown). */
export function statusWords(status) {
  return STATUS[status] || (status ? String(status) : "Idle");
}

/** "Silhouette carving"... for a method name. */
export function methodWords(method) {
  return METHOD[method] || String(method || "");
}

/** "Connected"... for a device state. */
export function deviceStateWords(state) {
  return DEVICE_STATE[state] || String(state || "unknown");
}

/** A sentence for an API error: the server's message, led by what the code means. */
export function errorWords(code, message, httpStatus) {
  const known = ERROR[code];
  if (known && message && !known.includes(message)) return known + " (" + message + ")";
  if (known) return known;
  if (message) return message.charAt(0).toUpperCase() + message.slice(1);
  return "The daemon answered " + httpStatus + ".";
}

/** "about 1 min 20 s" for seconds. */
export function durationWords(s) {
  if (s == null || !isFinite(s)) return "";
  s = Math.max(0, Math.round(s));
  if (s < 60) return s + " s";
  const m = Math.floor(s / 60), r = s % 60;
  if (m < 60) return m + " min" + (r ? " " + r + " s" : "");
  return Math.floor(m / 60) + " h " + (m % 60) + " min";
}

/** A progress line in words: "Scanning: position 3 of 8, capturing. About 12 s left." */
export function progressWords(p) {
  if (!p || !p.scan_id) return "Idle: no scan has run since the daemon started.";
  let line = statusWords(p.status);
  const msg = (p.message || "").trim();
  // A finished scan's message is its stage ("complete"), which repeats the status: say it once.
  const repeats = msg === p.status || (p.status !== "running" && msg === p.stage);
  if (msg && !repeats) line += ": " + msg;
  if (p.status === "running" && p.remaining_s != null) line += ". About " + durationWords(p.remaining_s) + " left";
  if (p.total && ["paused", "cancelled", "failed", "interrupted"].includes(p.status))
    line += " after view " + Math.min(p.step, p.total) + " of " + p.total;
  if (p.status === "complete" && p.elapsed_s) line += " in " + durationWords(p.elapsed_s);
  else if (p.status !== "running" && p.elapsed_s) line += " (" + durationWords(p.elapsed_s) + " of scanning)";
  return line + ".";
}

/** A date in the reader's locale, e.g. "2 Dec 2026, 00:31". */
export function dateWords(unixSeconds, rfc3339) {
  const d = rfc3339 ? new Date(rfc3339) : new Date((unixSeconds || 0) * 1000);
  if (isNaN(d)) return "";
  return d.toLocaleString(undefined, { dateStyle: "medium", timeStyle: "short" });
}

/** Figures from a scan report, as short phrases ("8 views", "volume 61.2 cm³"...). */
export function figureWords(r) {
  if (!r) return [];
  const out = [];
  if (r.views != null) out.push(r.views + " views");
  if (r.volume_m3 != null && r.volume_m3 > 0) out.push("volume " + (r.volume_m3 * 1e6).toFixed(1) + " cm³");
  if (r.mesh_triangles != null) out.push(r.mesh_triangles.toLocaleString() + " triangles");
  if (r.points != null) out.push(r.points.toLocaleString() + " points");
  if (r.voxel_size_m != null) out.push("voxel " + (r.voxel_size_m * 1000).toFixed(2) + " mm");
  if (r.reprojection_iou_mean != null && r.reprojection_iou_mean > 0)
    out.push("silhouette agreement " + (100 * r.reprojection_iou_mean).toFixed(1) + " %");
  if (r.iou != null) out.push("overlap with the true shape " + (100 * r.iou).toFixed(1) + " %");
  if (r.chamfer_rel != null) out.push("shape error " + (100 * r.chamfer_rel).toFixed(2) + " % of size");
  if (r.total_s != null) out.push("took " + durationWords(r.total_s));
  return out;
}
