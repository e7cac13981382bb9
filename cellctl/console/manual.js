// The jog panel: the arm and the vacuum by hand, through /manual and /gripper (cellctl/http/manual_api.py).
// Loaded after console.js, whose helpers it uses ($, el, say, get, command, headers, refreshCell, ui).
//
// A move runs only while this tab says it is there: a heartbeat every JOG_BEAT_MS while the move lasts (the
// daemon stops it after manual.heartbeat_timeout_s without one). "Hold to move" stops when the button or key
// is released, the pointer leaves, the tab is hidden or closed; a step (one click) runs to its end.
"use strict";

const JOG_BEAT_MS = 40;
const KEYS = { ArrowRight: ["x", 1], ArrowLeft: ["x", -1], ArrowUp: ["y", 1], ArrowDown: ["y", -1],
  PageUp: ["z", 1], PageDown: ["z", -1] };
const jog = { settings: null, motion: null, beat: null, button: null, held: false, last: null };

function jogSay(text, isError = false) {
  const p = $("#jog-state");
  p.textContent = text;
  p.classList.toggle("error", isError);
}

function poseText(p) {
  if (!p) return "–";
  return `x ${fmt(p.x_mm, 3)}  y ${fmt(p.y_mm, 3)}  z ${fmt(p.z_mm, 3)} mm  α ${fmt(p.alpha_deg, 2)}°`;
}

async function loadManual() {
  jog.settings = await get("/manual");
  const s = jog.settings;
  const speed = $("#jog-speed");
  speed.max = String(s.speed_pct);
  speed.value = String(s.speed_pct);
  speed.title = `at most ${s.speed_pct} % of the arm's speed: ${fmt(s.speed_mm_s, 1)} mm/s (manual.speed_pct)`;
  const axes = $("#jog-axes");
  axes.replaceChildren();
  for (const axis of s.axes) {
    for (const dir of [-1, 1]) {
      const b = el("button", { type: "button", textContent: `${axis} ${dir > 0 ? "+" : "−"}` });
      b.dataset.axis = axis;
      b.dataset.dir = String(dir);
      holdable(b, () => jogBody(axis, dir));
      axes.append(b);
    }
  }
  const positions = $("#goto-position");
  positions.replaceChildren(...Object.keys(s.positions).map((name) => el("option", { value: name, textContent: name })));
  $("#goto-position-go").disabled = positions.options.length === 0;
  $("#vacuum-on").disabled = $("#vacuum-off").disabled = !s.gripper;
  showMotion(s.current || s.last);
}

function jogBody(axis, dir) {
  const body = { axis, frame: $("#jog-frame").value, speed_pct: Number($("#jog-speed").value) };
  if ($("#jog-mode").value === "step") body.distance = dir * Number($("#jog-step").value);
  else body.direction = dir;
  return ["/manual/jog", body];
}

// A button that moves while it is held (or, for a step, once per click).
function holdable(button, request) {
  button.addEventListener("pointerdown", (e) => {
    if (e.button !== 0) return;
    button.setPointerCapture(e.pointerId);  // a release anywhere still reaches this button
    const [path, body] = request();
    press(path, body, button);
  });
  for (const kind of ["pointerup", "pointercancel", "lostpointercapture"]) {
    button.addEventListener(kind, () => release());
  }
}

async function press(path, body, button) {
  if (jog.motion !== null) {  // one move at a time: said, not silently dropped
    jogSay("The previous move is still under way: wait until it has ended", true);
    return;
  }
  const stepping = body.distance !== undefined;
  jog.held = !stepping;
  jog.button = button;
  try {
    const m = await command("POST", path, body);
    jog.motion = m.motion;
    button?.classList.add("moving");
    jog.beat = setInterval(beat, JOG_BEAT_MS);
    showMotion(m);
    if (!stepping && !jog.held) stopMove();  // released while the move was being asked for
  } catch (err) {
    jogSay(err.message, true);
    jog.button = null;
  }
}

async function beat() {
  const id = jog.motion;
  if (id === null) return;
  let r;
  try {
    r = await fetch(`/manual/moves/${id}/alive`, { method: "POST", headers: headers() });
  } catch { return; }  // the daemon unreachable: it stops the arm by itself
  if (!r.ok) {
    const body = await r.json().catch(() => ({}));
    stopBeating();
    jogSay(`The move stopped: ${body.detail || r.statusText}`, true);
    return;
  }
  const m = await r.json();
  if (m.motion !== jog.motion) return;
  showMotion(m);
  if (m.state !== "moving") stopBeating();
}

// The button or key released (or the tab hidden or closed): stop now. A step runs to its end.
function release() {
  if (!jog.held) return;
  jog.held = false;
  if (jog.motion !== null) stopMove();  // else not started yet: press() stops it when the daemon answers
}

function stopMove() {
  fetch(`/manual/moves/${jog.motion}/stop`, { method: "POST", headers: headers(), keepalive: true });
  stopBeating();
}

function stopBeating() {
  clearInterval(jog.beat);
  jog.beat = null;
  jog.motion = null;
  jog.button?.classList.remove("moving");
  jog.button = null;
  setTimeout(refreshCell, 100);
}

function showMotion(m) {
  if (!m) return;
  jog.last = m;
  $("#jog-pose").textContent = poseText(m.pose);
  const moved = `moved ${fmt(m.moved_mm, 3)} mm`;
  if (m.state === "moving") jogSay(`${m.what}: moving at ${fmt(m.speed_mm_s, 1)} mm/s, ${moved}`);
  else jogSay(`${m.what}: ${m.state} (${m.reason}), ${moved}`, m.state === "refused" || m.state === "failed");
}

function moveToBody() {
  const pose = { x_mm: Number($("#goto-x").value), y_mm: Number($("#goto-y").value),
    z_mm: Number($("#goto-z").value), alpha_deg: Number($("#goto-alpha").value) };
  return ["/manual/move-to", { pose, speed_pct: Number($("#jog-speed").value) }];
}

async function fillHere() {
  const pose = (await get("/cell")).arm_pose;
  if (!pose) { jogSay("The arm reports no pose (is it connected?)", true); return; }
  $("#goto-x").value = pose.x_mm.toFixed(3);
  $("#goto-y").value = pose.y_mm.toFixed(3);
  $("#goto-z").value = pose.z_mm.toFixed(3);
  $("#goto-alpha").value = pose.alpha_deg.toFixed(3);
}

async function vacuum(on) {
  try {
    const got = await command("POST", on ? "/gripper/grip" : "/gripper/release");
    $("#vacuum-state").textContent = `vacuum ${got.vacuum}: ${fmt(got.vacuum_kpa, 1)} kPa, object ` +
      (got.object_detected ? "detected" : "not detected");
  } catch (err) {
    jogSay(err.message, true);
  }
}

function wireManual() {
  holdable($("#goto-go"), moveToBody);
  holdable($("#goto-position-go"), () => ["/manual/move-to",
    { position: $("#goto-position").value, speed_pct: Number($("#jog-speed").value) }]);
  $("#goto-here").addEventListener("click", fillHere);
  $("#vacuum-on").addEventListener("click", () => vacuum(true));
  $("#vacuum-off").addEventListener("click", () => vacuum(false));
  const panel = $("#jog-panel");
  panel.addEventListener("keydown", (e) => {
    const key = KEYS[e.key];
    if (!key || e.repeat || e.target.matches("input, select")) return;
    e.preventDefault();
    const button = document.querySelector(`#jog-axes button[data-axis="${key[0]}"][data-dir="${key[1]}"]`);
    const [path, body] = jogBody(key[0], key[1]);
    press(path, body, button);
  });
  panel.addEventListener("keyup", (e) => { if (KEYS[e.key]) release(); });
  // a key held in the panel: the move stops when focus leaves the panel (not when it moves inside it)
  panel.addEventListener("focusout", (e) => { if (!panel.contains(e.relatedTarget)) release(); });
  document.addEventListener("visibilitychange", () => { if (document.visibilityState !== "visible") release(); });
  window.addEventListener("pagehide", () => release());
  const source = new EventSource("/events");  // another client's moves, and this one's end
  source.addEventListener("manual", (e) => {
    const m = JSON.parse(e.data);
    if (jog.motion === null || m.motion === jog.motion) showMotion(m);
  });
}

wireManual();
loadManual().catch((err) => jogSay(`Manual motion unavailable: ${err.message}`, true));
