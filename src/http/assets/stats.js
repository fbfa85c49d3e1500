// The statistics page: GET /api/v1/stats for the chosen period, drawn as a table and an
// SVG chart built here (a bar per printer per day; no charting library). The API key,
// when the daemon wants one for reads, is the dashboard's (this browser's storage).
"use strict";

const key = localStorage.getItem("crispen-key") || "";
const SVG = "http://www.w3.org/2000/svg";
const COLOURS = ["#2f7ed8", "#e4572e", "#17a398", "#f3a712", "#8e44ad", "#5d6d7e"];

function el(tag, attrs, text) {
  const e = tag.startsWith("svg:") ? document.createElementNS(SVG, tag.slice(4)) : document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, v);
  if (text != null) e.textContent = text;
  return e;
}

function hours(s) { return (s / 3600).toFixed(1); }
function pct(x) { return x == null ? "" : (100 * x).toFixed(1) + "%"; }
// Empty when no print's price was known (not a cost of 0).
function money(x) { return x == null ? "" : x.toFixed(2); }

// One bar per printer within each day's slot; the y axis 0 to 100 %.
function chart(stats) {
  const printers = stats.printers;
  const days = stats.days;
  const left = 40, top = 10, height = 200, slot = Math.max(days.length > 31 ? 12 : 40, 12 * printers.length + 8);
  const width = left + slot * days.length + 10;
  const svg = el("svg:svg", { width, height: top + height + 60, viewBox: `0 0 ${width} ${top + height + 60}`,
    role: "img", "aria-label": "utilisation per printer per day" });
  svg.classList.add("chart");
  for (const y of [0, 0.25, 0.5, 0.75, 1]) {
    const py = top + height * (1 - y);
    svg.append(el("svg:line", { x1: left, x2: width, y1: py, y2: py, stroke: "#ccc" }));
    svg.append(el("svg:text", { x: left - 4, y: py + 4, "text-anchor": "end", "font-size": 10 }, (100 * y) + "%"));
  }
  const bar = (slot - 8) / Math.max(1, printers.length);
  days.forEach((day, d) => {
    const x0 = left + d * slot + 4;
    printers.forEach((p, i) => {
      const u = p.daily_utilisation[d] || 0;
      const h = height * Math.min(u, 1);
      const r = el("svg:rect", { x: x0 + i * bar, y: top + height - h, width: Math.max(1, bar - 1), height: h,
        fill: COLOURS[i % COLOURS.length], "data-printer": p.name, "data-day": day, "data-utilisation": u });
      r.append(el("svg:title", {}, `${p.name} ${day}: ${pct(u)}`));
      svg.append(r);
    });
    // Under its day's slot, read downwards from the slot's middle.
    const cx = x0 + (slot - 8) / 2, cy = top + height + 8;
    const label = el("svg:text", { x: cx, y: cy, "font-size": 10, "text-anchor": "end",
      transform: `rotate(-60 ${cx} ${cy})` }, day.slice(5));
    svg.append(label);
  });
  const legend = el("p", { class: "legend" });
  printers.forEach((p, i) => {
    const s = el("span", {}, "■ ");
    s.style.color = COLOURS[i % COLOURS.length]; // not an attribute: the page's CSP
    legend.append(s, document.createTextNode(p.name + "  "));
  });
  const box = document.getElementById("chart");
  box.replaceChildren(svg, legend);
}

function table(groups, id, printers) {
  const t = el("table", { class: "stats" });
  const head = ["name", "done", "failed", "cancelled", "printing h"];
  if (printers) head.push("utilisation");
  head.push("filament m", "used g", "cost", "most common failures");
  const tr = el("tr");
  head.forEach((h) => tr.append(el("th", {}, h)));
  t.append(tr);
  for (const g of groups) {
    const row = el("tr", { "data-name": g.name });
    const cells = [g.name, g.jobs.done, g.jobs.failed, g.jobs.cancelled, hours(g.printing_s)];
    if (printers) cells.push(pct(g.utilisation));
    cells.push((g.filament_mm / 1000).toFixed(2), g.used_g.toFixed(1), money(g.cost),
      g.failure_reasons.map((r) => `${r.reason} (${r.jobs})`).join("; "));
    cells.forEach((c) => row.append(el("td", {}, String(c))));
    t.append(row);
  }
  document.getElementById(id).replaceChildren(t);
}

async function load() {
  const days = document.getElementById("days").value;
  const headers = key ? { "X-Api-Key": key } : {};
  try {
    const r = await fetch(`/api/v1/stats?days=${encodeURIComponent(days)}`, { headers });
    const body = await r.json();
    if (!r.ok) throw new Error(body.error || r.status);
    chart(body);
    table(body.printers, "printers", true);
    table(body.folders, "folders", false);
    table(body.materials, "materials", false);
    document.getElementById("summary").textContent =
      `statistics ${body.days[0]} to ${body.days[body.days.length - 1]}: ` +
      `${body.farm.jobs.done} done, ${body.farm.jobs.failed} failed, ${body.farm.jobs.cancelled} cancelled`;
    document.getElementById("stats").dataset.loaded = "true";
  } catch (e) {
    const n = document.getElementById("notice");
    n.textContent = "statistics: " + e.message;
    n.className = "bad";
    n.hidden = false;
  }
}

document.getElementById("days").addEventListener("change", load);
load();
