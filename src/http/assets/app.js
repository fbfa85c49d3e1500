// The crispen dashboard: live state from /api/v1/events, actions and uploads through the
// JSON API. The API key (when the daemon wants one) is kept in this browser's storage and
// sent as X-Api-Key, as every other client does.
"use strict";

const $ = (sel) => document.querySelector(sel);
let key = localStorage.getItem("crispen-key") || "";
let last = null;
const pictureCache = new Map(); // url -> blob URL
// Cameras: printer -> { state, error, frame_at, shown (frame_at shown), url (blob URL) }.
const cameras = new Map();

function headers(extra) {
  const h = Object.assign({}, extra || {});
  if (key) h["X-Api-Key"] = key;
  return h;
}

function esc(text) {
  return String(text == null ? "" : text).replace(/[&<>"']/g, (c) =>
    ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" })[c]);
}

function notice(text, bad) {
  const n = $("#notice");
  n.textContent = text;
  n.className = bad ? "bad" : "good";
  n.hidden = !text;
  clearTimeout(notice.timer);
  if (text) notice.timer = setTimeout(() => { n.hidden = true; }, 6000);
}

function askForKey(message) {
  $("#keyform").hidden = false;
  notice(message, true);
}

// The key can be entered before any action asks for it (the daemon's read-only mode
// shows the farm without one); the button says whether this browser holds one.
function showKeyState() {
  $("#keybutton").textContent = key ? "Key ✓" : "Key";
}
$("#keybutton").addEventListener("click", () => {
  $("#keyform").hidden = !$("#keyform").hidden;
  if (!$("#keyform").hidden) $("#key").focus();
});
showKeyState();

$("#keyform").addEventListener("submit", (e) => {
  e.preventDefault();
  key = $("#key").value.trim();
  localStorage.setItem("crispen-key", key);
  showKeyState();
  $("#keyform").hidden = true;
  notice("");
  connect();
  route();
});

async function api(method, path, body) {
  const r = await fetch(path, { method, headers: headers(), body });
  let answer = {};
  try { answer = await r.json(); } catch (_) { /* not JSON */ }
  if (r.status === 401 || r.status === 403) askForKey(answer.error || "API key needed");
  if (!r.ok) throw new Error(answer.error || (method + " " + path + ": HTTP " + r.status));
  return answer;
}

// Pictures are fetched with the key and shown from blob URLs.
function picture(url, alt, cls) {
  const cached = pictureCache.get(url);
  const img = '<img class="' + (cls || "") + '" alt="' + esc(alt) + '" data-src="' + esc(url) + '"' +
    (cached ? ' src="' + cached + '"' : "") + ">";
  return img;
}

function loadPictures(root) {
  root.querySelectorAll("img[data-src]:not([src])").forEach(async (img) => {
    const url = img.dataset.src;
    if (pictureCache.has(url)) { img.src = pictureCache.get(url); return; }
    try {
      const r = await fetch(url, { headers: headers() });
      if (!r.ok) { img.remove(); return; }
      const blob = URL.createObjectURL(await r.blob());
      pictureCache.set(url, blob);
      img.src = blob;
    } catch (_) { img.remove(); }
  });
}

function temp(cur, target) {
  if (cur == null) return "–";
  return Math.round(cur) + (target ? " / " + Math.round(target) : "") + " °C";
}

function duration(s) {
  if (s == null || !isFinite(s)) return "";
  s = Math.max(0, Math.round(s));
  const h = Math.floor(s / 3600), m = Math.floor((s % 3600) / 60), sec = s % 60;
  return h ? h + " h " + String(m).padStart(2, "0") + " min" : m ? m + " min" : sec + " s";
}

// What a print's time left rests on: the firmware's planner over the lines not yet
// acknowledged, with the printer's settings or the machine's, at the printer's pace on its
// earlier prints.
function timeLeftBasis(t) {
  if (!t) return "";
  const pace = t.pace.prints
    ? " × " + t.pace.factor.toFixed(2) + ", this printer's pace over its last " + (t.pace.prints === 1 ? "print" : t.pace.prints + " prints")
    : " (no finished print on this printer yet to correct it)";
  const settings = t.settings === "printer" ? " with the printer's own settings (M503)" : " with the machine's stock settings";
  return "the planner's " + duration(t.planned_s) + settings + pace + (t.heating ? "; the heat-up's own time on top" : "");
}

function label(state) { return String(state).replace(/_/g, " "); }

function jobOf(status, id) { return status.jobs.find((j) => j.id === id); }

function printerTile(p, status) {
  const job = p.job ? jobOf(status, p.job) : null;
  const live = p.progress || null;
  const pct = live && live.lines_total ? (100 * live.lines_acked / live.lines_total) : null;
  let html = '<article class="tile state-' + esc(p.state) + '" data-printer="' + esc(p.name) + '">';
  html += '<div class="head"><h3>' + esc(p.name) + '</h3><span class="state">' + esc(label(p.state)) + "</span></div>";
  const shown = job || (!p.bed_cleared && status.jobs.filter((j) => j.printer === p.name).slice(-1)[0]);
  if (shown && shown.pictures.includes("after.png")) {
    html += picture("/api/v1/jobs/" + encodeURIComponent(shown.id) + "/pictures/after.png", shown.file, "part");
  }
  html += cameraView(p.name);
  html += '<div class="job">' + (job ? '<a href="#job/' + esc(job.id) + '">' + esc(job.file) + "</a>" : '<span class="muted">no job</span>') + "</div>";
  if (pct != null) {
    // A <progress> element: the page's policy allows no inline styles.
    html += '<progress class="bar" max="100" value="' + pct.toFixed(1) + '"></progress>';
    html += '<div class="figures"><span class="pct">' + pct.toFixed(1) + " %</span>" +
      (live.remaining_s != null ? '<span class="left" title="' + esc(timeLeftBasis(live.time_left)) + '">' + duration(live.remaining_s) + " left" +
        (live.time_left && live.time_left.heating ? " + heat-up" : "") + "</span>" : "") + "</div>";
  }
  // Current temperatures, printing or idle; none while the daemon cannot read them.
  const t = p.temperatures;
  if (t) {
    html += '<div class="temps"><span>Hotend <b>' + temp(t.hotend_c, t.hotend_target_c) + "</b></span>" +
      "<span>Bed <b>" + temp(t.bed_c, t.bed_target_c) + "</b></span></div>";
  }
  html += holdsLine(p.holds);
  html += careView(p);
  html += bedView(p);
  if (p.detail) html += '<div class="detail">' + esc(p.detail) + "</div>";
  html += '<div class="actions">';
  if (!p.bed_cleared && p.bed.state !== "ejecting") html += '<button class="clear" data-action="clear" data-printer="' + esc(p.name) + '">Bed is clear</button>';
  if (cameras.has(p.name) && p.state !== "printing" && p.state !== "ejecting") html += '<button class="reference" data-action="reference" data-printer="' + esc(p.name) + '" title="take the camera\'s picture now as the empty bed the check compares with">New reference</button>';
  if (p.state === "printing") html += '<button data-action="pause" data-printer="' + esc(p.name) + '">Pause</button>';
  if (p.state === "paused" || p.state === "waiting_for_operator") html += '<button data-action="resume" data-printer="' + esc(p.name) + '">Resume</button>';
  // This printer's print only: of a job with copies, the copy it prints.
  if (job && (p.state === "printing" || p.state === "paused" || p.state === "waiting_for_operator")) html += '<button class="danger" data-action="cancel" data-job="' + esc(job.id) + '" data-copy="' + (job.copy ? job.copy.n : 1) + '">Cancel</button>';
  // A spool is changed between prints (a print's filament is booked to the spool it began with).
  if (p.holds && !job) {
    html += '<button class="spool" data-spool-printer="' + esc(p.name) + '">Load spool</button>';
    if (!p.holds.unloaded && (p.holds.spool || p.holds.filament)) html += '<button data-action="unload" data-printer="' + esc(p.name) + '">Unload</button>';
  }
  if (p.switchable && p.state === "off") html += '<button data-action="poweron" data-printer="' + esc(p.name) + '">Power on</button>';
  if (p.switchable && p.state === "idle") html += '<button data-action="poweroff" data-printer="' + esc(p.name) + '" title="only once its hotend is cool; it is switched on again when it has work">Power off</button>';
  if (!p.offline) {
    html += p.held
      ? '<button data-action="careend" data-printer="' + esc(p.name) + '">End maintenance</button>'
      : '<button data-action="carestart" data-printer="' + esc(p.name) + '" title="it finishes its print, then takes no job until maintenance ends">Maintenance</button>';
  }
  html += "</div></article>";
  return html;
}

// One interval of a maintenance task: "1.2 of 2 kg".
const CARE_UNITS = { print_hours: "print hours", kg: "kg", abrasive_kg: "kg abrasive", jobs: "prints", days: "days" };
function careInterval(i) {
  return (Math.round(i.used * 10) / 10) + " of " + i.every + " " + (CARE_UNITS[i.measure] || i.measure);
}

// A printer's due maintenance tasks, each with its intervals and a button to record it done.
function careView(p) {
  const due = (p.maintenance || []).filter((t) => t.due);
  if (!due.length) return "";
  let html = '<ul class="care">';
  for (const t of due) {
    const reached = t.intervals.filter((i) => i.used >= i.every).map(careInterval).join(", ");
    html += '<li class="' + (t.block ? "blocking" : "due") + '">' + esc(t.task) + " due: " + esc(reached) +
      ' <button data-action="caredone" data-printer="' + esc(p.name) + '" data-task="' + esc(t.task) + '">Done</button></li>';
  }
  return html + "</ul>";
}

// A printer's bed when its camera found it not clear: the marked picture and the figures.
function bedView(p) {
  const why = p.bed && p.bed.state === "waiting" && p.bed.why;
  if (!why || why.kind !== "not_clear") return "";
  const check = why.check;
  let html = '<div class="bedcheck">';
  if (check.picture) {
    const file = check.picture.split("/").pop();
    html += picture("/api/v1/printers/" + encodeURIComponent(p.name) + "/bed/" + encodeURIComponent(file), "bed check of " + p.name, "marked");
  }
  html += '<div class="verdict">' + esc(checkSummary(check.verdict)) + "</div></div>";
  return html;
}

// A check's answer in words, as the daemon says it ("not clear: 6.1 % of the bed differs, ...").
function checkSummary(v) {
  if (v.unsure && !v.patches.length) return "not clear: cannot tell, the picture is too dark or noisy";
  let text = (v.clear ? "clear" : "not clear") + ": " + v.differs_percent.toFixed(1) + " % of the bed differs";
  const largest = v.patches[0];
  if (largest) {
    text += largest.size_mm ? ", largest patch " + largest.size_mm[0].toFixed(0) + " × " + largest.size_mm[1].toFixed(0) + " mm"
      : ", largest patch " + largest.w + " × " + largest.h + " px";
    if (v.patches.length > 1) text += " (" + v.patches.length + " patches)";
  }
  return text;
}

// A job's prints cleared off the bed by machine: each eject and camera check.
function clearingSection(id, steps) {
  if (!steps || !steps.length) return "";
  let html = '<h3>Clearing the bed</h3><ol class="clearing" id="clearing">';
  for (const s of steps) {
    if (s.step === "eject") {
      html += "<li>Eject sequence on " + esc(s.printer) + " " + new Date(s.started_s * 1000).toLocaleTimeString() + ", " +
        duration(s.ended_s - s.started_s) + ": " + (s.error ? '<span class="reason">failed: ' + esc(s.error) + "</span>" : "done") + "</li>";
    } else if (s.step === "check") {
      const c = s.check;
      html += '<li>Camera check on ' + esc(s.printer) + " " + new Date(c.at_s * 1000).toLocaleTimeString() + ': <b class="' +
        (c.verdict.clear ? "ok" : "reason") + '">' + esc(checkSummary(c.verdict)) + "</b>";
      if (c.picture && c.picture.startsWith("camera/")) {
        html += "<figure>" + picture("/api/v1/jobs/" + encodeURIComponent(id) + "/camera/" + encodeURIComponent(c.picture.split("/").pop()), "bed check", "marked") +
          "<figcaption>The bed as the camera saw it, what differs from the empty bed boxed in red</figcaption></figure>";
      }
      html += "</li>";
    }
  }
  return html + "</ol>";
}

// A printer's camera on its tile: its latest picture (a click opens the live view) and,
// when it gives none, why.
function cameraView(name) {
  const c = cameras.get(name);
  if (!c) return "";
  let html = '<a class="camera" href="#camera/' + encodeURIComponent(name) + '" title="live view">';
  html += c.url ? '<img class="cam" data-camera="' + esc(name) + '" alt="camera of ' + esc(name) + '" src="' + c.url + '">' :
    '<span class="cam none">no picture</span>';
  html += "</a>";
  if (c.state !== "online") {
    html += '<div class="camstate cam-' + esc(c.state) + '">camera ' + esc(c.state) + (c.error ? ": " + esc(c.error) : "") + "</div>";
  }
  return html;
}

// Each camera's picture is fetched only when the camera has a new frame.
async function refreshCameras() {
  let list;
  try { list = await api("GET", "/api/v1/cameras"); } catch (_) { return; }
  let changed = false;
  for (const s of list) {
    const c = cameras.get(s.printer) || {};
    if (c.state !== s.state || c.error !== s.error) changed = true;
    Object.assign(c, { state: s.state, error: s.error, frame_at: s.frame_at });
    cameras.set(s.printer, c);
    if (s.frame_at != null && s.frame_at !== c.shown) {
      try {
        const r = await fetch("/api/v1/printers/" + encodeURIComponent(s.printer) + "/snapshot", { headers: headers() });
        if (r.ok) {
          const url = URL.createObjectURL(await r.blob());
          if (c.url) URL.revokeObjectURL(c.url);
          if (!c.url) changed = true;
          c.url = url;
          c.shown = s.frame_at;
          document.querySelectorAll('img.cam[data-camera="' + CSS.escape(s.printer) + '"]').forEach((img) => { img.src = url; });
        }
      } catch (_) { /* the next round tries again */ }
    }
  }
  if (changed && last) render(last);
}

// The live view: the printer's picture as often as its camera gives a new one.
async function showCamera(name) {
  const page = $("#jobpage");
  page.innerHTML = '<p><a href="#">← farm</a></p><h2>Camera of ' + esc(name) + '</h2>' +
    '<img id="live" class="live" alt="live view of ' + esc(name) + '"><p class="muted" id="livestate"></p>';
  const token = showCamera.token = {};
  let shown = null;
  while (showCamera.token === token && location.hash === "#camera/" + encodeURIComponent(name)) {
    try {
      const r = await fetch("/api/v1/printers/" + encodeURIComponent(name) + "/snapshot", { headers: headers() });
      if (r.ok) {
        const at = r.headers.get("x-frame-time");
        if (at !== shown) {
          shown = at;
          const img = $("#live");
          const old = img.src;
          img.src = URL.createObjectURL(await r.blob());
          if (old) URL.revokeObjectURL(old);
          $("#livestate").textContent = "frame of " + new Date(1000 * at).toLocaleTimeString();
        }
      } else {
        const answer = await r.json().catch(() => ({}));
        $("#livestate").textContent = answer.error || ("HTTP " + r.status);
      }
    } catch (err) { $("#livestate").textContent = err.message; }
    await new Promise((ok) => setTimeout(ok, 1000));
  }
}

// A filament's colour as a swatch: an SVG fill (the page's policy allows no inline styles).
function swatch(f) {
  const hex = f && f.colour_hex && /^[0-9a-fA-F]{6}$/.test(f.colour_hex) ? "#" + f.colour_hex : null;
  const fill = hex || NAMED[f && f.colour] || "#9aa3ad";
  return '<svg class="swatch" width="14" height="14" viewBox="0 0 14 14" aria-hidden="true"><circle cx="7" cy="7" r="6" fill="' + fill + '" stroke="#0004"/></svg>';
}
const NAMED = { black: "#111111", white: "#f4f4f4", grey: "#8a8a8a", silver: "#c0c0c0", red: "#c81e1e",
  orange: "#ff8200", yellow: "#fadc00", green: "#1ea03c", blue: "#1e50c8", purple: "#7832a0", pink: "#f078aa", brown: "#78461e" };

function grams(g) { return g == null ? "?" : Math.round(g) + " g"; }

// What a printer holds: its filament and spool (what is left, what its print takes), its nozzle.
function holdsLine(h) {
  if (!h) return "";
  let text;
  if (h.unloaded) text = '<span class="warn">nothing loaded</span>';
  else if (!h.filament) text = '<span class="muted">filament not known</span>';
  else {
    const f = h.filament;
    text = swatch(f) + " <b>" + esc(f.material) + " " + esc(f.colour) + "</b>";
    if (h.spool) text += ' <span class="muted">' + esc(h.spool) + "</span> · " + grams(h.remaining_g) + " left";
    if (h.reserved_g) text += " · " + grams(h.reserved_g) + " for this print";
  }
  const nozzle = h.nozzle_mm + " mm " + (h.hardened ? "hardened" : "brass") + (h.tags && h.tags.length ? " · " + esc(h.tags.join(", ")) : "");
  return '<div class="holds">' + text + '</div><div class="nozzle muted">' + nozzle + "</div>";
}

// The "load a spool" panel: a spool the farm knows (not on another printer), or a new one.
async function openLoad(printer) {
  const form = $("#loadform");
  form.dataset.printer = printer;
  $("#loadtitle").textContent = "Load a spool on " + printer;
  let list = { spools: [], source: "crispen" };
  try { list = await api("GET", "/api/v1/spools"); } catch (err) { notice(err.message, true); }
  const free = list.spools.filter((s) => !s.loaded_on || s.loaded_on === printer);
  $("#loadspool").innerHTML = '<option value="">' + (free.length ? "a new spool…" : "no spool free: a new one") + "</option>" +
    free.map((s) => '<option value="' + esc(s.id) + '">' + esc(s.id + " · " + s.material + " " + s.colour +
      (s.remaining_g != null ? " · " + Math.round(s.remaining_g) + " g" : "") + (s.brand ? " · " + s.brand : "")) + "</option>").join("");
  // Spoolman's spools are added in Spoolman: only those are loaded here.
  openLoad.spoolman = list.source === "spoolman";
  $("#loadspool").required = openLoad.spoolman;
  $("#newspool").hidden = openLoad.spoolman;
  form.hidden = false;
}

$("#loadspool").addEventListener("change", () => {
  $("#newspool").hidden = !!$("#loadspool").value || openLoad.spoolman;
});

$("#loadcancel").addEventListener("click", () => { $("#loadform").hidden = true; });

$("#loadform").addEventListener("submit", async (e) => {
  e.preventDefault();
  const form = $("#loadform");
  const q = new URLSearchParams();
  if ($("#loadspool").value) q.set("spool", $("#loadspool").value);
  else for (const k of ["material", "colour", "grams", "price_per_kg"]) {
    const v = form.elements[k].value.trim();
    if (v) q.set(k, v);
  }
  try {
    const answer = await api("POST", "/api/v1/printers/" + encodeURIComponent(form.dataset.printer) + "/load?" + q);
    notice(answer.message || "loaded");
    form.hidden = true;
  } catch (err) {
    notice(err.message, true);
  }
});

function strengthText(s) {
  if (s == null) return "–";
  if (typeof s === "string") return s;
  if (s.lambda2 != null) return "λ2 " + s.lambda2;
  return JSON.stringify(s);
}

const ORDER = ["printing", "ready", "preparing", "queued", "failed", "interrupted", "cancelled", "done"];

function queueTable(status) {
  const jobs = status.jobs.slice().sort((a, b) =>
    ORDER.indexOf(a.state) - ORDER.indexOf(b.state) || b.updated - a.updated);
  if (!jobs.length) return '<p class="muted">No jobs yet: drop a model on a hot folder.</p>';
  let html = '<table><thead><tr><th>File</th><th>State</th><th>Height</th><th>Strength</th><th>Printer</th><th></th></tr></thead><tbody>';
  for (const j of jobs) {
    const live = j.progress;
    let extra = "";
    if (j.step) extra = j.step;
    else if (live && live.lines_total) extra = (100 * live.lines_acked / live.lines_total).toFixed(1) + " %";
    html += '<tr data-job="' + esc(j.id) + '" class="job-' + esc(j.state) + '">' +
      '<td><a href="#job/' + esc(j.id) + '">' + esc(j.file) + '</a><div class="muted">' + esc(j.folder_name) + "</div>" +
      (j.copy ? '<div class="muted">copy ' + j.copy.n + " of " + j.copies + "</div>" : "") +
      (j.copies_status ? '<div class="copies">' + esc(copiesText(j.copies_status)) + "</div>" : "") +
      (j.reason ? '<div class="reason">' + esc(j.reason) + "</div>" : "") +
      (j.waiting ? '<div class="waiting">' + esc(j.waiting) + "</div>" : "") + "</td>" +
      '<td><span class="pill s-' + esc(j.state) + '">' + esc(j.state) + "</span> " + (j.held ? '<span class="pill held">held</span> ' : "") +
      (j.asks && j.asks.priority ? '<span class="pill prio">priority ' + esc(j.asks.priority) + "</span> " : "") + esc(extra) +
      (asksText(j.asks) ? '<div class="muted">' + esc(asksText(j.asks)) + "</div>" : "") + "</td>" +
      "<td>" + (j.height_mm != null ? j.height_mm + " mm" : "–") + "</td>" +
      "<td>" + esc(strengthText(j.strength)) + "</td>" +
      "<td>" + esc(j.printer || j.machines.join(", ")) + "</td><td>";
    html += jobButtons(j) + "</td></tr>";
  }
  return html + "</tbody></table>";
}

// How a job's copies stand, in words: "3 of 6 printed, 2 printing on a, c, 1 waiting".
function copiesText(c) {
  let text = c.printed + " of " + c.total + " printed";
  if (c.printing.length) text += ", " + c.printing.length + " printing on " + c.printing.join(", ");
  if (c.waiting) text += ", " + c.waiting + " waiting";
  if (c.stopped) text += ", " + c.stopped + " stopped";
  return text;
}

// What a job asks of its printer, in words.
function asksText(a) {
  if (!a) return "";
  const parts = [];
  const f = [a.material, a.colour].filter(Boolean).join(" ");
  if (f) parts.push(f);
  if (a.nozzle_mm) parts.push(a.nozzle_mm + " mm nozzle");
  if (a.tags && a.tags.length) parts.push("group " + a.tags.join("+"));
  return parts.join(" · ");
}

// A job's actions: a held job (uploaded without "print") waits for its Print button.
function jobButtons(j) {
  let html = "";
  if (j.held && ["queued", "preparing", "ready"].includes(j.state)) html += '<button class="release" data-action="release" data-job="' + esc(j.id) + '">Print</button>';
  if (["queued", "preparing", "ready", "printing"].includes(j.state)) html += '<button class="danger" data-action="cancel" data-job="' + esc(j.id) + '">Cancel</button>';
  if (["failed", "cancelled", "interrupted"].includes(j.state)) html += '<button data-action="retry" data-job="' + esc(j.id) + '">Retry</button>';
  return html;
}

function folderZones(status) {
  return status.folders.map((f) =>
    '<label class="folder" data-folder="' + esc(f.name) + '"><b>' + esc(f.name) + "</b>" +
    "<span>" + f.height_mm + " mm · " + esc(strengthText(f.strength)) + " · " + esc(f.printers.join(", ")) + "</span>" +
    '<span class="muted">' + f.queued + " waiting · drop or tap to upload</span>" +
    '<input type="file" accept=".stl,.obj,.3mf,.gcode,.toml" hidden></label>').join("");
}

function render(status) {
  last = status;
  const printing = status.printers.filter((p) => p.state === "printing").length;
  $("#summary").textContent = printing + "/" + status.printers.length + " printing · " +
    status.jobs.filter((j) => ["queued", "preparing", "ready"].includes(j.state)).length + " waiting";
  patch($("#printers"), status.printers.map((p) => printerTile(p, status)).join("") ||
    '<p class="muted">No printers configured.</p>');
  if (!$("#folders").dataset.busy) patch($("#folders"), folderZones(status));
  sendToOptions(status);
  patch($("#queue"), queueTable(status));
  loadPictures($("#farm"));
  // The job page open gains its comparison (measured after the job is ready) when it is made.
  const open = location.hash.match(/^#job\/(.+)$/);
  if (open) {
    const job = status.jobs.find((j) => j.id === decodeURIComponent(open[1]));
    const comparison = JSON.stringify(job && job.comparison);
    if (job && render.comparison !== undefined && render.comparison !== comparison) showJob(job.id);
    render.comparison = comparison;
  } else {
    render.comparison = undefined;
  }
}

// Replaces only the parts that changed, so a button is not swapped out under a finger
// (or a file chooser under an open dialog) by the once-a-second progress updates.
function patch(container, html) {
  if (container.dataset.html === html) return;
  container.dataset.html = html;
  const fresh = document.createElement("div");
  fresh.innerHTML = html;
  const old = Array.from(container.children);
  const next = Array.from(fresh.children);
  if (old.length !== next.length || next.some((n, i) => n.tagName !== old[i].tagName)) {
    container.replaceChildren(...next);
    return;
  }
  next.forEach((n, i) => {
    if (n.tagName === "TABLE") {
      patchRows(old[i], n);
    } else if (!n.isEqualNode(old[i])) {
      keepPictures(old[i], n);
      old[i].replaceWith(n);
    }
  });
}

// A tile redrawn for its progress keeps its loaded picture element (no flicker).
function keepPictures(oldNode, newNode) {
  newNode.querySelectorAll("img[data-src]").forEach((img) => {
    const loaded = Array.from(oldNode.querySelectorAll("img[data-src]"))
      .find((o) => o.dataset.src === img.dataset.src && o.complete && o.naturalWidth > 0);
    if (loaded) img.replaceWith(loaded);
  });
}

function patchRows(oldTable, newTable) {
  const oldBody = oldTable.tBodies[0], newBody = newTable.tBodies[0];
  const rows = Array.from(newBody.rows);
  const oldRows = Array.from(oldBody.rows);
  if (rows.length !== oldRows.length) { oldTable.replaceWith(newTable); return; }
  rows.forEach((r, i) => { if (!r.isEqualNode(oldRows[i])) oldRows[i].replaceWith(r); });
}

// Live state over server-sent events, read with fetch so the key can go in a header.
async function connect() {
  if (connect.abort) connect.abort.abort();
  const abort = new AbortController();
  connect.abort = abort;
  const link = $("#link");
  try {
    const r = await fetch("/api/v1/events", { headers: headers(), signal: abort.signal });
    if (r.status === 401 || r.status === 403) {
      const answer = await r.json().catch(() => ({}));
      askForKey(answer.error || "API key needed");
      link.textContent = "no key"; link.className = "link down";
      return;
    }
    if (!r.ok) throw new Error("HTTP " + r.status);
    link.textContent = "live"; link.className = "link up";
    const reader = r.body.getReader();
    const decoder = new TextDecoder();
    let buffer = "";
    for (;;) {
      const { value, done } = await reader.read();
      if (done) break;
      buffer += decoder.decode(value, { stream: true });
      let end;
      while ((end = buffer.indexOf("\n\n")) >= 0) {
        const block = buffer.slice(0, end);
        buffer = buffer.slice(end + 2);
        let event = "message", data = "";
        for (const line of block.split("\n")) {
          if (line.startsWith("event:")) event = line.slice(6).trim();
          else if (line.startsWith("data:")) data += line.slice(5).replace(/^ /, "");
        }
        if (event === "status" && data) render(JSON.parse(data));
      }
    }
  } catch (e) {
    if (abort.signal.aborted) return;
  }
  link.textContent = "reconnecting"; link.className = "link down";
  setTimeout(connect, 2000);
}

const ACTIONS = {
  clear: (el) => ["/api/v1/printers/" + encodeURIComponent(el.dataset.printer) + "/clear"],
  pause: (el) => ["/api/v1/printers/" + encodeURIComponent(el.dataset.printer) + "/pause"],
  resume: (el) => ["/api/v1/printers/" + encodeURIComponent(el.dataset.printer) + "/resume"],
  cancel: (el) => el.dataset.copy
    ? ["/api/v1/jobs/" + encodeURIComponent(el.dataset.job) + "/cancel?copy=" + encodeURIComponent(el.dataset.copy), "Cancel this print?"]
    : ["/api/v1/jobs/" + encodeURIComponent(el.dataset.job) + "/cancel", "Cancel this job (and every copy of it still to print)?"],
  cancelpart: (el) => ["/api/v1/jobs/" + encodeURIComponent(el.dataset.job) + "/parts/" + encodeURIComponent(el.dataset.part) + "/cancel",
    "Stop printing " + el.dataset.part + "? The other parts print on."],
  retry: (el) => ["/api/v1/jobs/" + encodeURIComponent(el.dataset.job) + "/retry"],
  release: (el) => ["/api/v1/jobs/" + encodeURIComponent(el.dataset.job) + "/release"],
  unload: (el) => ["/api/v1/printers/" + encodeURIComponent(el.dataset.printer) + "/unload", "Take the spool off " + el.dataset.printer + "? It takes no job until one is loaded."],
  caredone: (el) => ["/api/v1/printers/" + encodeURIComponent(el.dataset.printer) + "/maintenance/done?by=dashboard&task=" + encodeURIComponent(el.dataset.task),
    "Record " + el.dataset.task + " as done on " + el.dataset.printer + "? Its count starts again from now."],
  carestart: (el) => ["/api/v1/printers/" + encodeURIComponent(el.dataset.printer) + "/maintenance/start?by=dashboard",
    "Put " + el.dataset.printer + " into maintenance? It finishes its print, then takes no job until maintenance ends."],
  poweron: (el) => ["/api/v1/printers/" + encodeURIComponent(el.dataset.printer) + "/power/on"],
  poweroff: (el) => ["/api/v1/printers/" + encodeURIComponent(el.dataset.printer) + "/power/off", "Switch " + el.dataset.printer + " off? It is switched on again when it has work."],
  careend: (el) => ["/api/v1/printers/" + encodeURIComponent(el.dataset.printer) + "/maintenance/end?by=dashboard"],
  reference: (el) => ["/api/v1/printers/" + encodeURIComponent(el.dataset.printer) + "/clear?reference=true", "Is the bed of " + el.dataset.printer + " empty, and its camera where it stays? Its picture now becomes the empty bed the check compares with."],
};

document.addEventListener("click", async (e) => {
  const spool = e.target.closest("button[data-spool-printer]");
  if (spool) { openLoad(spool.dataset.spoolPrinter); return; }
  const seek = e.target.closest("button[data-seek]");
  if (seek) {
    const video = document.querySelector("#jobpage figure.timelapse video");
    if (video) { video.currentTime = Number(seek.dataset.seek); video.play().catch(() => {}); }
    return;
  }
  const el = e.target.closest("button[data-action]");
  if (!el) return;
  const [path, confirmText] = ACTIONS[el.dataset.action](el);
  if (confirmText && !confirm(confirmText)) return;
  el.disabled = true;
  try {
    const answer = await api("POST", path);
    notice(answer.message || "done");
    if (el.dataset.action === "cancelpart") showJob(el.dataset.job);
  } catch (err) {
    notice(err.message, true);
  } finally {
    el.disabled = false;
  }
});

// What the upload options ask of a model, as its sidecar: one copy on each printer ticked,
// else the copies asked (nothing for one copy on any printer).
function copiesSidecar() {
  const chosen = [...document.querySelectorAll("#sendto input:checked")].map((c) => c.value);
  if (chosen.length) return "printers = [" + chosen.map((n) => JSON.stringify(n)).join(", ") + "]\n";
  const n = parseInt($("#uploadcopies").value, 10);
  return n > 1 ? "copies = " + n + "\n" : "";
}

// The printers the upload options offer, redrawn only when the farm's printers change (not
// under a finger ticking them).
function sendToOptions(status) {
  const names = status.printers.map((p) => p.name);
  const box = $("#sendto");
  if (box.dataset.names === names.join("\n")) return;
  box.dataset.names = names.join("\n");
  box.innerHTML = names.map((n) => '<label><input type="checkbox" value="' + esc(n) + '"> ' + esc(n) + "</label>").join("");
}

async function upload(folder, file) {
  const zone = document.querySelector('[data-folder="' + CSS.escape(folder) + '"]');
  $("#folders").dataset.busy = "1";
  if (zone) zone.classList.add("busy");
  try {
    const sidecar = /\.toml$/i.test(file.name) ? "" : copiesSidecar();
    // The sidecar goes first: the model is picked up with it.
    if (sidecar) await api("PUT", "/api/v1/folders/" + encodeURIComponent(folder) + "/files/" + encodeURIComponent(file.name + ".toml"), new Blob([sidecar]));
    const answer = await api("PUT", "/api/v1/folders/" + encodeURIComponent(folder) + "/files/" + encodeURIComponent(file.name), file);
    notice(answer.message || "uploaded");
  } catch (err) {
    notice(file.name + ": " + err.message, true);
  } finally {
    delete $("#folders").dataset.busy;
    if (zone) zone.classList.remove("busy");
    if (last) render(last);
  }
}

const folders = $("#folders");
folders.addEventListener("dragover", (e) => {
  const zone = e.target.closest("[data-folder]");
  if (!zone) return;
  e.preventDefault();
  zone.classList.add("over");
});
folders.addEventListener("dragleave", (e) => {
  const zone = e.target.closest("[data-folder]");
  if (zone) zone.classList.remove("over");
});
folders.addEventListener("drop", (e) => {
  const zone = e.target.closest("[data-folder]");
  if (!zone) return;
  e.preventDefault();
  zone.classList.remove("over");
  for (const file of e.dataTransfer.files) upload(zone.dataset.folder, file);
});
folders.addEventListener("change", (e) => {
  const zone = e.target.closest("[data-folder]");
  if (zone && e.target.files) for (const file of e.target.files) upload(zone.dataset.folder, file);
});
// Nothing dropped outside a folder opens the file in place of the dashboard.
window.addEventListener("dragover", (e) => e.preventDefault());
window.addEventListener("drop", (e) => e.preventDefault());

// Numbers as an operator reads them: a few digits, the unit always said.
function num(v, digits) { return +Number(v).toFixed(digits); }
function mm(v) { return v == null || !isFinite(v) ? "?" : num(v, 3) + " mm"; }
function pct(v) { return v == null || !isFinite(v) ? "?" : num(100 * v, 2) + " %"; }

// A job's states in words (the API's names are for programs).
const STATE_WORDS = {
  queued: "queued for preparation", preparing: "being prepared", ready: "ready to print", printing: "printing",
  done: "printed", failed: "failed", cancelled: "cancelled", interrupted: "interrupted",
};
function stateWords(state) { return STATE_WORDS[state] || label(state); }

// The enhancement's strength in words. The paper's: its user study's medium is λ2 = 20
// (the height table's for small prints; 15 at 50 mm, 6 at 100 mm), its strong 40. The
// print-aware mode's λ2 is on a different band and says nothing alone: its target share
// and what bounded it do.
const LIMIT_WORDS = {
  strong_p99: "held to the paper's strong setting",
  ceiling: "held to a line width",
};
function strengthWords(e) {
  if (e.lambda2 == null) return e.mode === "pre-sliced" ? "none: sliced elsewhere" : "none: printed unmodified";
  const pa = e.print_aware;
  if (pa) {
    return "print-aware, λ2 " + num(e.lambda2, 2) + " (aims at " + num(100 * pa.target_share, 1) +
      " % of the surface past a quarter line" + (pa.limited_by ? ", " + (LIMIT_WORDS[pa.limited_by] || pa.limited_by) : "") + ")";
  }
  const word = e.lambda2 >= 30 ? "strong" : e.lambda2 >= 10 ? "medium" : "light";
  return word + " (λ2 " + num(e.lambda2, 2) + ", the paper's method)";
}

// A candidate of the observer (strength = "observed") in words.
function candidateWords(c) {
  if (c.mode === "plain") return "plain (unmodified)";
  if (c.mode === "print-aware") return "print-aware, λ2 " + num(c.strength, 2);
  const word = { 10: "light", 20: "medium", 40: "strong" }[c.strength];
  return (word ? "the paper's " + word + ", " : "the paper's method, ") + "λ2 " + num(c.strength, 2);
}

// Why the observer's strength is what it is.
function choiceText(o) {
  const seen = "the model printed " + num(o.reference_height_mm, 0) + " mm tall" +
    (o.conditions ? ", seen from " + num(o.conditions.distance_mm / 10, 0) + " cm in " + o.conditions.views + " views" : "");
  const c = o.chosen != null ? o.candidates[o.chosen] : null;
  switch (o.choice) {
    case "most_alike":
      return c ? "Of " + o.candidates.length + " candidates, " + candidateWords(c) + " looks most like " + seen +
        " (resemblance " + num(c.resemblance, 3) + "; 1 would be indistinguishable)." : "";
    case "at_reference":
      return "Printed " + num(o.height_mm, 0) + " mm tall, at or above the reference size (" +
        num(o.reference_height_mm, 0) + " mm): unmodified, as the paper's table prints it there.";
    case "timed_out":
      return "The observer ran out of time after " + duration(o.seconds) + "; the strength is the paper's table's.";
    case "failed":
      return "The observer could not look (" + (o.failure || "no candidate could be made") + "); the strength is the paper's table's.";
  }
  return "";
}

// The observer's section: every candidate's resemblance to the print at the reference
// size, what it lost and added (in multiples of a just-visible difference), the views.
function observedSection(j, o) {
  let html = '<h3>Strength chosen by the observer</h3><p id="observed-why">' + esc(choiceText(o)) + "</p>";
  if (o.candidates && o.candidates.length) {
    html += '<table class="figures-table" id="observed"><thead><tr><th>candidate</th><th>resemblance</th>' +
      "<th>visible difference</th><th>lost</th><th>added</th></tr></thead><tbody>";
    o.candidates.forEach((c, i) => {
      const mark = i === o.chosen ? ' class="chosen"' : "";
      const cells = c.resemblance != null ?
        [num(c.resemblance, 3), num(c.difference_jnd, 2), num(c.lost_jnd, 2), num(c.added_jnd, 2)] :
        ["not made: " + (c.error || "?"), "", "", ""];
      html += "<tr" + mark + "><td>" + esc(candidateWords(c) + (i === o.chosen ? " (chosen)" : "")) + "</td>" +
        cells.map((v) => "<td>" + esc(v) + "</td>").join("") + "</tr>";
    });
    html += "</tbody></table>";
  }
  if (j.pictures.includes("observed.png")) {
    html += '<figure id="observed-views">' + picture("/api/v1/jobs/" + encodeURIComponent(j.id) + "/pictures/observed.png", "the observer's views") +
      "<figcaption>What the observer compared, one view a column: first the model printed at the reference size, " +
      "scaled to this print's size; then each candidate, in the order of the table</figcaption></figure>";
  }
  return html;
}

// Rows of [what, figure] as a definition list (the page's layout for figures).
function rowsList(rows, id) {
  return "<dl" + (id ? ' id="' + id + '"' : "") + ">" + rows.filter((r) => r[1] != null && r[1] !== "")
    .map(([k, v]) => "<dt>" + esc(k) + "</dt><dd>" + esc(v) + "</dd>").join("") + "</dl>";
}

// A short table of shares and distances, mm and %.
function figureTable(head, rows, id) {
  return '<table class="figures-table" id="' + id + '"><thead><tr><th>' + esc(head[0]) + "</th><th>" + esc(head[1]) +
    "</th></tr></thead><tbody>" + rows.map(([k, v]) => "<tr><td>" + esc(k) + "</td><td>" + esc(v) + "</td></tr>").join("") +
    "</tbody></table>";
}

// What an operator decides with: strength, printed size, machine, nozzle and layers,
// material, and what the G-code says a print takes. The report's server paths and the
// enhancement's solver figures stay in the raw report.
function printSummary(j, report) {
  const e = report.enhancement || {};
  const p = e.printed || {};
  const s = report.model_size_mm || [];
  const size = s.length === 3 && s.every((v) => isFinite(v) && v > 0) ?
    s.map((v) => num(v, 1)).join(" × ") + " mm (W × D × H)" + (p.scale ? ", the model file scaled ×" + num(p.scale, 4) : "") : null;
  const nozzle = p.nozzle_mm || (e.print_aware && e.print_aware.nozzle_mm) || (j.asks && j.asks.nozzle_mm);
  const layers = [nozzle ? nozzle + " mm nozzle" : "", report.layer_height_mm ? num(report.layer_height_mm, 3) + " mm layers" : "",
    report.layer_count ? report.layer_count + " layers" : ""].filter(Boolean).join(", ");
  const colour = (j.asks && j.asks.colour) || "any colour";
  const temps = [report.nozzle_temp_c ? num(report.nozzle_temp_c, 0) + " °C nozzle" : "",
    report.bed_temp_c ? num(report.bed_temp_c, 0) + " °C bed" : "unheated bed"].filter(Boolean).join(", ");
  const time = report.estimated_print_time_s != null ? duration(report.estimated_print_time_s) + " (the slicer's estimate)" : null;
  const filament = [report.filament_g != null ? num(report.filament_g, 1) + " g" : "",
    report.filament_mm != null ? num(report.filament_mm / 1000, 2) + " m" : ""].filter(Boolean).join(" / ");
  return rowsList([
    ["Enhancement", strengthWords(e)],
    ["Printed size", size],
    ["Machine", report.machine ? report.machine + (j.printer && j.printer !== report.machine ? ", on printer " + j.printer : "") : j.printer],
    ["Slicer", report.slicer_version || report.slicer],
    ["Nozzle and layers", layers],
    ["Material", report.material ? report.material.toUpperCase() + ", " + colour + (temps ? " (" + temps + ")" : "") : null],
    ["Print time", time],
    ["Filament", filament],
  ], "print");
}

// The enhancement in figures: the outer walls the nozzle draws (against the unmodified
// model's G-code), and the mesh at the printed size.
function movedFigures(j, report) {
  const e = report.enhancement || {};
  let html = "";
  const w = report.walls;
  if (w) {
    const rows = [];
    if (w.quarter_line_mm > 0) rows.push(["more than a quarter line width (" + mm(w.quarter_line_mm) + ")", pct(w.share_over_quarter_line)]);
    rows.push(["more than 0.05 mm", pct(w.share_over_0_05_mm)], ["more than 0.1 mm", pct(w.share_over_0_1_mm)],
      ["more than 0.2 mm", pct(w.share_over_0_2_mm)], ["mean / p95 / max", num(w.mean_mm, 3) + " / " + num(w.p95_mm, 3) + " / " + mm(w.max_mm)],
      ["layers compared", String(w.layers) + (w.layers_unmatched ? " (" + w.layers_unmatched + " in one file only)" : "")]);
    html += figureTable(["Outer wall in the G-code moved", "of its length"], rows, "walls");
  } else if (j.job.comparison) {
    html += '<p class="muted" id="walls">' + esc(comparisonText(j.job.comparison)) + "</p>";
  }
  const p = e.printed;
  if (p) {
    const rows = [];
    if (p.threshold_mm != null) rows.push(["more than a quarter line width (" + mm(p.threshold_mm) + ")", pct(p.share_above_threshold)]);
    rows.push(["mean / p95 / max", num(p.mean_mm, 3) + " / " + num(p.p95_mm, 3) + " / " + mm(p.max_mm)]);
    html += figureTable(["Surface of the enhanced mesh moved", "of its area"], rows, "printed");
  }
  return html;
}

// A job's prints in words: when the last one started, how long it took, how it ended.
function printingText(j) {
  const h = j.job.history || [];
  let at = -1;
  h.forEach(([state], i) => { if (state === "printing") at = i; });
  if (at < 0) return "";
  const started = h[at][1];
  const next = h[at + 1];
  const where = j.printer ? " on " + j.printer : "";
  const when = new Date(started * 1000).toLocaleString();
  if (!next) return "Printing" + where + " since " + when + " (" + duration(Date.now() / 1000 - started) + " so far).";
  const r = j.job.print_report;
  const took = r && r.duration_s != null ? r.duration_s : next[1] - started;
  const outcome = { done: "finished", ready: "finished; another copy waits", failed: "failed", cancelled: "cancelled",
    interrupted: "interrupted" }[next[0]] || stateWords(next[0]);
  let text = "Started" + where + " " + when + ", took " + duration(took) + ": " + outcome + ".";
  if (j.job.copies_done > 1) text += " " + j.job.copies_done + " copies printed.";
  if (r && r.resends) text += " The printer asked for " + r.resends + " line" + (r.resends === 1 ? "" : "s") + " again.";
  return text;
}

// A job's wall comparison while it has no figures: measured after the job is ready.
function comparisonText(c) {
  if (c.state === "pending") return "Outer walls against the unmodified model's: pending (measured once no job is being prepared)";
  if (c.state === "not_measured") return "Outer walls against the unmodified model's: not measured (" + c.reason + ")";
  return "";
}

// The raw report, as fetched: a blob the link opens (a plain link would not carry the
// API key). The previous page's blob is let go.
function rawLink(j) {
  if (rawLink.url) URL.revokeObjectURL(rawLink.url);
  rawLink.url = URL.createObjectURL(new Blob([JSON.stringify(j, null, 2)], { type: "application/json" }));
  return '<p><a id="raw" href="' + rawLink.url + '" target="_blank">raw report (JSON)</a></p>';
}

async function showJob(id) {
  const page = $("#jobpage");
  page.innerHTML = '<p><a href="#">← farm</a></p><p class="muted">loading…</p>';
  let j;
  try {
    j = await api("GET", "/api/v1/jobs/" + encodeURIComponent(id));
  } catch (err) {
    page.innerHTML = '<p><a href="#">← farm</a></p><p class="reason">' + esc(err.message) + "</p>";
    return;
  }
  // A job in the history has its record's fields, not a queue entry's (and may have lost
  // its whole record).
  j.pictures = j.pictures || [];
  j.job = j.job || { history: [] };
  const folder = j.folder_name || String(j.folder || "").split("/").filter(Boolean).pop() || "";
  const base = "/api/v1/jobs/" + encodeURIComponent(id) + "/pictures/";
  const report = j.job && j.job.slice_report;
  let html = '<p><a href="#">← farm</a></p><h2>' + esc(j.file) + ' <span class="pill s-' + esc(j.state) + '">' + esc(stateWords(j.state)) + "</span>" +
    (j.held ? ' <span class="pill held">held</span>' : "") + "</h2>";
  html += '<p class="muted">' + esc(j.id) + " · folder " + esc(folder) + (j.printer ? " · printer " + esc(j.printer) : "") + "</p>";
  // Copies: the job that asked for them lists them all; a copy links back to it.
  const copy = j.copy || (j.job && j.job.copy);
  if (copy) html += '<p id="copyof">Copy ' + copy.n + ' of <a href="#job/' + encodeURIComponent(copy.job) + '">' + esc(copy.job) + "</a></p>";
  if (j.copies_status) {
    const c = j.copies_status;
    html += '<p id="copies">Copies: ' + esc(copiesText(c)) + '</p><ol id="copylist">' + c.jobs.map((id) =>
      '<li><a href="#job/' + encodeURIComponent(id) + '">' + esc(id) + "</a></li>").join("") + "</ol>";
  }
  if (j.reason) html += '<p class="reason" id="reason">' + esc(j.reason) + "</p>";
  if (j.waiting) html += '<p class="waiting">' + esc(j.waiting) + "</p>";
  const moved = j.moved;
  if (moved) html += '<p class="moved" id="moved">' + esc(moved) + "</p>";
  if (report) html += printSummary(j, report);
  // Filament: what it asks, what a print needs, what its prints took and cost.
  const filament = [];
  if (asksText(j.asks)) filament.push("asks " + asksText(j.asks));
  if (j.asks && j.asks.priority) filament.push("priority " + j.asks.priority);
  if (j.need_g != null) filament.push("needs about " + grams(j.need_g) + " a print");
  else if (j.need_m != null) filament.push("needs about " + (+j.need_m.toFixed(2)) + " m a print");
  if (j.used_g != null) filament.push("used " + (+j.used_g.toFixed(2)) + " g");
  if (j.cost != null) filament.push("cost " + j.cost.toFixed(2));
  if (filament.length) html += '<p id="filament">' + esc(filament.join(" · ")) + "</p>";
  if (j.pictures.length) {
    html += '<div class="pictures">';
    for (const [name, title] of [["before.png", "Before"], ["after.png", "After"], ["displacement.png", "Displacement"]]) {
      if (j.pictures.includes(name)) html += "<figure>" + picture(base + name, title) + "<figcaption>" + title + "</figcaption></figure>";
    }
    html += "</div>";
  } else {
    html += '<p class="muted">No pictures yet: pictures of the model are drawn for enhanced jobs once prepared, the preview of the print once no job is being prepared.</p>';
  }
  if (j.pictures.includes("preview.png")) {
    html += '<figure id="preview">' + picture(base + "preview.png", "preview of the print") +
      "<figcaption>The print as the printer will lay it, from its G-code: the original model, the plain print " +
      "and the enhanced print (one camera, a low light from the left); below, the prints at their actual size</figcaption></figure>";
  }
  if (report && report.parts && report.parts.length > 1) html += partsSection(j, report.parts);
  if (report && report.enhancement && report.enhancement.observed) html += observedSection(j, report.enhancement.observed);
  if (report && report.enhancement && report.enhancement.lambda2 != null) {
    html += "<h3>What moved</h3>" + movedFigures(j, report);
    if (j.pictures.includes("walls.png")) {
      html += '<figure class="walls">' + picture(base + "walls.png", "outer walls") +
        "<figcaption>Outer walls of three layers (the most changed of the bottom, middle and top thirds): " +
        "unmodified grey, enhanced red</figcaption></figure>";
    }
  }
  const printing = printingText(j);
  if (printing) html += '<h3>Printing</h3><p id="printing">' + esc(printing) + "</p>";
  html += clearingSection(id, j.job.clearing);
  if (j.camera) html += cameraSection(id, j.camera);
  html += "<h3>History</h3><ol class='history'>" + (j.job.history || []).map(([state, t]) =>
    "<li>" + esc(stateWords(state)) + " <span class='muted'>" + new Date(t * 1000).toLocaleString() + "</span></li>").join("") + "</ol>";
  html += rawLink(j);
  html += '<div class="actions">' + jobButtons(j) + "</div>";
  page.innerHTML = html;
  loadPictures(page);
  loadVideos(page);
}

// A plate's parts on the bed, as its G-code lays them (outlines in machine X and Y, mm),
// with those cancelled for the current print and a button to cancel each of the others.
function partsSection(j, parts) {
  const h = j.job.history || [];
  const started = h.filter(([state]) => state === "printing").length;
  const print = ["queued", "preparing", "ready"].includes(j.state) ? started + 1 : Math.max(started, 1);
  const cancelled = new Map((j.job.parts_cancelled || []).filter((c) => c.print === print).map((c) => [c.part, c]));
  const xs = [], ys = [];
  for (const p of parts) for (const [x, y] of p.outline) { xs.push(x); ys.push(y); }
  let svg = "";
  if (xs.length) {
    const pad = 5, x0 = Math.min(...xs) - pad, y1 = Math.max(...ys) + pad;
    const w = Math.max(...xs) + pad - x0, hgt = y1 - (Math.min(...ys) - pad);
    // Machine Y points away from the viewer: flipped so the plate looks as from the front.
    const at = ([x, y]) => (x - x0).toFixed(2) + "," + (y1 - y).toFixed(2);
    svg = '<svg class="plate" viewBox="0 0 ' + w.toFixed(2) + " " + hgt.toFixed(2) + '" role="img" aria-label="the plate\'s parts on the bed">' +
      parts.map((p, i) => {
        if (!p.outline.length) return "";
        const cx = p.outline.reduce((a, q) => a + q[0], 0) / p.outline.length;
        const cy = p.outline.reduce((a, q) => a + q[1], 0) / p.outline.length;
        return '<g class="part' + (cancelled.has(p.name) ? " cancelled" : "") + '"><title>' + esc(p.name) + "</title>" +
          '<polygon points="' + p.outline.map(at).join(" ") + '"/>' +
          '<text x="' + (cx - x0).toFixed(2) + '" y="' + (y1 - cy).toFixed(2) + '">' + (i + 1) + "</text></g>";
      }).join("") + "</svg>";
  }
  const can = ["ready", "printing"].includes(j.state);
  const rows = parts.map((p, i) => {
    const c = cancelled.get(p.name);
    let what = (+p.extruded_mm.toFixed(0)) + " mm of filament";
    if (c) {
      const d = c.dropped;
      what = "cancelled" + (d && d.layer ? " at layer " + d.layer + (d.z_mm != null ? " (Z " + (+d.z_mm.toFixed(2)) + " mm)" : "") : d ? " from line " + d.line : " before its print");
    }
    const button = can && !c ? ' <button class="danger" data-action="cancelpart" data-job="' + esc(j.id) + '" data-part="' + esc(p.name) + '">Cancel part</button>' : "";
    return "<li" + (c ? ' class="cancelled"' : "") + "><b>" + (i + 1) + "</b> " + esc(p.name) + ' <span class="muted">' + esc(what) + "</span>" + button + "</li>";
  }).join("");
  return '<h3>Parts <small class="muted">' + (parts.length - cancelled.size) + " of " + parts.length + ' on the plate</small></h3><div class="parts">' + svg + '<ol id="parts">' + rows + "</ol></div>";
}

// A job's snapshots and timelapse, as its printer's camera took them.
function cameraSection(id, cam) {
  const base = "/api/v1/jobs/" + encodeURIComponent(id) + "/camera/";
  let html = '<h3>Camera <small class="muted">' + esc(cam.printer) + "</small></h3>";
  if (cam.timelapse) {
    html += '<figure class="timelapse"><video controls muted playsinline data-src="' + esc(base + cam.timelapse.file) + '"></video>' +
      "<figcaption>Timelapse: " + cam.timelapse.frames + " frames, " + (cam.timelapse.bytes / 1024).toFixed(0) + " KiB</figcaption></figure>";
  } else if (cam.timelapse_error) {
    html += '<p class="muted">No timelapse: ' + esc(cam.timelapse_error) + "</p>";
  }
  if (cam.dropped && cam.dropped.length) {
    // Where each cancelled part stops printing in the timelapse; a button plays from there.
    html += '<ul class="dropped">' + cam.dropped.map((d) => {
      const at = Math.floor(d.video_s / 60) + ":" + (d.video_s % 60).toFixed(1).padStart(4, "0");
      const seek = cam.timelapse ? ' <button data-seek="' + d.video_s + '">from ' + at + " in the timelapse</button>" : "";
      return "<li>" + esc(d.part) + " dropped" + (d.layer ? " at layer " + d.layer : "") + ", after frame " + d.frame + seek + "</li>";
    }).join("") + "</ul>";
  }
  if (cam.missing && cam.missing.length) {
    const of = cam.layers ? " of " + cam.layers : "";
    html += '<ul class="missing">' + cam.missing.map((m) =>
      "<li>No timelapse frame of " + (m.first === m.last ? "layer " + m.first : "layers " + m.first + "–" + m.last) + of +
      ": " + esc(noFrameWords(m.why)) + ' <span class="muted">' + new Date(m.at * 1000).toLocaleTimeString() + "</span></li>").join("") +
      "</ul>";
  }
  if (cam.snapshots.length) {
    html += '<div class="pictures snapshots">';
    for (const s of cam.snapshots) {
      html += "<figure>" + picture(base + s.file, s.name) + "<figcaption>" + esc(s.name.replace(/-/g, " ")) +
        ' <span class="muted">' + new Date(s.at * 1000).toLocaleTimeString() + "</span></figcaption></figure>";
    }
    html += "</div>";
  }
  return html;
}

// Why a job has no frame where it wanted one (a NoFrame of its camera.json), in words.
function noFrameWords(why) {
  switch (why.kind) {
    case "starting": return "the camera had given no frame yet";
    case "offline": {
      const since = why.since ? " since " + new Date(why.since * 1000).toLocaleTimeString() : "";
      return "the camera was offline" + since + (why.fault ? " (" + cameraFaultWords(why.fault) + ")" : "");
    }
    case "stale": return "the camera's latest frame was " + Math.round(why.age_s) + " s old";
    case "picture": return "the camera's frame could not be made into a picture";
    case "disk": return "the frame could not be written to the disk";
    default: return label(why.kind);
  }
}

// A camera's last failure (a CameraFault), in words.
function cameraFaultWords(f) {
  switch (f.kind) {
    case "connect": return "cannot connect";
    case "timeout": return "no answer within " + f.seconds + " s";
    case "no_frame": return "no frame within " + f.seconds + " s";
    case "status": return "HTTP status " + f.code;
    case "not_jpeg": return "not a JPEG";
    case "too_large": return "a frame larger than " + (f.max_bytes / 1048576).toFixed(1) + " MB";
    case "not_stream": return "not an MJPEG stream";
    case "no_boundary": return "no boundary within " + (f.max_bytes / 1048576).toFixed(1) + " MB";
    case "closed": return "the stream ended";
    case "http": return "the HTTP exchange failed";
    case "refused": return frameFaultWords(f.frame);
    default: return label(f.kind);
  }
}

// Why a camera's frame was refused (a FrameFault), in words.
function frameFaultWords(f) {
  switch (f.kind) {
    case "headers": return "a part's headers were unreadable";
    case "not_jpeg": return "a part that is not a JPEG";
    case "cut": return "frames cut short";
    case "trailing": return "frames run into the next part";
    case "malformed": return "frames whose JPEG segments are malformed";
    case "undecodable": return "frames whose picture does not decode";
    default: return label(f.kind);
  }
}

function loadVideos(root) {
  root.querySelectorAll("video[data-src]:not([src])").forEach(async (video) => {
    try {
      const r = await fetch(video.dataset.src, { headers: headers() });
      if (r.ok) video.src = URL.createObjectURL(await r.blob());
    } catch (_) { /* left without */ }
  });
}

function route() {
  const m = location.hash.match(/^#job\/(.+)$/);
  const cam = location.hash.match(/^#camera\/(.+)$/);
  $("#farm").hidden = !!(m || cam);
  $("#jobpage").hidden = !(m || cam);
  if (m) showJob(decodeURIComponent(m[1]));
  if (cam) showCamera(decodeURIComponent(cam[1]));
}

window.addEventListener("hashchange", route);
route();
connect();
refreshCameras();
setInterval(refreshCameras, 3000);
