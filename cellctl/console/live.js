// The live camera view of the console: a camera live (MJPEG from /cameras/{name}/live.mjpg, read here with fetch so
// each frame's figures in its X-Live-Stats header come with it), its histogram and saturated pixels, exposure and
// gain controls, and the settings written back to the cell file after the diff is shown.
// Uses console.js's helpers ($, el, fmt, say, get, command, ui, ApiError, detailOf): loaded after it.
"use strict";

const live = {
  camera: null,       // the camera chosen
  abort: null,        // the AbortController of the running stream (null: stopped)
  frames: 0,          // frames shown since the stream started
  started: 0,         // performance.now() at its start
  lastUrl: null,      // the blob: URL on screen
  settings: null,     // GET /cameras/{name}/settings as last read
  cameras: [],
};

const CRLFCRLF = [13, 10, 13, 10];

function liveLayers() {
  return [...document.querySelectorAll("#live-layers input:checked")].map((i) => i.value);
}

function liveSay(text, isError = false) {
  const box = $("#live-status");
  box.textContent = text;
  box.className = isError ? "note state-faulted" : "note";
}

function indexOf(buf, seq, from = 0) {
  outer: for (let i = from; i <= buf.length - seq.length; i++) {
    for (let j = 0; j < seq.length; j++) if (buf[i + j] !== seq[j]) continue outer;
    return i;
  }
  return -1;
}

// One part of the multipart stream from the front of `buf`: {headers, body, used}, or null until it has arrived.
function nextPart(buf) {
  const end = indexOf(buf, CRLFCRLF);
  if (end < 0) return null;
  const head = new TextDecoder().decode(buf.subarray(0, end));
  const headers = {};
  for (const line of head.split("\r\n")) {
    const colon = line.indexOf(":");
    if (colon > 0 && !line.startsWith("--")) headers[line.slice(0, colon).trim().toLowerCase()] = line.slice(colon + 1).trim();
  }
  const length = Number(headers["content-length"]);
  if (!Number.isFinite(length)) return null;
  const start = end + 4;
  if (buf.length < start + length) return null;
  return { headers, body: buf.slice(start, start + length), used: start + length };
}

async function readParts(response, onPart) {
  const reader = response.body.getReader();
  let buf = new Uint8Array(0);
  for (;;) {
    let part;
    while ((part = nextPart(buf))) {
      buf = buf.slice(part.used);
      onPart(part);
    }
    const { value, done } = await reader.read();
    if (done) return;
    const joined = new Uint8Array(buf.length + value.length);
    joined.set(buf);
    joined.set(value, buf.length);
    buf = joined;
  }
}

function showFrame(part) {
  const url = URL.createObjectURL(new Blob([part.body], { type: part.headers["content-type"] }));
  const img = $("#live-image");
  img.src = url;
  if (live.lastUrl) URL.revokeObjectURL(live.lastUrl);
  live.lastUrl = url;
  live.frames += 1;
  const frameId = part.headers["x-frame-id"];
  img.dataset.frame = frameId;
  let stats = {};
  try { stats = JSON.parse(part.headers["x-live-stats"] || "{}"); } catch { /* a frame without figures */ }
  // the rate between the first frame and this one (not since the request: the first frame comes at once)
  if (live.frames === 1) live.first = performance.now();
  const fps = (live.frames - 1) / Math.max(0.001, (performance.now() - live.first) / 1000);
  liveSay(`${live.camera} live · frame ${frameId}` + (live.frames > 1 ? ` · ${fps.toFixed(1)} frames/s` : ""));
  showStats(stats);
}

function showStats(s) {
  $("#live-frame-id").textContent = $("#live-image").dataset.frame || "–";
  $("#live-mean").textContent = fmt(s.mean_pct, 1, " %");
  const sat = $("#live-saturated");
  sat.textContent = typeof s.saturated === "number" ? `${fmt(s.saturated_pct, 2, " %")} (${s.saturated} px)` : "–";
  sat.dataset.pct = s.saturated_pct ?? "";
  sat.className = s.saturated > 0 ? "state-faulted" : "";
  $("#live-features").textContent = Array.isArray(s.features) ? String(s.features.length) : "–";
  $("#live-exposure").textContent = typeof s.exposure_s === "number" ? `${Number(s.exposure_s.toPrecision(4))} s` : "–";
  drawHistogram(s.histogram || [], s.saturated > 0);
}

function drawHistogram(hist, saturated) {
  const c = $("#live-histogram");
  const g = c.getContext("2d");
  g.clearRect(0, 0, c.width, c.height);
  g.fillStyle = "#f4f4f4";
  g.fillRect(0, 0, c.width, c.height);
  if (!hist.length) return;
  // a log scale: the few pixels of a feature or of saturation stay visible beside the background's peak
  const top = Math.log10(1 + 1e5 * Math.max(...hist));
  const w = c.width / hist.length;
  hist.forEach((h, i) => {
    const height = top > 0 ? Math.log10(1 + 1e5 * h) / top * (c.height - 2) : 0;
    g.fillStyle = i === hist.length - 1 && saturated ? "#d000d0" : "#455a64";
    g.fillRect(i * w, c.height - height, Math.max(1, w - 1), height);
  });
  c.dataset.bins = String(hist.length);
}

function stopLive(note = null) {
  if (live.abort) live.abort.abort();
  live.abort = null;
  $("#live-start").disabled = false;
  $("#live-stop").disabled = true;
  if (note !== null) liveSay(note);
}

async function startLive() {
  stopLive();
  const camera = $("#live-camera").value;
  if (!camera) return;
  live.camera = camera;
  const controller = new AbortController();
  live.abort = controller;
  live.frames = 0;
  live.started = performance.now();
  $("#live-start").disabled = true;
  $("#live-stop").disabled = false;
  const width = Math.min(1280, Math.max(320, Math.round(($("#live-image").clientWidth || 800) * (window.devicePixelRatio || 1))));
  const query = [`fps=${$("#live-fps").value || 4}`, `width=${width}`, ...liveLayers().map((l) => `layers=${l}`)];
  if (!liveLayers().length) query.push("layers=none");  // the frame alone
  liveSay(`${camera}: starting…`);
  try {
    const r = await fetch(`/cameras/${encodeURIComponent(camera)}/live.mjpg?${query.join("&")}`,
      { signal: controller.signal });
    if (!r.ok) throw new ApiError(r.status, await detailOf(r));
    await readParts(r, (part) => {
      if (controller.signal.aborted) return;
      if ((part.headers["content-type"] || "").startsWith("application/json")) {
        const why = JSON.parse(new TextDecoder().decode(part.body));
        stopLive(`stopped: ${why.stopped}`);
        $("#live-status").className = "note state-faulted";
        return;
      }
      showFrame(part);
    });
    if (live.abort === controller) stopLive(`${camera}: the stream ended`);
  } catch (err) {
    if (controller.signal.aborted) return;  // stopped here
    const text = err instanceof ApiError ? `${camera}: refused (${err.status}): ${err.message}` : `${camera}: ${err.message}`;
    if (live.abort === controller) stopLive();
    liveSay(text, true);
  }
}

// -- exposure and gain -------------------------------------------------------------------------------

async function loadSettings() {
  const camera = $("#live-camera").value;
  const box = $("#live-settings");
  if (!camera) return;
  try {
    live.settings = await get(`/cameras/${encodeURIComponent(camera)}/settings`);
  } catch (err) {
    $("#live-settings-note").textContent = `settings of ${camera}: ${err.message}`;
    return;
  }
  renderSettings(live.settings);
  box.hidden = false;
}

function renderSettings(answer) {
  const rows = Object.values(answer.settings).map((s) => {
    const input = el("input", { id: `live-set-${s.key}`, type: "number", min: s.minimum, max: s.maximum,
      step: "any", value: s.value ?? "" });
    input.dataset.key = s.key;
    return el("label", { className: "live-setting" }, `${s.label} (${s.key}, ${s.unit}) `, input,
      el("span", { className: "note" }, ` allowed ${s.minimum} to ${s.maximum}; cell file: ${s.in_file ?? "not set"}` +
        (s.changed ? " · changed" : "")));
  });
  $("#live-setting-rows").replaceChildren(...rows);
  $("#live-settings-note").textContent = answer.note || "";
  const changed = Object.values(answer.settings).some((s) => s.changed);
  $("#live-diff").disabled = !changed;
}

async function applySettings() {
  const camera = $("#live-camera").value;
  const values = {};
  for (const input of document.querySelectorAll("#live-setting-rows input")) {
    const s = live.settings?.settings[input.dataset.key];
    if (input.value === "") continue;
    const v = Number(input.value);
    if (!s || v !== s.value) values[input.dataset.key] = v;
  }
  if (!Object.keys(values).length) { say("Nothing changed."); return; }
  try {
    say(`Setting ${Object.keys(values).join(", ")} of ${camera}…`);
    live.settings = await command("POST", `/cameras/${encodeURIComponent(camera)}/settings`, { values });
    renderSettings(live.settings);
    $("#live-settings-note").textContent = "";
    say(`${camera}: ${Object.entries(values).map(([k, v]) => `${k} ${v}`).join(", ")} set on the camera`);
  } catch (err) {
    $("#live-settings-note").textContent = err.message;
    say(err.message, true);
  }
}

async function showDiff(confirm) {
  const camera = $("#live-camera").value;
  try {
    const answer = await command("POST", `/cameras/${encodeURIComponent(camera)}/settings/save`, { confirm });
    $("#live-diff-text").textContent = answer.diff || answer.message;
    $("#live-diff-box").hidden = false;
    $("#live-write").hidden = !answer.diff || answer.written;
    $("#live-write-note").textContent = answer.written ? answer.message : (answer.diff ? `to ${answer.file}` : "");
    if (answer.written) { say(answer.message); loadSettings(); }
  } catch (err) {
    $("#live-write-note").textContent = err.message;
    say(err.message, true);
  }
}

// -- wiring ------------------------------------------------------------------------------------------

async function liveCameras() {
  let cell;
  try { cell = await get("/cell"); } catch { return; }
  const names = cell.cameras || [];
  if (names.join() === live.cameras.join()) return;
  live.cameras = names;
  const select = $("#live-camera");
  const chosen = select.value;
  select.replaceChildren(...names.map((n) => el("option", { value: n }, n)));
  if (names.includes(chosen)) select.value = chosen;
  loadSettings();
}

function wireLive() {
  $("#live-start").addEventListener("click", startLive);
  $("#live-stop").addEventListener("click", () => stopLive(`${live.camera}: stopped`));
  $("#live-camera").addEventListener("change", () => {
    const was = !!live.abort;
    stopLive(`${$("#live-camera").value}: not live`);
    $("#live-diff-box").hidden = true;
    loadSettings();
    if (was) startLive();
  });
  for (const box of document.querySelectorAll("#live-layers input")) {
    box.addEventListener("change", () => { if (live.abort) startLive(); });
  }
  $("#live-apply").addEventListener("click", applySettings);
  $("#live-reload").addEventListener("click", loadSettings);
  $("#live-diff").addEventListener("click", () => showDiff(false));
  $("#live-write").addEventListener("click", () => showDiff(true));
  window.addEventListener("pagehide", () => stopLive());  // the stream closes with the page
  liveCameras();
  setInterval(liveCameras, 5000);
}

wireLive();
