// The fleet page: plain JS over the page's own JSON (api/status, api/trend, api/jobs; relative URLs, so it works
// at / of `cellctl fleet serve` and at /fleet/ of a daemon). Read-only: no token, nothing loaded from elsewhere.
// Every few seconds it reads the plant database again; when that fails it says why and keeps what it showed.
"use strict";

const REFRESH_MS = 5000;
const SILENT_S = 60;  // a cell not offline but unheard of this long is flagged (its heartbeat is every ~10 s)
const COLOURS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#7f7f7f"];
const DRIFT_RED = "#c62828";

const $ = (sel) => document.querySelector(sel);
let lastTrend = "";  // the trend as last drawn (JSON): redrawn only when it changed, so a hovered tip stays

// -- small helpers ----------------------------------------------------------------------------------

function el(tag, props = {}, ...children) {
  const node = Object.assign(document.createElement(tag), props);
  for (const c of children) node.append(c instanceof Node ? c : String(c ?? ""));
  return node;
}

function svg(tag, attrs = {}, ...children) {
  const node = document.createElementNS("http://www.w3.org/2000/svg", tag);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, v);
  for (const c of children) node.append(c instanceof Node ? c : String(c));
  return node;
}

function fmt(x, digits = 1) {
  return typeof x === "number" && isFinite(x) ? x.toFixed(digits) : "–";
}

function badge(kind, value) {
  return el("span", { className: `badge ${kind}-${value}` }, value);
}

function ago(seconds) {
  if (seconds < 90) return `${Math.max(0, Math.round(seconds))} s ago`;
  if (seconds < 5400) return `${Math.round(seconds / 60)} min ago`;
  if (seconds < 172800) return `${Math.round(seconds / 3600)} h ago`;
  return `${Math.round(seconds / 86400)} days ago`;
}

async function get(path) {
  const r = await fetch(path, { headers: { Accept: "application/json" }, cache: "no-store" });
  if (!r.ok) {
    let detail = r.statusText;
    try { detail = (await r.json()).detail ?? detail; } catch { /* not JSON: the status text says enough */ }
    throw new Error(`${path}: ${detail}`);
  }
  return r.json();
}

// -- the table of cells ------------------------------------------------------------------------------

function renderCells(cells, jobs, colourOf) {
  const targets = [...new Set(cells.flatMap((c) => Object.keys(c.calibrations)))].sort();
  const head = [
    el("tr", {}, ...["cell", "state", "last seen", "live job"].map((h) => el("th", { rowSpan: 2 }, h)),
      ...targets.map((t) => el("th", { colSpan: 3, className: "target" }, t))),
    el("tr", {}, ...targets.flatMap(() => [el("th", {}, "version"), el("th", { className: "mean" }, "verif. mean µm"),
      el("th", {}, "health")]))];
  $("#cells thead").replaceChildren(...(cells.length ? head : []));

  const jobOf = new Map(jobs.map((j) => [`${j.cell}/${j.id}`, j]));
  const now = Date.now();
  $("#cells tbody").replaceChildren(...cells.map((c) => {
    const swatch = el("span", { className: "swatch" });
    swatch.style.background = colourOf(c.name);
    const name = /^https?:\/\//.test(c.api_url || "")  // the cell's own console, for a closer look
      ? el("a", { href: c.api_url.replace(/\/$/, "") + "/console/", title: `${c.api_url} · ${c.software_revision}` }, c.name)
      : el("span", { title: c.software_revision || "" }, c.name);
    const age = (now - Date.parse(c.last_seen)) / 1000;
    const silent = c.state !== "offline" && age > SILENT_S;
    const job = c.live_job != null ? jobOf.get(`${c.name}/${c.live_job}`) : null;
    const row = el("tr", { className: c.state === "offline" ? "offline" : "" },
      el("td", { className: "cell-name" }, swatch, name, c.description ? el("span", { className: "desc" }, c.description) : ""),
      el("td", { className: "state" }, badge("state", c.state)),
      el("td", { className: `last-seen${silent ? " silent" : ""}`, title: new Date(c.last_seen).toLocaleString() },
        ago(age) + (silent ? " (silent)" : "")),
      el("td", { className: "live-job" }, c.live_job == null ? "–" : `#${c.live_job}${job ? ` ${job.routine}` : ""}`));
    row.dataset.cell = c.name;
    for (const t of targets) {
      const cal = c.calibrations[t];
      const cols = cal
        ? [el("td", { className: "version" }, `v${cal.version}`), el("td", { className: "mean" }, fmt(cal.verification_mean_um)),
          el("td", { className: "health" }, badge("health", cal.health))]
        : [el("td", { className: "version" }, "–"), el("td", { className: "mean" }, "–"), el("td", { className: "health" }, "–")];
      for (const td of cols) td.dataset.target = t;
      row.append(...cols);
    }
    return row;
  }));
  $("#no-cells").hidden = cells.length > 0;
  const counts = {};
  for (const c of cells) counts[c.state] = (counts[c.state] || 0) + 1;
  $("#cell-count").textContent = cells.length
    ? `${cells.length} · ` + Object.entries(counts).map(([s, n]) => `${n} ${s}`).join(", ") : "";
}

// -- one plot per target: time on x, µm on y, a colour per cell ----------------------------------------

function niceStep(range, ticks) {
  const raw = range / ticks, mag = 10 ** Math.floor(Math.log10(raw)), norm = raw / mag;
  return (norm <= 1 ? 1 : norm <= 2 ? 2 : norm <= 5 ? 5 : 10) * mag;
}

// Time ticks on round local times (hours, or midnights for a step of a day or more), at most seven.
const HOUR = 3600e3, DAY = 86400e3;
const TIME_STEPS = [HOUR, 2 * HOUR, 3 * HOUR, 6 * HOUR, 12 * HOUR, DAY, 2 * DAY, 3 * DAY, 7 * DAY, 14 * DAY, 30 * DAY,
  91 * DAY];

function timeTicks(x0, x1) {
  const step = TIME_STEPS.find((s) => (x1 - x0) / s <= 7) || TIME_STEPS.at(-1);
  const d = new Date(x0);
  d.setMinutes(0, 0, 0);
  d.setHours(step >= DAY ? 0 : d.getHours() - d.getHours() % (step / HOUR));  // 06:00, 12:00, not 07:00, 13:00
  const ticks = [];
  for (let t = d.getTime(); t <= x1; ) {
    if (t >= x0) ticks.push(t);
    const next = new Date(t);  // by the calendar, so a day is a day across a change of summer time
    if (step >= DAY) next.setDate(next.getDate() + Math.round(step / DAY));
    else next.setHours(next.getHours() + step / HOUR);
    t = next.getTime();
  }
  const label = step >= DAY ? { month: "short", day: "numeric" } : step >= 6 * HOUR
    ? { month: "short", day: "numeric", hour: "2-digit", minute: "2-digit" } : { hour: "2-digit", minute: "2-digit" };
  return ticks.map((t) => [t, new Date(t).toLocaleString(undefined, label)]);
}

// The time span of every plot (the same for all, so the targets line up): [first, last] of all their points.
function timeSpan(targets) {
  const xs = Object.values(targets).flatMap((cells) => Object.values(cells).flatMap((s) =>
    [...s.calibrations, ...s.checks].map((p) => Date.parse(p.t)))).filter(isFinite);
  let x0 = Math.min(...xs), x1 = Math.max(...xs);
  if (x1 - x0 < 60e3) { x0 -= 1800e3; x1 += 1800e3; }  // one moment: half an hour either side
  const pad = (x1 - x0) * 0.03;  // markers at the ends stay inside the frame
  return [x0 - pad, x1 + pad];
}

function trendChart(target, perCell, colourOf, [x0, x1]) {
  const W = 760, left = 52, right = 170, top = 30, bottom = 40;
  const series = Object.entries(perCell).sort(([a], [b]) => a.localeCompare(b)).map(([cell, s]) => ({
    cell,
    means: s.calibrations.map((c) => ({ ...c, x: Date.parse(c.t), y: c.mean_um })).sort((a, b) => a.x - b.x),
    checks: s.checks.map((c) => ({ ...c, x: Date.parse(c.t), y: c.drift_um })).sort((a, b) => a.x - b.x),
  }));
  const all = series.flatMap((s) => [...s.means, ...s.checks]).filter((p) => isFinite(p.x) && isFinite(p.y));
  const figure = el("figure", { className: "chart" });
  figure.dataset.target = target;
  if (!all.length) return figure;
  const H = Math.max(300, top + 16 * series.length + 80);  // taller when the legend needs it

  const yMax = Math.max(...all.map((p) => p.y), 1e-9);
  const step = niceStep(yMax * 1.05, 4), y1 = Math.ceil(yMax * 1.05 / step) * step;
  const px = (x) => left + (x - x0) / (x1 - x0) * (W - left - right);
  const py = (y) => H - bottom - y / y1 * (H - top - bottom);

  const g = svg("svg", { viewBox: `0 0 ${W} ${H}`, width: "100%", role: "img", "font-size": "11",
      "aria-label": `${target}: verification mean and drift per cell over time` },
    svg("text", { x: left, y: 14, "font-weight": "bold", "font-size": "13" }, target),
    svg("text", { x: W - right, y: 14, fill: "#5b6577", "text-anchor": "end" },
      "verification mean per version · drift at each check"));
  for (let y = 0; y <= y1 + step / 2; y += step) {  // horizontal grid with its µm labels
    g.append(svg("line", { x1: left, x2: W - right, y1: py(y), y2: py(y), stroke: y ? "#e3e7ee" : "#999" }),
      svg("text", { x: left - 4, y: py(y) + 4, "text-anchor": "end" }, Number(y.toPrecision(3))));
  }
  for (const [t, text] of timeTicks(x0, x1)) {
    g.append(svg("line", { x1: px(t), x2: px(t), y1: top, y2: H - bottom + 4, stroke: "#e3e7ee" }),
      svg("text", { x: px(t), y: H - bottom + 15, "text-anchor": "middle" }, text));
  }
  g.append(svg("rect", { x: left, y: top, width: W - left - right, height: H - top - bottom, fill: "none", stroke: "#999" }),
    svg("text", { x: (left + W - right) / 2, y: H - 6, "text-anchor": "middle" }, "time"),
    svg("text", { x: 12, y: (top + H - bottom) / 2, transform: `rotate(-90 12 ${(top + H - bottom) / 2})`,
      "text-anchor": "middle" }, "µm"));

  series.forEach((s, i) => {
    const colour = colourOf(s.cell);
    const group = svg("g", { class: "series", "data-cell": s.cell });
    if (s.means.length > 1) {
      group.append(svg("polyline", { class: "mean-line", points: s.means.map((p) => `${px(p.x)},${py(p.y)}`).join(" "),
        fill: "none", stroke: colour, "stroke-width": 1.5 }));
    }
    const when = (p) => new Date(p.x).toLocaleString();
    for (const p of s.means) {
      group.append(svg("circle", { class: "mean", cx: px(p.x), cy: py(p.y), r: 3.5, fill: colour },
        svg("title", {}, `${s.cell} ${target} v${p.version}: verification mean ${fmt(p.y, 2)} µm (${when(p)})`)));
    }
    for (const p of s.checks) {  // a diamond per check; a drift verdict filled and ringed in red
      const [cx, cy] = [px(p.x), py(p.y)];
      if (p.drifted) {
        group.append(svg("circle", { class: "drift-ring", cx, cy, r: 8, fill: "none", stroke: DRIFT_RED, "stroke-width": 2 }));
      }
      group.append(svg("path", {
        class: p.drifted ? "check drift" : "check", d: `M${cx} ${cy - 5}L${cx + 5} ${cy}L${cx} ${cy + 5}L${cx - 5} ${cy}Z`,
        fill: p.drifted ? colour : "#fff", stroke: colour, "stroke-width": 1.5,
      }, svg("title", {}, `${s.cell} ${target} check: drift ${fmt(p.y, 2)} µm, ${p.drifted ? "DRIFT" : "holds"} (${when(p)})`)));
    }
    g.append(group);
    // the legend: this cell's colour and name (long names cut, whole in the tip)
    const ly = top + 10 + 16 * i, lx = W - right + 12;
    g.append(svg("g", { class: "legend", "data-cell": s.cell },
      svg("line", { x1: lx, x2: lx + 18, y1: ly - 4, y2: ly - 4, stroke: colour, "stroke-width": 1.5 }),
      svg("circle", { cx: lx + 9, cy: ly - 4, r: 3.5, fill: colour }),
      svg("text", { x: lx + 24, y: ly, fill: colour }, s.cell.length > 20 ? s.cell.slice(0, 19) + "…" : s.cell,
        svg("title", {}, s.cell))));
  });
  // the key of the marks, under the cells
  const ky = top + 16 * series.length + 22, kx = W - right + 12;
  g.append(svg("g", { class: "key", fill: "#5b6577" },
    svg("circle", { cx: kx + 9, cy: ky - 4, r: 3.5, fill: "#5b6577" }), svg("text", { x: kx + 24, y: ky }, "verification mean"),
    svg("path", { d: `M${kx + 9} ${ky + 11}l5 5l-5 5l-5 -5Z`, fill: "#fff", stroke: "#5b6577", "stroke-width": 1.5 }),
    svg("text", { x: kx + 24, y: ky + 20 }, "drift at a check"),
    svg("circle", { cx: kx + 9, cy: ky + 32, r: 7, fill: "none", stroke: DRIFT_RED, "stroke-width": 2 }),
    svg("text", { x: kx + 24, y: ky + 36 }, "verdict: drift")));
  figure.append(g);
  return figure;
}

function renderTrend(targets, colourOf) {
  const drawn = JSON.stringify(targets);
  if (drawn === lastTrend) return;
  lastTrend = drawn;
  const names = Object.keys(targets).sort();
  const span = names.length ? timeSpan(targets) : null;
  $("#charts").replaceChildren(...names.map((t) => trendChart(t, targets[t], colourOf, span)));
  $("#no-trend").hidden = names.length > 0;
}

// -- the refresh loop ---------------------------------------------------------------------------------

async function refresh() {
  try {
    const [status, trend, jobs] = await Promise.all([get("api/status"), get("api/trend"), get("api/jobs?limit=200")]);
    // a cell keeps its colour in the table and every plot: by its place among all cells (sorted by name)
    const names = status.cells.map((c) => c.name);
    const colourOf = (cell) => COLOURS[Math.max(0, names.indexOf(cell)) % COLOURS.length];
    if (names.join("\n") !== refresh.names) { refresh.names = names.join("\n"); lastTrend = ""; }  // colours moved
    renderCells(status.cells, jobs.jobs, colourOf);
    renderTrend(trend.targets, colourOf);
    $("#conn").textContent = "live";
    $("#conn").className = "pill live";
    $("#updated").textContent = `last read ${new Date().toLocaleTimeString()}`;
    $("#message").hidden = true;
  } catch (err) {
    $("#conn").textContent = "plant database unreachable";
    $("#conn").className = "pill down";
    $("#message").textContent = `${err.message} — showing what was last read; trying again every ${REFRESH_MS / 1000} s`;
    $("#message").hidden = false;
  }
  setTimeout(refresh, REFRESH_MS);
}

refresh();
