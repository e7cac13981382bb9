// The cellctl web console: plain JS against the daemon's HTTP API (same origin, nothing loaded from elsewhere).
// Reading needs no token; commands send the token the operator pasted (kept in sessionStorage only) and
// take the operator lock first (POST /lock, a 30 s lease renewed while the tab is open), so other clients can
// watch but not command meanwhile.
// When the cell's operator is the web console (operator: {backend: web}), a routine's request for operator
// input shows at the top: the frame with the projected model points to click in pairs, or an instruction.
"use strict";

const $ = (sel) => document.querySelector(sel);
const store = window.sessionStorage;
const ui = {
  token: store.getItem("cellctl.token"),
  lockId: null,       // the operator lock this page holds (never kept: a new page has taken none)
  lockNote: null,     // why it holds none, when that is news (broken, given back)
  heartbeat: null,    // the interval that renews the lock while this page holds it
  lastCommand: 0,     // performance.now() of the operator's last command here (monotonic: a clock step ends no lease)
  holder: `console-${Math.random().toString(36).slice(2, 8)}`,  // this page, as others see it holding the lock
  selected: null,     // the job shown in the job and results panels
  jobs: new Map(),    // id -> job as last listed
  progress: new Map(),  // id -> latest progress event
  routines: null,
  cell: null,
  resultsShown: null,  // "id:item" whose results are on screen
};

class ApiError extends Error {
  constructor(status, detail) { super(detail); this.status = status; }
}

// -- small helpers ----------------------------------------------------------------------------------

function el(tag, props = {}, ...children) {
  const node = Object.assign(document.createElement(tag), props);
  for (const c of children) node.append(c instanceof Node ? c : String(c ?? ""));
  return node;
}

function fmt(x, digits = 1, unit = "") {
  return typeof x === "number" && isFinite(x) ? `${x.toFixed(digits)}${unit}` : "–";
}

let sayTimer = null;
function say(text, isError = false) {
  const box = $("#message");
  box.textContent = text;
  box.className = isError ? "error" : "";
  box.hidden = !text;
  clearTimeout(sayTimer);  // news fades; an error stays until the next action
  if (!isError && text) sayTimer = setTimeout(() => { box.hidden = true; }, 8000);
}

async function detailOf(response) {
  try {
    const body = await response.json();
    return typeof body.detail === "string" ? body.detail : JSON.stringify(body.detail ?? body);
  } catch { return response.statusText; }
}

async function get(path) {
  const r = await fetch(path, { headers: { Accept: "application/json" } });
  if (!r.ok) throw new ApiError(r.status, await detailOf(r));
  return r.json();
}

// -- token, lock, commands ------------------------------------------------------------------------
// The operator lock is taken by the first command, not by opening the page, as a short lease that a heartbeat
// renews while this tab is open: a closed tab gives it back at once (pagehide), a crashed or frozen one loses it
// within LEASE_S. After IDLE_MS without a command the tab gives it back by itself: an open tab on a forgotten
// screen must not keep the MES and the CLI out (no longer than the old fixed 600 s lock did); the next command
// simply takes it again.

const LEASE_S = 30;
const HEARTBEAT_MS = 10_000;
const IDLE_MS = 10 * 60_000;

function showToken() {
  $("#token-form").hidden = !!ui.token;
  $("#token-state").hidden = !ui.token;
  $("#lock-state").textContent = ui.lockId ? `lock held as ${ui.holder}` : (ui.lockNote || "no lock taken");
}

function forgetToken() {
  ui.token = null;
  store.removeItem("cellctl.token");
  dropLock();
}

function headers(extra = {}) {
  const h = { "Content-Type": "application/json", Authorization: `Bearer ${ui.token}`, "X-Cellctl-Client": "console" };
  if (ui.lockId) h["X-Cellctl-Lock"] = ui.lockId;
  return Object.assign(h, extra);
}

// A refused command: say why in words an operator can act on; a wrong token is dropped.
function refused(status, detail) {
  if (status === 401 || status === 403) {
    forgetToken();
    $("#token-input").focus();
    return new ApiError(status, `The daemon refused the token (${status}: ${detail}). Nothing was changed. ` +
      "Paste the output of `cellctl token` for this cell and try again.");
  }
  if (status === 423) return new ApiError(status, `Another client holds the operator lock: ${detail}`);
  return new ApiError(status, `Refused (${status}): ${detail}`);
}

function holdLock(lockId) {
  ui.lockId = lockId;
  ui.lockNote = null;
  ui.heartbeat ??= setInterval(heartbeat, HEARTBEAT_MS);
  showToken();
}

function dropLock(note = null) {
  ui.lockId = null;
  ui.lockNote = note;
  clearInterval(ui.heartbeat);
  ui.heartbeat = null;
  showToken();
}

// Someone with the token broke this tab's lock: say who and why, and do not take it back by ourselves.
function lockBroken(broken) {
  const text = `Your operator lock was broken by ${broken.by}: ${broken.reason}`;
  dropLock(`lock broken by ${broken.by}`);
  say(`${text}. Nothing this tab sends holds it any more; the next command takes it again if it is free.`, true);
  refreshCell();
  return new ApiError(423, text);
}

async function lockRequest() {
  const r = await fetch("/lock", { method: "POST", headers: headers(),
    body: JSON.stringify({ holder: ui.holder, ttl_s: LEASE_S }) });
  const body = await r.json().catch(() => ({}));
  return { r, body, detail: typeof body.detail === "string" ? body.detail : r.statusText };
}

async function takeLock() {
  // take the lock, or renew ours; a lock id the daemon no longer knows is dropped and the lock taken anew
  for (let attempt = 0; attempt < 2; attempt++) {
    const { r, body, detail } = await lockRequest();
    if (r.ok) { holdLock(body.lock_id); return; }
    if (r.status === 423 && body.broken) throw lockBroken(body.broken);
    if (r.status === 423 && ui.lockId && attempt === 0) {
      dropLock();
      const holder = (await get("/lock")).holder;
      if (holder) throw refused(423, detail);
      continue;  // ours had lapsed and nobody holds it: take it again
    }
    throw refused(r.status, detail);
  }
}

async function heartbeat() {
  if (!ui.lockId || !ui.token) { dropLock(); return; }
  if (performance.now() - ui.lastCommand > IDLE_MS) {
    await releaseLock().catch(() => {});
    dropLock(`lock given back after ${IDLE_MS / 60_000} min without a command`);
    return;
  }
  let answer;
  try { answer = await lockRequest(); } catch { return; }  // the daemon unreachable: try again at the next beat
  const { r, body, detail } = answer;
  if (r.ok && body.lock_id !== ui.lockId) {
    // our lease lapsed (a background tab's timers may run only once a minute) and the lock was free, so this
    // renewal took a new one: give it back; the next command takes the lock again, in the operator's sight
    ui.lockId = body.lock_id;
    await releaseLock().catch(() => {});
    dropLock("lock lapsed while this tab was in the background");
    return;
  }
  if (r.ok) { holdLock(body.lock_id); return; }
  if (r.status === 423 && body.broken) { lockBroken(body.broken); return; }
  if (r.status === 401 || r.status === 403) { say(refused(r.status, detail).message, true); return; }
  dropLock("lock lost");
  say(`This tab no longer holds the operator lock: ${detail}`, true);
  refreshCell();
}

async function command(method, path, body = undefined) {
  if (!ui.token) {
    $("#token-input").focus();
    throw new ApiError(401, "Commands need the token: paste the output of `cellctl token` above.");
  }
  ui.lastCommand = performance.now();
  await takeLock();
  const r = await fetch(path, { method, headers: headers(),
    body: body === undefined ? undefined : JSON.stringify(body) });
  if (!r.ok) {
    const answer = await r.json().catch(() => ({}));
    if (r.status === 423 && answer.broken) throw lockBroken(answer.broken);
    throw refused(r.status, typeof answer.detail === "string" ? answer.detail : r.statusText);
  }
  return r.status === 204 ? null : r.json();
}

async function act(what, fn) {
  // every button: run the command, report the outcome, refresh what it changed
  try {
    say(`${what}…`);
    const answer = await fn();
    // a job command says what it did (a pause asked of a running job takes effect at the next step)
    say(answer && typeof answer.message === "string" ? answer.message : `${what}: done`);
  } catch (err) {
    say(err.message, true);
  }
  refreshJobs();
  refreshCell();
}

async function releaseLock() {
  if (!ui.lockId) return;
  await fetch("/lock", { method: "DELETE", headers: headers() });
  dropLock();
  refreshCell();
}

// -- cell status ------------------------------------------------------------------------------

async function refreshCell() {
  let cell;
  try { cell = await get("/cell"); } catch { return; }
  ui.cell = cell;
  $("#cell-name").textContent = `· ${cell.cell}${cell.simulated ? " (simulated)" : ""}`;
  document.title = `cellctl · ${cell.cell}`;
  const rows = cell.devices.map((d) => el("tr", {},
    el("td", {}, d.name), el("td", {}, d.kind), el("td", {}, d.backend),
    el("td", { className: d.state === "ready" ? "" : "state-faulted", title: d.error || "" },
      d.state + (d.error ? ` (${d.error})` : ""))));
  $("#devices tbody").replaceChildren(...rows);
  const p = cell.arm_pose;
  $("#arm-pose").textContent = p ? `x ${fmt(p.x_mm, 3)} mm, y ${fmt(p.y_mm, 3)} mm, z ${fmt(p.z_mm, 3)} mm, ` +
    `α ${fmt(p.alpha_deg, 2)}°` : "unknown";
  const lock = cell.lock;
  $("#lock-holder").textContent = lock.held ? `${lock.holder}${lock.holder === ui.holder ? " (this console)" : ""}, ` +
    `${Math.round(lock.expires_in_s)} s left` : "free";
  $("#live-job").textContent = cell.job ? `job ${cell.job}` : "none";
  const schedule = cell.health_schedule;
  $("#next-check").textContent = schedule ? `${schedule.next_check} (every ${schedule.every_h} h)` +
    (schedule.waiting_for ? `, waiting: ${schedule.waiting_for}` : "") : "not scheduled";
  const disk = cell.disk;  // below the floor, new jobs and resumptions are refused (store.min_free_mb)
  $("#disk-free").textContent = disk ? `${fmt(disk.free_mb, 0)} MB free of ${fmt(disk.total_mb, 0)} MB` +
    (disk.low ? `: below the ${disk.min_free_mb} MB floor, no job can start; ` +
      `free space on its filesystem (${disk.filesystem})` : "")
    : "unknown";
  $("#disk-free").className = disk && disk.low ? "state-faulted" : "";
  $("#seed-label").hidden = !cell.simulated;
  ensureCameras(cell.cameras);
}

// -- routines form ------------------------------------------------------------------------------

function fieldKind(spec) {
  if (spec.$ref) return "json";
  if (spec.enum) return "enum";
  const types = spec.anyOf ? spec.anyOf.filter((s) => s.type !== "null") : [spec];
  if (types.length !== 1) return "json";
  const t = types[0];
  if (t.enum) return "enum";
  return { integer: "integer", number: "number", boolean: "boolean", string: "string" }[t.type] || "json";
}

function fieldInput(name, spec, value) {
  const kind = fieldKind(spec);
  const plain = spec.anyOf ? spec.anyOf.find((s) => s.type !== "null") : spec;
  let input;
  if (kind === "enum") {
    input = el("select", {}, ...plain.enum.map((v) => el("option", { value: JSON.stringify(v) }, String(v))));
    input.value = JSON.stringify(value);
  } else if (kind === "boolean") {
    input = el("input", { type: "checkbox", checked: !!value });
  } else if (kind === "integer" || kind === "number") {
    input = el("input", { type: "number", step: kind === "integer" ? "1" : "any",
      value: value ?? "" });
    if (plain.minimum !== undefined) input.min = plain.minimum;
    if (plain.maximum !== undefined) input.max = plain.maximum;
  } else if (kind === "string") {
    input = el("input", { type: "text", value: value ?? "" });
  } else {
    input = el("input", { type: "text", value: value === undefined ? "" : JSON.stringify(value) });
  }
  input.name = name;
  input.dataset.kind = kind;
  input.dataset.initial = currentText(input);
  input.title = spec.description || "";
  input.addEventListener("input", () => input.classList.toggle("changed", currentText(input) !== input.dataset.initial));
  input.addEventListener("change", () => input.classList.toggle("changed", currentText(input) !== input.dataset.initial));
  return input;
}

function currentText(input) {
  return input.type === "checkbox" ? String(input.checked) : input.value;
}

function parseField(input) {
  const kind = input.dataset.kind, text = input.value.trim();
  if (kind === "boolean") return input.checked;
  if (kind === "enum") return JSON.parse(input.value);
  if (kind === "integer" || kind === "number") {
    if (text === "") return null;
    const n = Number(text);
    if (!isFinite(n) || (kind === "integer" && !Number.isInteger(n))) {
      throw new ApiError(422, `params.${input.name}: ${JSON.stringify(text)} is not ${kind === "integer" ? "an integer" : "a number"}`);
    }
    return n;
  }
  if (kind === "string") return input.value;
  try { return JSON.parse(text); } catch {
    throw new ApiError(422, `params.${input.name}: ${JSON.stringify(text)} is not JSON (e.g. [1.0, 2.0])`);
  }
}

function buildForm() {
  const name = $("#routine").value;
  const box = $("#params");
  box.replaceChildren();
  $("#plan-box").hidden = true;
  $("#plan").hidden = !(name && ui.routines.routines[name]?.previews);
  if (!name) {
    $("#routine-note").textContent = "Choose what to run: a routine, or a sequence of them.";
    return;
  }
  if (ui.routines.sequences[name]) {
    $("#routine-note").textContent = `A sequence: ${ui.routines.sequences[name].join(" → ")}. ` +
      "Each routine runs with the cell file's parameters.";
    return;
  }
  const { params: schema, defaults } = ui.routines.routines[name];
  $("#routine-note").textContent = schema.description || "";
  for (const [key, spec] of Object.entries(schema.properties || {})) {
    const value = key in defaults ? defaults[key] : spec.default;
    const input = fieldInput(key, spec, value);
    input.id = `param-${key}`;
    const unit = unitOf(key, spec);
    // the name as the cell file and the CLI spell it, what the declaration says it is, the input and its unit
    box.append(el("label", { htmlFor: input.id, className: "param" }, el("code", {}, key),
      el("span", { className: "param-description" }, spec.description || "")),
    el("span", { className: "param-input" }, input, el("span", { className: "unit" }, unit)));
  }
}

// A parameter's unit: its declaration's, else the one its name carries (x_mm, err_um, alpha_deg: the convention)
const UNITS = { mm: "mm", um: "µm", m: "m", in: "in", deg: "°", s: "s", ms: "ms", h: "h", px: "px", pct: "%" };
function unitOf(name, spec) {
  return spec.unit || UNITS[name.match(/_([a-z]+)$/)?.[1]] || "";
}

async function loadRoutines() {
  ui.routines = await get("/routines");
  const select = $("#routine");
  const group = (label, names) => el("optgroup", { label }, ...names.map((n) => el("option", { value: n }, n)));
  // nothing chosen at first: the operator picks what the cell will do (the form refuses to start without)
  select.replaceChildren(el("option", { value: "", disabled: true }, "choose…"),
    group("routines", Object.keys(ui.routines.routines)), group("sequences", Object.keys(ui.routines.sequences)));
  select.value = "";
  buildForm();
}

// the parameters the operator changed from the cell file's (the rest the daemon takes from the cell file)
function formParams() {
  const params = {};
  for (const input of $("#params").querySelectorAll("[name]")) {
    if (currentText(input) !== input.dataset.initial) params[input.name] = parseField(input);
  }
  return params;
}

// A routine that plans its own motion shows it before anything moves (GET: read-only, no lock, no token)
async function showPlan() {
  const name = $("#routine").value;
  try {
    say("Planning…");
    const plan = await get(`/routines/${encodeURIComponent(name)}/plan?params=` +
      encodeURIComponent(JSON.stringify(formParams())));
    const parts = [];
    for (const t of plan.tables) {
      parts.push(el("h3", {}, t.title), tableOf(t.columns, t.rows.map((row) => row.map(cellText))));
      if (t.note) parts.push(el("p", { className: "note" }, t.note));
    }
    $("#plan-box").replaceChildren(...parts);
    $("#plan-box").hidden = false;
    say(`The plan of ${name}: nothing has moved`);
  } catch (err) {
    $("#plan-box").replaceChildren(el("p", { className: "error" }, err.message));
    $("#plan-box").hidden = false;
    say(err.message, true);
  }
}

async function startRoutine(event) {
  event.preventDefault();
  await act("Starting the routine", async () => {
    const params = formParams();
    const body = { routine: $("#routine").value, params };
    const seed = $("#seed").value.trim();
    if (seed !== "" && !$("#seed-label").hidden) body.seed = Number(seed);
    if ($("#save-images").checked) body.save_images = true;  // only when asked, as the CLI's --save-images
    const job = await command("POST", "/jobs", body);
    select(job.id);
  });
}

// -- jobs -----------------------------------------------------------------------------------------

const LIVE = new Set(["queued", "running", "paused", "faulted"]);
const ENDED = new Set(["done", "aborted", "faulted"]);  // faulted: ended for now (it resumes after an ack)

async function refreshJobs() {
  let list;
  try { list = (await get("/jobs?limit=30")).jobs; } catch { return; }
  ui.jobs = new Map(list.map((j) => [j.id, j]));
  const rows = list.map((j) => {
    const p = ui.progress.get(j.id) || j.progress;
    const row = el("tr", { className: j.id === ui.selected ? "selected" : "" },
      el("td", {}, j.id), el("td", {}, j.routine), el("td", { className: `state-${j.state}` }, j.state),
      el("td", {}, p ? `${p.step} / ${p.total}` : "–"), el("td", {}, j.updated.replace("T", " ").slice(0, 19)));
    row.dataset.job = j.id;
    row.addEventListener("click", () => select(j.id));
    return row;
  });
  $("#jobs tbody").replaceChildren(...rows);
  if (ui.selected === null && list.length) select((list.find((j) => LIVE.has(j.state)) || list[0]).id);
  else if (ui.selected !== null) showJob();
}

function select(id) {
  ui.selected = id;
  for (const row of document.querySelectorAll("#jobs tbody tr")) {
    row.classList.toggle("selected", Number(row.dataset.job) === id);
  }
  showJob();
}

async function showJob() {
  const id = ui.selected;
  if (id === null) return;
  let job;
  try { job = await get(`/jobs/${id}`); } catch (err) { say(err.message, true); return; }
  if (id !== ui.selected) return;
  ui.jobs.set(id, job);
  $("#job-title").textContent = `${job.id}: ${job.routine}`;
  const state = $("#job-state");
  state.textContent = job.state;
  state.className = `state-${job.state}`;
  $("#job-reason").textContent = job.reason ? `(${job.reason})` : "";
  $("#job-images").hidden = !job.save_images;
  $("#job-run-dir").textContent = job.run_dir;
  showProgress(ui.progress.get(id) || job.progress, job.state);
  const can = {
    pause: ["queued", "running"], "pause-now": ["running"], resume: ["paused"], ack: ["faulted"],
    abort: ["queued", "running", "paused", "faulted"],
  };
  for (const [button, states] of Object.entries(can)) $(`#${button}`).disabled = !states.includes(job.state);
  if (job.state === "done") showResults(job);
  else if (ui.resultsShown !== null && !ui.resultsShown.startsWith(`${id}:`)) clearResults();
}

function showProgress(p, state) {
  if (!p) {
    $("#job-step").textContent = "step – / –";
    $("#job-progress").value = 0;
    for (const id of ["#job-cell-time", "#job-eta", "#job-residual"]) $(id).textContent = "–";
    return;
  }
  const seq = p.item ? ` of ${p.item} (${p.routine})` : "";
  $("#job-step").textContent = `step ${p.step} / ${p.total}${seq}` +
    (p.operator ? ` · waiting for operator input (request ${p.operator.request})` : "");
  $("#job-progress").max = Math.max(p.total, 1);
  $("#job-progress").value = p.step;
  $("#job-cell-time").textContent = fmt(p.cell_time_s, 1, " s");
  // what is left to run: nothing, once the job is done or aborted (its last progress still carries an estimate)
  $("#job-eta").textContent = ["done", "aborted"].includes(state) ? "–" : fmt(p.eta_cell_s, 1, " s of cell time");
  $("#job-residual").textContent = fmt(p.residual_um, 2, " µm");
}

function onEvent(kind, data) {
  if (kind === "progress") {
    ui.progress.set(data.job, data);
    if (ui.selected === null || (data.job !== ui.selected && !LIVE.has(ui.jobs.get(ui.selected)?.state))) {
      select(data.job);  // follow the live job unless the operator is looking at another live one
    }
    if (data.job === ui.selected) showProgress(data, ui.jobs.get(data.job)?.state);
    const cell = document.querySelector(`#jobs tr[data-job="${data.job}"] td:nth-child(4)`);
    if (cell) cell.textContent = `${data.step} / ${data.total}`;
  } else if (kind === "state") {
    if (data.state === "running" && !LIVE.has(ui.jobs.get(ui.selected)?.state)) ui.selected = data.job;
    refreshJobs();
    refreshCell();
    refreshOperator();
    // a job that ended (a sequence aborted or faulted may have stored and activated calibrations already)
    if (ENDED.has(data.state)) { refreshCalibrations(); refreshHealth(); }
  } else if (kind === "health") {
    refreshHealth();
  } else if (kind === "lock") {
    if (data.state === "broken" && ui.lockId && data.holder === ui.holder) lockBroken(data);
    refreshCell();
  } else if (kind === "operator") {
    if (data.state === "waiting") say(`Operator input wanted (request ${data.request}): ${data.instruction}`);
    refreshOperator();
  }
}

function listen() {
  const source = new EventSource("/events");
  const conn = $("#conn");
  source.onopen = () => { conn.textContent = "live"; conn.className = "pill live"; };
  source.onerror = () => { conn.textContent = "reconnecting…"; conn.className = "pill"; };
  for (const kind of ["progress", "state", "operator", "health", "lock"]) {
    source.addEventListener(kind, (e) => onEvent(kind, JSON.parse(e.data)));
  }
}

// -- results ----------------------------------------------------------------------------------------

function clearResults() {
  ui.resultsShown = null;
  $("#results-title").textContent = "";
  $("#plot-figure").hidden = true;
  $("#item-label").hidden = true;
  $("#report").replaceChildren();
  $("#results-note").textContent = "Results appear here when the selected job is done.";
}

async function showResults(job) {
  const items = ui.routines?.sequences[job.routine] || null;
  const itemSelect = $("#item");
  if (items && itemSelect.dataset.job !== String(job.id)) {
    itemSelect.replaceChildren(...items.map((i) => el("option", { value: i }, i)));
    itemSelect.dataset.job = String(job.id);
  }
  const item = items ? itemSelect.value : "";
  const key = `${job.id}:${item}`;
  if (ui.resultsShown === key) return;
  ui.resultsShown = key;
  $("#item-label").hidden = !items;
  $("#results-title").textContent = `of job ${job.id}${item ? ` · ${item}` : ""}`;
  const q = item ? `?item=${encodeURIComponent(item)}` : "";
  const plot = $("#plot");
  plot.onerror = () => { $("#plot-figure").hidden = true; };
  plot.onload = () => { $("#plot-figure").hidden = false; };
  $("#plot-figure").hidden = true;
  $("#results-note").textContent = "";
  try {
    const result = await get(`/jobs/${job.id}/result${q}`);
    // a routine without a residual plot (a check) names none: not asked for, so no 404 in the browser's log
    if (result.files?.plot) plot.src = `/jobs/${job.id}/plot${q}`;
    const r = await fetch(`/jobs/${job.id}/report${q}`);
    renderResults(result, r.ok ? await r.text() : "");
  } catch (err) {
    $("#report").replaceChildren(el("p", { className: "note" }, `No results: ${err.message}`));
  }
}

// The routine's own tables and charts as result.json gives them (whatever the routine), then the whole
// report folded below, built from its Markdown; everything as text (never as HTML).
function renderResults(result, markdown) {
  const parts = [];
  for (const t of result.tables || []) {
    parts.push(el("h3", {}, t.title), tableOf(t.columns, t.rows.map((row) => row.map(cellText))));
    if (t.note) parts.push(el("p", { className: "note" }, t.note));
  }
  for (const c of result.charts || []) parts.push(chartOf(c));
  $("#report").replaceChildren(...parts, el("details", {}, el("summary", {}, "The whole report"),
    ...reportNodes(markdown)));
}

// A cell as report.md shows it: a float as the routine rounded it (4 significant digits if it did not).
function cellText(v) {
  if (v === null || v === undefined) return "-";
  if (typeof v === "number" && !Number.isInteger(v)) return String(v).length <= 7 ? String(v) : v.toPrecision(4);
  return String(v);
}

function tableOf(columns, rows) {
  return el("table", { className: "report-table" },
    el("thead", {}, el("tr", {}, ...columns.map((c) => el("th", {}, c)))),
    el("tbody", {}, ...rows.map((row) => el("tr", {}, ...row.map((c) => el("td", {}, c))))));
}

function svg(tag, attrs = {}, ...children) {
  const node = document.createElementNS("http://www.w3.org/2000/svg", tag);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, v);
  for (const c of children) node.append(c instanceof Node ? c : String(c));
  return node;
}

const COLOURS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f"];

// A routine's line chart ({title, x_label, y_label, series: {label: [[x, y(, ±err)], ...]}, log_y, x_from})
// drawn as SVG; a point's third value, if any, is drawn as an error bar.
function chartOf(chart) {
  const W = 520, H = 300, left = 56, right = 130, top = 24, bottom = 40, inset = 8;
  const ty = (y) => (chart.log_y ? Math.log10(y) : y);
  const series = Object.entries(chart.series || {}).map(([label, pts]) =>
    [label, pts.filter(([x, y]) => isFinite(x) && isFinite(y) && (!chart.log_y || y > 0))]);
  const all = series.flatMap(([, pts]) => pts);
  const figure = el("figure", { className: "chart" });
  if (!all.length) return figure;
  const err = ([, y, e]) => (isFinite(e) && e > 0 && (!chart.log_y || y - e > 0) ? e : 0);
  // one value (a single check) spans a unit beyond it, the way the axis runs: never a span around a lone point
  const span = (v, from) => {
    const lo = Math.min(...v, from ?? Infinity), hi = Math.max(...v);
    return hi > lo ? [lo, hi] : from === undefined ? [lo - 1, hi + 1] : [lo, lo + 1];
  };
  const [x0, x1] = span(all.map(([x]) => x), chart.x_from);
  const [y0, y1] = span(all.flatMap((p) => [ty(p[1] - err(p)), ty(p[1] + err(p))]));
  const px = (x) => left + inset + (x - x0) / (x1 - x0) * (W - left - right - 2 * inset);
  const pyT = (t) => H - bottom - inset - (t - y0) / (y1 - y0) * (H - top - bottom - 2 * inset);  // t: as ty gives
  const py = (y) => pyT(ty(y));
  const label = (v) => (chart.log_y ? (10 ** v).toPrecision(2) : Number(v.toPrecision(3)));
  const g = svg("svg", { viewBox: `0 0 ${W} ${H}`, width: "100%", style: "max-width: 640px", role: "img", "font-size": "11" },
    svg("text", { x: left, y: 14, "font-weight": "bold" }, chart.title || chart.name),
    svg("rect", { x: left, y: top, width: W - left - right, height: H - top - bottom, fill: "none", stroke: "#999" }),
    svg("text", { x: px(x0), y: H - bottom + 14, "text-anchor": "middle" }, label(x0)),
    svg("text", { x: px(x1), y: H - bottom + 14, "text-anchor": "middle" }, label(x1)),
    svg("text", { x: left - 4, y: pyT(y0) + 4, "text-anchor": "end" }, label(y0)),
    svg("text", { x: left - 4, y: pyT(y1) + 4, "text-anchor": "end" }, label(y1)),
    svg("text", { x: (left + W - right) / 2, y: H - 6, "text-anchor": "middle" }, chart.x_label || ""),
    svg("text", { x: 12, y: (top + H - bottom) / 2, transform: `rotate(-90 12 ${(top + H - bottom) / 2})`, "text-anchor": "middle" }, chart.y_label || ""));
  if (!chart.log_y && y0 < 0 && y1 > 0) {  // zero, where the values go both ways (a drift, an error)
    g.append(svg("line", { x1: left, x2: W - right, y1: pyT(0), y2: pyT(0), stroke: "#bbb", "stroke-dasharray": "4 3" }));
  }
  series.forEach(([name, pts], i) => {
    const colour = COLOURS[i % COLOURS.length];
    const bars = pts.filter((p) => err(p) > 0).map((p) => {
      const [x, y] = p, e = err(p), cx = px(x), lo = py(y - e), hi = py(y + e);
      return svg("path", { class: "error-bar", stroke: colour, fill: "none",
        d: `M${cx},${lo}V${hi}M${cx - 3},${lo}H${cx + 3}M${cx - 3},${hi}H${cx + 3}` });
    });
    g.append(svg("polyline", { points: pts.map(([x, y]) => `${px(x)},${py(y)}`).join(" "), fill: "none", stroke: colour }),
      ...bars, ...pts.map(([x, y]) => svg("circle", { cx: px(x), cy: py(y), r: 2.5, fill: colour })),
      svg("text", { x: W - right + 8, y: top + 12 + 14 * i, fill: colour }, name));
  });
  figure.append(g);
  return figure;
}

// The whole report from its Markdown: headings, tables and paragraphs, as text.
function reportNodes(markdown) {
  const nodes = [];
  let table = null;
  const cells = (line) => line.trim().replace(/^\|/, "").replace(/\|$/, "").split("|").map((c) => c.trim());
  for (const line of markdown.split("\n")) {
    const text = line.trim();
    if (text.startsWith("|")) {
      if (/^:?-{2,}/.test(text.replace(/^\|/, "").trim())) continue;  // the |---|---| rule
      if (!table) {
        table = tableOf(cells(text), []);
        nodes.push(table);
      } else {
        table.tBodies[0].append(el("tr", {}, ...cells(text).map((c) => el("td", {}, c))));
      }
      continue;
    }
    table = null;
    const h = text.match(/^#{1,4}\s+(.*)/);
    if (h) nodes.push(el("h3", {}, h[1]));
    else if (text && !text.startsWith("![")) nodes.push(el("p", { className: "note" }, text.replace(/[*`]/g, "")));
  }
  return nodes;
}

// -- cameras ---------------------------------------------------------------------------------------

const cameraLoops = new Map();

function ensureCameras(names) {
  for (const name of names) {
    if (cameraLoops.has(name)) continue;
    const img = el("img", { alt: "" });  // the caption names it (and says why, when there is no frame)
    const caption = el("figcaption", {}, name);
    const figure = el("figure", { id: `camera-${name}` }, img, caption);
    $("#cameras").append(figure);
    cameraLoops.set(name, true);
    pollCamera(name, img, caption);
  }
}

async function pollCamera(name, img, caption) {
  // one request at a time per camera; faster while a job runs (the daemon then only re-sends its frame)
  for (;;) {
    if (!document.hidden) {
      const layers = [...document.querySelectorAll("#layers input:checked")].map((i) => `layers=${i.value}`);
      const width = Math.min(1280, Math.max(320, Math.round(img.clientWidth * (window.devicePixelRatio || 1))));
      try {
        const r = await fetch(`/cameras/${encodeURIComponent(name)}/overlay.png?width=${width}&${layers.join("&")}`);
        if (!r.ok) throw new ApiError(r.status, await detailOf(r));
        const url = URL.createObjectURL(await r.blob());
        const old = img.src;
        img.src = url;
        if (old.startsWith("blob:")) URL.revokeObjectURL(old);
        const at = new Date(Number(r.headers.get("X-Captured")) * 1000).toLocaleTimeString();
        caption.textContent = `${name} · frame ${r.headers.get("X-Frame-Id")} · ${at}`;
      } catch (err) {
        caption.textContent = `${name}: ${err.message}`;
      }
    }
    await new Promise((done) => setTimeout(done, ui.cell?.job ? 1000 : 4000));
  }
}

// -- calibrations ------------------------------------------------------------------------------------

async function refreshCalibrations() {
  let list;
  try { list = (await get("/calibrations")).calibrations; } catch { return; }
  const rows = list.slice().reverse().map((c) => {
    const v = c.stats?.verification || {};
    const activate = el("button", { type: "button", disabled: c.active }, c.active ? "active" : "Activate");
    activate.addEventListener("click", () => act(`Activating calibration ${c.id}`, async () => {
      await command("POST", `/calibrations/${c.id}/activate`);
      await refreshCalibrations();
    }));
    const exports = el("span", {}, el("a", { href: `/calibrations/${c.id}/export?format=json` }, "JSON"), " · ",
      el("a", { href: `/calibrations/${c.id}/export?format=opencv` }, "OpenCV"));
    return el("tr", {}, el("td", {}, c.id), el("td", {}, c.target), el("td", {}, c.routine), el("td", {}, c.version),
      el("td", {}, c.created), el("td", {}, `${fmt(v.mean_um, 2)} / ${fmt(v.max_um, 2)}`),
      el("td", {}, activate), el("td", {}, exports));
  });
  $("#calibrations tbody").replaceChildren(...rows);
}

// -- health: the last check of each target, a drift alarm with the action it calls for, the trend -------------

function remedy(target, action) {
  // the action a check named, as the job that carries it out: a touch-up (the judging routine again, update=true) or the
  // routine to recalibrate with
  const routine = action.match(/run (\S+)$/);
  if (routine) return { label: `Recalibrate ${target}: ${routine[1]}`, job: { routine: routine[1], params: {} } };
  if (action.startsWith("touch-up")) {
    return { label: `Touch up ${target}`, job: { routine: ui.routines.judge, params: { targets: target, update: true } } };
  }
  return null;
}

async function refreshHealth() {
  let targets;
  try { targets = (await get("/health/calibrations")).targets; } catch { return; }
  const rows = [], alarms = [], series = {};
  let t0 = null;
  for (const [target, h] of Object.entries(targets)) {
    const last = h.last_check;
    const d = last?.drift || {};
    const std = (k) => d[k.replace("_um", "_std_um")];
    rows.push(el("tr", {}, el("td", {}, target), el("td", {}, `${h.active.id} (v${h.active.version}, ${h.active.routine})`),
      el("td", {}, last ? last.created : "never"),
      el("td", { className: h.verdict === "drift" ? "state-faulted" : "" }, h.verdict),
      el("td", {}, last ? `${fmt(d.dx_um, 2)} ± ${fmt(std("dx_um"), 2)}` : "–"),
      el("td", {}, last ? `${fmt(d.dy_um, 2)} ± ${fmt(std("dy_um"), 2)}` : "–"),
      el("td", {}, last ? last.p_value.toPrecision(3) : "–"), el("td", {}, last ? last.action : "")));
    if (h.verdict === "drift" && last) alarms.push([target, last.action]);
    for (const c of h.history) {
      const t = Date.parse(c.created.replace(/([+-]\d\d)(\d\d)$/, "$1:$2")) / 3.6e6;
      t0 = t0 === null ? t : Math.min(t0, t);
      for (const axis of ["dx_um", "dy_um"]) {
        (series[`${target} ${axis.slice(0, 2)}`] ||= []).push([t, c.drift[axis], c.drift[axis.replace("_um", "_std_um")]]);
      }
    }
  }
  $("#health tbody").replaceChildren(...rows);
  for (const pts of Object.values(series)) for (const p of pts) p[0] -= t0;
  $("#health-chart").replaceChildren(Object.keys(series).length ? chartOf({ name: "drift",
    title: "Drift at each check (± 1 σ)", x_label: "hours since the first check", y_label: "µm", x_from: 0,
    series }) : "");
  const alarm = $("#health-alarm");
  alarm.hidden = !alarms.length;
  $("#health-alarm-text").textContent = alarms.map(([t, a]) => `${t}: ${a}`).join(" · ");
  $("#health-actions").replaceChildren(...alarms.map(([target, action]) => remedy(target, action)).filter(Boolean)
    .map(({ label, job }) => {
      const button = el("button", { type: "button", className: "remedy" }, label);
      button.addEventListener("click", () => act(label, async () => {
        const submitted = await command("POST", "/jobs", job);
        select(submitted.id);
      }));
      return button;
    }));
}

// -- operator requests: what the web operator waits for (clicks on a frame, or an instruction to confirm) --------

const op = { req: null, img: null, pairs: [], selected: null, hover: null, view: null };
const PICK_PX = 24;  // a model point is picked when the click is within this many screen pixels of it

async function refreshOperator() {
  let state;
  try { state = await get("/operator/request"); } catch { return; }
  const req = state.request;
  if (!req) { if (op.req) closeOperator(); return; }
  if (!op.req || op.req.id !== req.id) openOperator(req);
}

function closeOperator() {
  Object.assign(op, { req: null, img: null, pairs: [], selected: null, hover: null, view: null });
  $("#operator-panel").hidden = true;
}

function openOperator(req) {
  Object.assign(op, { req, img: null, pairs: [], selected: null, hover: null });
  $("#operator-panel").hidden = false;
  // the job waits for this person: bring the request into sight (a long parameter form can push it below the fold)
  $("#operator-panel").scrollIntoView({ block: "start" });
  $("#op-title").textContent = `· request ${req.id}${req.job ? ` of job ${req.job}` : ""}`;
  $("#op-instruction").textContent = req.instruction;
  const clicks = req.answer_with === "clicks";
  $("#op-clicks").hidden = !clicks;
  $("#op-confirm").hidden = clicks;
  if (clicks) {
    setView(req);
    const img = new Image();
    img.onload = () => { if (op.req === req) { op.img = img; drawOperator(); } };
    img.src = req.frame_url;
    drawOperator();
  }
  showPairs();
}

// The canvas shows the frame and, around it, room for projected points that fall outside it.
// Canvas coordinates: x = (u - left) * k with u in image pixels (OpenCV: integers at pixel centres).
function setView(req) {
  const [w, h] = req.image_size;
  const us = req.model_points.map((p) => p.u), vs = req.model_points.map((p) => p.v);
  const lo = (vals, size) => Math.max(-size / 2, Math.min(-0.5, Math.min(...vals) - 20));
  const hi = (vals, size) => Math.min(1.5 * size, Math.max(size - 0.5, Math.max(...vals) + 20));
  const left = lo(us, w), top = lo(vs, h), spanU = hi(us, w) - left, spanV = hi(vs, h) - top;
  const k = 1280 / spanU;
  const c = $("#op-canvas");
  c.width = Math.round(spanU * k);
  c.height = Math.round(spanV * k);
  Object.assign(c.dataset, { left, top, spanU, spanV });  // for whoever maps image pixels to the screen
  op.view = { left, top, spanU, spanV, k, w, h };
}

function toImage(event) {
  const r = $("#op-canvas").getBoundingClientRect(), v = op.view;
  return { u: v.left + (event.clientX - r.left) / r.width * v.spanU,
           v: v.top + (event.clientY - r.top) / r.height * v.spanV };
}

function nearestModelPoint(event) {
  const r = $("#op-canvas").getBoundingClientRect(), v = op.view;
  const taken = new Set(op.pairs.map((p) => p.model_index));
  let best = null, bestD = PICK_PX;
  for (const p of op.req.model_points) {
    if (taken.has(p.index)) continue;
    const sx = r.left + (p.u - v.left) / v.spanU * r.width, sy = r.top + (p.v - v.top) / v.spanV * r.height;
    const d = Math.hypot(sx - event.clientX, sy - event.clientY);
    if (d < bestD) { best = p.index; bestD = d; }
  }
  return best;
}

function drawOperator() {
  const req = op.req, c = $("#op-canvas"), g = c.getContext("2d"), v = op.view;
  if (!req || !v) return;
  const X = (u) => (u - v.left) * v.k, Y = (vv) => (vv - v.top) * v.k;
  const pts = new Map(req.model_points.map((p) => [p.index, p]));
  g.fillStyle = "#262b33";
  g.fillRect(0, 0, c.width, c.height);
  if (op.img) {
    g.imageSmoothingEnabled = false;
    g.drawImage(op.img, X(-0.5), Y(-0.5), v.w * v.k, v.h * v.k);
  }
  g.strokeStyle = "#8a94a6"; g.lineWidth = 1;
  g.strokeRect(X(-0.5), Y(-0.5), v.w * v.k, v.h * v.k);
  g.strokeStyle = req.colour; g.globalAlpha = 0.75; g.lineWidth = 2;
  for (const [a, b] of req.edges || []) {
    if (!pts.has(a) || !pts.has(b)) continue;
    g.beginPath(); g.moveTo(X(pts.get(a).u), Y(pts.get(a).v)); g.lineTo(X(pts.get(b).u), Y(pts.get(b).v)); g.stroke();
  }
  g.globalAlpha = 1;
  const paired = new Set(op.pairs.map((p) => p.model_index));
  for (const pair of op.pairs) {  // model point -> its image point
    const m = pts.get(pair.model_index);
    g.strokeStyle = "#ffd54f"; g.lineWidth = 1.5; g.setLineDash([6, 4]);
    g.beginPath(); g.moveTo(X(m.u), Y(m.v)); g.lineTo(X(pair.u), Y(pair.v)); g.stroke();
    g.setLineDash([]);
    const x = X(pair.u), y = Y(pair.v);
    g.strokeStyle = "#ffffff"; g.lineWidth = 2.5;
    g.beginPath(); g.moveTo(x - 9, y); g.lineTo(x + 9, y); g.moveTo(x, y - 9); g.lineTo(x, y + 9); g.stroke();
  }
  g.font = "bold 15px system-ui, sans-serif";
  for (const p of req.model_points) {
    const x = X(p.u), y = Y(p.v);
    g.beginPath(); g.arc(x, y, 7, 0, 2 * Math.PI);
    if (paired.has(p.index)) { g.fillStyle = req.colour; g.fill(); } else { g.strokeStyle = req.colour; g.lineWidth = 3; g.stroke(); }
    g.fillStyle = req.colour;
    g.fillText(String(p.index), x + 9, y - 9);
  }
  for (const [index, width] of [[op.hover, 2], [op.selected, 4]]) {
    if (index === null || !pts.has(index)) continue;
    const p = pts.get(index);
    g.strokeStyle = "#ffeb3b"; g.lineWidth = width;
    g.beginPath(); g.arc(X(p.u), Y(p.v), 13, 0, 2 * Math.PI); g.stroke();
  }
}

function showPairs() {
  const req = op.req;
  if (!req || req.answer_with !== "clicks") return;
  $("#op-pairs").replaceChildren(...op.pairs.map((p) =>
    el("li", {}, `point ${p.model_index} → (${p.u.toFixed(1)}, ${p.v.toFixed(1)})`)));
  $("#op-count").textContent = `${op.pairs.length} pair${op.pairs.length === 1 ? "" : "s"}; at least ${req.at_least} ` +
    `needed, spread over the ${req.object}`;
  $("#op-submit").disabled = op.pairs.length < req.at_least;
  $("#op-undo").disabled = !op.pairs.length && op.selected === null;
  hint(op.selected === null
    ? "Step 1: click a model point (a numbered circle) on the overlay; the nearest one is highlighted."
    : `Step 2: click where model point ${op.selected} is in the image (Undo to pick another model point).`);
  drawOperator();
}

function canvasMove(event) {
  if (!op.req || op.selected !== null) return;
  const hover = nearestModelPoint(event);
  if (hover !== op.hover) { op.hover = hover; drawOperator(); }
}

function canvasClick(event) {
  if (!op.req || !op.view) return;
  if (op.selected === null) {
    const index = nearestModelPoint(event);
    if (index === null) { hint("Click on (or next to) a model point first: one of the numbered circles.", true); return; }
    op.selected = index; op.hover = null;
  } else {
    const { u, v } = toImage(event);
    if (u < -0.5 || v < -0.5 || u > op.view.w - 0.5 || v > op.view.h - 0.5) {
      hint("That is outside the image: click where the model point is in the picture.", true); return;
    }
    op.pairs.push({ model_index: op.selected, u: Math.round(u * 100) / 100, v: Math.round(v * 100) / 100 });
    op.selected = null;
  }
  showPairs();
}

function hint(text, isError = false) {
  $("#op-hint").textContent = text;
  $("#op-hint").className = isError ? "note error" : "note";
}

function undoPair() {
  if (op.selected !== null) op.selected = null; else op.pairs.pop();
  showPairs();
}

async function answerOperator(what, path, body) {
  const req = op.req;
  if (!req) return;
  await act(`${what} (request ${req.id})`, async () => {
    await command("POST", path, body);
    if (op.req === req) closeOperator();
  });
  refreshOperator();
}

function wireOperator() {
  const c = $("#op-canvas");
  c.addEventListener("mousemove", canvasMove);
  c.addEventListener("mouseleave", () => { op.hover = null; drawOperator(); });
  c.addEventListener("click", canvasClick);
  document.addEventListener("keydown", (e) => {
    if (op.req && e.key === "Escape" && op.selected !== null) { op.selected = null; showPairs(); }
  });
  $("#op-undo").addEventListener("click", undoPair);
  $("#op-submit").addEventListener("click", () => answerOperator(`Submitting ${op.pairs.length} pairs`,
    op.req.answer_url, { clicks: op.pairs }));
  $("#op-decline-clicks").addEventListener("click", () => {
    const reason = window.prompt("Why can the points not be clicked? (kept with the job)", "too few points visible");
    if (reason !== null) answerOperator("Declining", op.req.decline_url, { reason });
  });
  $("#op-done").addEventListener("click", () => answerOperator("Done", op.req.done_url));
  $("#op-decline").addEventListener("click", () => {
    const reason = window.prompt("Why can it not be done? (kept with the job)", "");
    if (reason !== null) answerOperator("Declining", op.req.decline_url, { reason });
  });
}

// -- start -------------------------------------------------------------------------------------------

function wire() {
  wireOperator();
  $("#token-form").addEventListener("submit", (e) => {
    e.preventDefault();
    const token = $("#token-input").value.trim();
    if (!token) return;
    ui.token = token;
    store.setItem("cellctl.token", token);
    $("#token-input").value = "";
    showToken();
    say("Token kept for this browser tab; it is checked with the first command.");
  });
  $("#forget-token").addEventListener("click", async () => { await releaseLock().catch(() => {}); forgetToken(); });
  $("#release-lock").addEventListener("click", () => act("Releasing the lock", releaseLock));
  $("#run-form").addEventListener("submit", startRoutine);
  $("#plan").addEventListener("click", showPlan);
  $("#routine").addEventListener("change", buildForm);
  $("#item").addEventListener("change", () => { const job = ui.jobs.get(ui.selected); if (job) showResults(job); });
  const jobCommand = (label, path, body) => () => act(`${label} job ${ui.selected}`,
    () => command("POST", `/jobs/${ui.selected}/${path}`, body));
  $("#pause").addEventListener("click", jobCommand("Pausing", "pause", { mode: "deferred" }));
  $("#pause-now").addEventListener("click", jobCommand("Pausing (immediate)", "pause", { mode: "immediate" }));
  $("#resume").addEventListener("click", jobCommand("Resuming", "resume"));
  $("#ack").addEventListener("click", jobCommand("Acknowledging", "ack"));
  $("#abort").addEventListener("click", () => {
    if (window.confirm(`Abort job ${ui.selected}? The arm stops; the samples so far are kept.`)) {
      jobCommand("Aborting", "abort")();
    }
  });
  // leaving the page gives the lock back (keepalive: the request outlives the page); a page restored from the
  // back-forward cache holds none
  // a tab brought back to the front renews at once (in the background its heartbeat may have been slowed)
  document.addEventListener("visibilitychange", () => {
    if (document.visibilityState === "visible" && ui.lockId) heartbeat();
  });
  window.addEventListener("pagehide", () => {
    if (!ui.lockId) return;
    fetch("/lock", { method: "DELETE", headers: headers(), keepalive: true });
    dropLock();
  });
}

async function main() {
  wire();
  showToken();
  listen();
  await Promise.all([loadRoutines().catch((err) => say(`Could not load the routines: ${err.message}`, true)),
    refreshCell(), refreshOperator()]);
  await Promise.all([refreshJobs(), refreshCalibrations(), refreshHealth()]);
  setInterval(refreshCell, 3000);
  setInterval(refreshOperator, 3000);
  setInterval(refreshJobs, 10000);
}

main();
