// scan3d status page: live state from /api/events, scans from /api/scans, a point-cloud view on a canvas.
// Plain browser JavaScript, no libraries: the appliance has no internet and serves only its own files.
"use strict";

const $ = (id) => document.getElementById(id);
const TOKEN_KEY = "scan3d-token";
let lastScanShown = "";
let statusTimer = null;
let boardRevision = -1;  // the newest board revision shown (the service counts one at every change)

// A reply to /api/status or /api/config may have been answered before a state event that arrived first,
// or after one still on its way (they travel on two connections): drawn out of order, an older copy would
// bring back what a newer one had cleared (a rejected edit already put right). Only a copy of the board
// at least as new as the one shown is drawn.
function isCurrent(revision) {
  if (typeof revision !== "number") return true;  // a service without revisions
  if (revision < boardRevision) return false;
  boardRevision = revision;
  return true;
}

function text(id, value) { $(id).textContent = value; }

function fmtMs(v) { return typeof v === "number" ? `${Math.round(v)} ms` : "–"; }

// camera-camera scans: {pixels, reconstructed, share} of the pixels both cameras see (empty otherwise)
function fmtBothSeen(b) {
  return b && typeof b.share === "number" ? `${(100 * b.share).toFixed(1)} %` : "–";
}

function bothSeenLine(b) {
  if (!b || typeof b.share !== "number") return "camera-camera: not measured (one camera, or mode projector)";
  return `camera-camera: ${(100 * b.share).toFixed(1)} % of the ${Number(b.pixels).toLocaleString()} pixels ` +
    `both cameras see got a point (${Number(b.reconstructed).toLocaleString()})`;
}

function pct(v) { return typeof v === "number" ? `${(100 * v).toFixed(1)} %` : "?"; }

// why the pixels of a scan have no point: per camera {reason: share of the image} (the sidecar's reason_shares;
// "decoded" is the share with a point, a zero share is left out), largest first
function reasonLines(reasons) {
  return Object.entries(reasons || {}).map(([cam, shares]) => {
    const rest = Object.entries(shares || {}).filter(([k, v]) => k !== "decoded" && typeof v === "number")
      .sort((a, b) => b[1] - a[1]).map(([k, v]) => `${k} ${pct(v)}`);
    return `${cam}: ${pct((shares || {}).decoded || 0)} with a point` + (rest.length ? `; ${rest.join(", ")}` : "");
  });
}

// a multi-exposure scan: {exposures_us, cameras: {cam: [{exposure_us, decoded_share, pixel_share}]}}
function hdrLine(hdr) {
  if (!hdr || !hdr.exposures_us || !hdr.exposures_us.length) return "";
  const cams = Object.entries(hdr.cameras || {}).map(([cam, passes]) =>
    `${cam} ` + passes.map((p) => `${p.exposure_us} µs ${pct(p.decoded_share)}`).join(", "));
  return `exposures ${hdr.exposures_us.join(", ")} µs; share of the decoded pixels each pass gave: ${cams.join("; ")}`;
}

function showFindings(scan) {
  const lines = reasonLines(scan.reasons);
  const apart = Object.entries(scan.separated || {}).map(([cam, v]) => `${cam} ${pct(v)}`);
  text("reasons", (lines.length ? `why pixels have no point (share of the image): ${lines.join(" | ")}` : "")
    + (apart.length ? ` | lit by two copies of the pattern (a mirror), the direct copy taken apart: ${apart.join(", ")}`
      : ""));
  const h = hdrLine(scan.hdr);
  $("hdr").hidden = !h;
  text("hdr", h);
  const ul = $("warnings");
  ul.replaceChildren();
  for (const w of scan.warnings || []) {
    const li = document.createElement("li");
    li.textContent = w;
    ul.append(li);
  }
  ul.hidden = !(scan.warnings || []).length;
}

function fmtTime(iso) {
  if (!iso) return "–";
  return iso.replace("T", " ").replace(/\.\d+/, "").replace(/\+00:00$/, "");
}

async function getJSON(url) {
  const r = await fetch(url, { cache: "no-store" });
  if (!r.ok) throw new Error(`${url}: HTTP ${r.status}`);
  return r.json();
}

// --- state -------------------------------------------------------------------------------------------

function showState(s) {
  const el = $("state");
  el.textContent = s.state;
  el.className = `state state-${s.state}`;
  let detail = s.detail || "";
  if (s.state === "starting" || s.state === "fault") detail = `${s.phase}${detail ? ": " + detail : ""}`;
  text("detail", detail);
  const c = s.counters || {};
  text("counters", `${c.scans_done ?? s.scans_done ?? 0} scans, ${c.scans_failed ?? 0} failed, ` +
       `${c.triggers_refused ?? 0} refused` + (s.queue_length ? `, ${s.queue_length} queued` : ""));
  if (s.serial) text("serial", s.serial);
  if (s.version) text("version", `v${s.version}`);
  showError(s.last_error);
  $("trigger").disabled = s.state !== "idle" && s.state !== "scanning" && s.state !== "processing" &&
    s.state !== "writing";
  if (!tuneRunning) $("tune").disabled = s.state !== "idle";
}

function showError(err) {
  const el = $("error");
  if (!err) { el.textContent = "none"; el.className = "muted"; text("advice", ""); return; }
  el.textContent = `${fmtTime(err.time_utc)} ${err.where}: ${err.message}`;
  el.className = "bad";
  text("advice", err.advice ? `What to do: ${err.advice}` : "");
}

function showShare(share) {
  const dl = $("share");
  dl.replaceChildren();
  const rows = Object.entries(share || {});
  if (!rows.length) { dl.textContent = "unknown"; return; }
  for (const [k, v] of rows) {
    const dt = document.createElement("dt");
    dt.textContent = k.replaceAll("_", " ");
    const dd = document.createElement("dd");
    dd.textContent = typeof v === "object" && v !== null ? JSON.stringify(v) : String(v);
    dl.append(dt, dd);
  }
}

async function refreshStatus() {
  try {
    const st = await getJSON("/api/status");
    if (!isCurrent(st.revision)) return;  // older than what is shown; a newer event is already drawn
    showState(st);
    showShare(st.share);
    showRejected(st.config ? st.config.error : "");
  } catch (e) { /* the event stream shows the link state */ }
}

function scheduleStatus() {  // at most one status request per second, however many events arrive
  if (statusTimer !== null) return;
  statusTimer = setTimeout(() => { statusTimer = null; refreshStatus(); }, 1000);
}

// --- scans -------------------------------------------------------------------------------------------

// calibration_health from the sidecar: {status: ok|drifting|bad|not measured, reason, checks: [{kind,
// residual_px, reference_px, limit_px, ...}]}; plotted as the largest residual (px) of the scan's checks.
function healthNumber(h) {
  if (typeof h === "number") return h;
  if (!h || typeof h !== "object" || h.status === "not measured") return null;
  const px = (h.checks || []).map((c) => c.residual_px).filter((v) => typeof v === "number");
  return px.length ? Math.max(...px) : null;
}

function healthLimit(h) {
  const lim = ((h && h.checks) || []).map((c) => c.limit_px).filter((v) => typeof v === "number");
  return lim.length ? Math.min(...lim) : null;
}

function healthLine(h) {
  if (!h) return "not measured";
  if (h.status === "not measured") return `not measured${h.reason ? ": " + h.reason : ""}`;
  const v = healthNumber(h), lim = healthLimit(h);
  return `${h.status}` + (v !== null ? `: largest residual ${v.toPrecision(3)} px` : "") +
    (lim !== null ? ` (limit ${lim.toPrecision(3)} px)` : "") + (h.reason ? ` — ${h.reason}` : "");
}

const HEALTH_COLOUR = { ok: "#3fb950", drifting: "#d29922", bad: "#f85149" };

function showScans(scans) {
  const body = $("scans");
  body.replaceChildren();
  if (!scans.length) {
    const tr = body.insertRow();
    const td = tr.insertCell();
    td.colSpan = 9; td.className = "muted"; td.textContent = "none yet";
  }
  for (const s of scans) {
    const t = s.timings_ms || {};
    const tr = body.insertRow();
    if (!s.ok) tr.className = "failed";
    const cells = [s.scan_id || "(refused)", fmtTime(s.started_utc), s.ok ? String(s.points) : s.error,
      fmtMs(t.trigger_to_file_ms), fmtMs(t.capture_ms), fmtMs(t.reconstruct_ms), fmtMs(t.write_ms),
      fmtBothSeen(s.both_seen), s.location || "–"];
    for (const c of cells) tr.insertCell().textContent = c;
  }
  const ok = scans.filter((s) => s.ok);
  drawHealth(ok.slice().reverse());
  if (ok.length) showLast(ok[0]);
}

function showLast(scan) {
  text("last-id", scan.scan_id);
  text("both-seen", bothSeenLine(scan.both_seen));
  showFindings(scan);
  if (scan.scan_id === lastScanShown) return;
  lastScanShown = scan.scan_id;
  const base = `/api/scans/${encodeURIComponent(scan.scan_id)}`;
  const img = $("preview");
  img.onload = () => { img.hidden = false; $("preview-none").hidden = true; };
  img.onerror = () => { img.hidden = true; $("preview-none").hidden = false; };
  img.src = `${base}/preview.png`;
  loadCloud(`${base}/cloud.bin`, scan);
}

let scansAsked = 0;

async function refreshScans() {
  const me = ++scansAsked;
  try {
    const data = await getJSON("/api/scans?limit=20");
    if (me === scansAsked) showScans(data.scans || []);  // an older answer arriving late is dropped
  } catch (e) { /* shown by the link state */ }
}

// --- calibration health plot ---------------------------------------------------------------------------

function drawHealth(scans) {
  const cv = $("health");
  const g = cv.getContext("2d");
  g.clearRect(0, 0, cv.width, cv.height);
  const pts = scans.map((s) => [Date.parse(s.started_utc), healthNumber(s.calibration_health), s.calibration_health])
    .filter((p) => p[1] !== null && !Number.isNaN(p[0]));
  const newest = scans.length ? scans[scans.length - 1].calibration_health : null;
  text("health-text", healthLine(newest));
  if (!pts.length) {
    g.fillStyle = "#8b98a5"; g.font = "14px sans-serif"; g.fillText("not measured", 12, cv.height / 2);
    return;
  }
  const xs = pts.map((p) => p[0]), ys = pts.map((p) => p[1]);
  const lim = healthLimit(pts[pts.length - 1][2]);
  const x0 = Math.min(...xs), x1 = Math.max(...xs);
  let y0 = 0, y1 = Math.max(...ys, lim !== null ? lim : 0);
  if (y1 - y0 < 1e-9) y1 = 1;
  y1 *= 1.1;
  const pad = 34, w = cv.width - 2 * pad, h = cv.height - 2 * pad;
  const X = (x) => pad + (x1 > x0 ? (x - x0) / (x1 - x0) : 0.5) * w;
  const Y = (y) => pad + h - ((y - y0) / (y1 - y0)) * h;
  g.strokeStyle = "#2b3642"; g.strokeRect(pad, pad, w, h);
  g.fillStyle = "#8b98a5"; g.font = "11px sans-serif";
  g.fillText(`${y1.toPrecision(2)} px`, 2, pad - 4); g.fillText("0", 2, pad + h);
  if (lim !== null) {  // the limit the calibration promised
    g.strokeStyle = "#f85149"; g.setLineDash([4, 4]); g.beginPath();
    g.moveTo(pad, Y(lim)); g.lineTo(pad + w, Y(lim)); g.stroke(); g.setLineDash([]);
    g.fillStyle = "#f85149"; g.fillText("limit", pad + w - 28, Y(lim) - 3);
  }
  g.strokeStyle = "#58a6ff"; g.lineWidth = 2; g.beginPath();
  pts.forEach((p, i) => (i ? g.lineTo(X(p[0]), Y(p[1])) : g.moveTo(X(p[0]), Y(p[1]))));
  g.stroke();
  for (const p of pts) {
    g.fillStyle = HEALTH_COLOUR[p[2].status] || "#58a6ff";
    g.beginPath(); g.arc(X(p[0]), Y(p[1]), 4, 0, 2 * Math.PI); g.fill();
  }
}

// --- point-cloud view (software rendering with a depth buffer) ------------------------------------------

const view = { xyz: null, center: [0, 0, 0], radius: 1, yaw: 0.5, pitch: -0.4, zoom: 1 };

async function loadCloud(url, scan) {
  try {
    const r = await fetch(url, { cache: "force-cache" });
    if (!r.ok) throw new Error(`HTTP ${r.status}`);
    const xyz = new Float32Array(await r.arrayBuffer());
    const n = xyz.length / 3;
    const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    for (let i = 0; i < n; i++) {
      for (let k = 0; k < 3; k++) {
        const v = xyz[3 * i + k];
        if (v < lo[k]) lo[k] = v;
        if (v > hi[k]) hi[k] = v;
      }
    }
    view.xyz = xyz;
    view.center = lo.map((v, k) => (v + hi[k]) / 2);
    view.radius = Math.max(1e-6, ...hi.map((v, k) => (v - lo[k]) / 2));
    view.lo = lo[2]; view.hi = hi[2];
    text("cloud-info", `${n.toLocaleString()} of ${Number(scan.points).toLocaleString()} points shown; drag to rotate`);
  } catch (e) {
    view.xyz = null;
    text("cloud-info", `no cloud (${e.message})`);
  }
  drawCloud();
}

function drawCloud() {
  const cv = $("cloud");
  const g = cv.getContext("2d");
  const W = cv.width, H = cv.height;
  const img = g.createImageData(W, H);
  const px = img.data;
  for (let i = 3; i < px.length; i += 4) { px[i - 3] = 11; px[i - 2] = 15; px[i - 1] = 20; px[i] = 255; }
  const xyz = view.xyz;
  if (xyz) {
    const depth = new Float32Array(W * H).fill(Infinity);
    const cy = Math.cos(view.yaw), sy = Math.sin(view.yaw), cp = Math.cos(view.pitch), sp = Math.sin(view.pitch);
    const s = (0.45 * Math.min(W, H) * view.zoom) / view.radius;
    const [mx, my, mz] = view.center;
    const zr = view.hi - view.lo || 1;
    for (let i = 0; i < xyz.length; i += 3) {
      const x = xyz[i] - mx, y = xyz[i + 1] - my, z = xyz[i + 2] - mz;
      const x1 = cy * x + sy * z, z1 = -sy * x + cy * z;       // yaw about y
      const y2 = cp * y - sp * z1, z2 = sp * y + cp * z1;      // pitch about x
      const u = Math.round(W / 2 + s * x1), v = Math.round(H / 2 + s * y2);  // camera y points down
      if (u < 0 || v < 0 || u >= W - 1 || v >= H - 1) continue;
      const t = (xyz[i + 2] - view.lo) / zr;                    // colour by distance from the camera
      const r = 90 + 165 * (1 - t), gr = 160 + 60 * (1 - t), b = 255 - 120 * t;
      for (let dv = 0; dv < 2; dv++) {
        for (let du = 0; du < 2; du++) {
          const k = (v + dv) * W + u + du;
          if (z2 < depth[k]) {
            depth[k] = z2;
            px[4 * k] = r; px[4 * k + 1] = gr; px[4 * k + 2] = b;
          }
        }
      }
    }
  }
  g.putImageData(img, 0, 0);
}

function setupCloudControls() {
  const cv = $("cloud");
  let drag = null;
  cv.addEventListener("pointerdown", (e) => { drag = [e.clientX, e.clientY]; cv.setPointerCapture(e.pointerId); });
  cv.addEventListener("pointermove", (e) => {
    if (!drag) return;
    view.yaw += (e.clientX - drag[0]) * 0.01;
    view.pitch = Math.max(-1.5, Math.min(1.5, view.pitch + (e.clientY - drag[1]) * 0.01));
    drag = [e.clientX, e.clientY];
    requestAnimationFrame(drawCloud);
  });
  const end = () => { drag = null; };
  cv.addEventListener("pointerup", end);
  cv.addEventListener("pointercancel", end);
  cv.addEventListener("wheel", (e) => {
    e.preventDefault();
    view.zoom = Math.max(0.2, Math.min(10, view.zoom * (e.deltaY < 0 ? 1.1 : 1 / 1.1)));
    requestAnimationFrame(drawCloud);
  }, { passive: false });
}

// --- configuration ------------------------------------------------------------------------------------

function showRejected(msg) {
  const el = $("rejected");
  el.hidden = !msg;
  el.textContent = msg ? `Last edit REJECTED (the last good configuration keeps running):\n${msg}` : "";
}

async function refreshConfig() {
  try {
    const c = await getJSON("/api/config");
    text("config-file", `${c.path} (loaded ${fmtTime(c.loaded_utc)})`);
    if (isCurrent(c.revision)) showRejected(c.rejected_edit);
    text("config", JSON.stringify(c.running, null, 2));
  } catch (e) { /* retried on the next state event */ }
}

// --- trigger ------------------------------------------------------------------------------------------

function askToken() {  // the token for writes from this page, asked once and remembered
  let token = localStorage.getItem(TOKEN_KEY);
  if (!token) {
    token = window.prompt("Token for scans from this page (the content of service.http.token_file):");
    if (!token) return null;
    localStorage.setItem(TOKEN_KEY, token.trim());
    token = token.trim();
  }
  $("forget").hidden = false;
  return token;
}

async function trigger() {
  const token = askToken();
  if (!token) return;
  text("trigger-result", "…");
  try {
    const r = await fetch("/api/trigger", { method: "POST", headers: { Authorization: `Bearer ${token}` } });
    const body = await r.json().catch(() => ({}));
    if (r.status === 401) {
      localStorage.removeItem(TOKEN_KEY);
      text("trigger-result", "wrong token (asked again on the next press)");
      return;
    }
    text("trigger-result", body.ok ? `scan ${body.result}` : (body.error || `HTTP ${r.status}`));
  } catch (e) {
    text("trigger-result", `no answer: ${e.message}`);
  }
}

// --- tune (the capture assistant) ----------------------------------------------------------------------

let tuneRunning = false;
let tuneChoice = null;  // the exposures (µs) of the last tune shown: what Apply writes

async function postTune(url, init) {  // {status, body}; a 401 forgets the token
  const token = askToken();
  if (!token) return null;
  const r = await fetch(url, { method: "POST", ...init,
    headers: { Authorization: `Bearer ${token}`, ...((init && init.headers) || {}) } });
  const body = await r.json().catch(() => ({}));
  if (r.status === 401) localStorage.removeItem(TOKEN_KEY);
  return { status: r.status, body };
}

async function tune() {
  const budget = Number($("tune-budget").value) || 2000;
  tuneRunning = true; $("tune").disabled = true; $("tune-apply").hidden = true; tuneChoice = null;
  text("tune-status", `probing the scene (budget ${budget} ms)…`);
  try {
    const res = await postTune(`/api/tune?time_budget_ms=${encodeURIComponent(budget)}`);
    if (!res) { text("tune-status", "no token"); return; }
    if (res.status === 401) { text("tune-status", "wrong token (asked again on the next press)"); return; }
    if (!res.body.ok) { text("tune-status", res.body.error || `HTTP ${res.status}`); return; }
    const t = res.body.tune;
    $("tune-result").hidden = false;
    text("tune-result", (t.lines || []).join("\n"));
    tuneChoice = t.choice.exposures_us;
    const dimmed = (t.choice.intensities || []).length ?
      ` and sequence.intensities = [${t.choice.intensities.join(", ")}]` : "";
    text("tune-status", `probed in ${Math.round(t.probe_ms)} ms; Apply writes sequence.exposures_us = ` +
      `[${tuneChoice.join(", ")}]${dimmed} into the configuration file (validated, then reloaded)`);
    $("tune-apply").hidden = false;
  } catch (e) {
    text("tune-status", `no answer: ${e.message}`);
  } finally {
    tuneRunning = false;
    $("tune").disabled = $("state").textContent !== "idle";
  }
}

async function applyTune() {
  if (!tuneChoice) return;
  text("tune-status", "writing and reloading…");
  try {
    const res = await postTune("/api/tune/apply", { body: JSON.stringify({ exposures_us: tuneChoice }),
      headers: { "Content-Type": "application/json" } });
    if (!res) return;
    if (res.body.ok) {
      const a = res.body.applied;
      const dimmed = (a.intensities || []).length ? `, sequence.intensities = [${a.intensities.join(", ")}]` : "";
      text("tune-status", `applied: ${a.path}: sequence.exposures_us = [${a.exposures_us.join(", ")}]${dimmed}; ` +
        "reloaded");
      $("tune-apply").hidden = true;
    } else {
      text("tune-status", res.body.error || `HTTP ${res.status}`);
    }
  } catch (e) {
    text("tune-status", `no answer: ${e.message}`);
  }
}

// --- live updates -------------------------------------------------------------------------------------

function connectEvents() {
  const link = $("link");
  const es = new EventSource("/api/events");
  es.onopen = () => {  // perhaps a restarted service, counting revisions from 0 again
    boardRevision = -1;
    link.textContent = "live"; link.className = "link on"; refreshScans(); refreshStatus();
  };
  es.onerror = () => { link.textContent = "reconnecting"; link.className = "link off"; };
  es.addEventListener("state", (e) => {
    const s = JSON.parse(e.data);
    if (s.last_scan_id && s.last_scan_id !== $("last-id").textContent) refreshScans();
    scheduleStatus();
    if (!isCurrent(s.revision)) return;  // a newer copy of the board (from /api/status) is drawn already
    showState(s);
    showRejected(s.config_error);
  });
  es.addEventListener("scan", (e) => {
    const scan = JSON.parse(e.data);
    if (scan.ok) showLast(scan);  // at once, from the event; the table follows from /api/scans
    refreshScans(); scheduleStatus(); refreshConfig();
  });
}

document.addEventListener("DOMContentLoaded", () => {
  $("trigger").addEventListener("click", trigger);
  $("tune").addEventListener("click", tune);
  $("tune-apply").addEventListener("click", applyTune);
  $("forget").addEventListener("click", () => { localStorage.removeItem(TOKEN_KEY); $("forget").hidden = true; });
  $("forget").hidden = !localStorage.getItem(TOKEN_KEY);
  setupCloudControls();
  drawCloud();
  refreshStatus();
  refreshScans();
  refreshConfig();
  connectEvents();
});
