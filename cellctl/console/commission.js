// The console's Commission panel: the device self-test (POST /cell/commission, cellctl/service/commission.py).
// It runs the test for every device or one, with the arm's 5 mm move only when the operator ticks that the way is
// clear, and shows the findings table: device, check, result, figure, finding / fix. It uses console.js's helpers
// ($, el, command, say, ui): like every command it sends the token and takes the operator lock first.
"use strict";

const commissionUi = { running: false, devicesShown: "" };

function commissionDevices() {
  // the devices a self-test checks (the operator is a person), from the cell status console.js keeps
  const cell = ui.cell;
  if (!cell) return;
  const names = cell.devices.filter((d) => d.kind !== "operator").map((d) => d.name);
  const key = names.join(",");
  if (key === commissionUi.devicesShown) return;
  commissionUi.devicesShown = key;
  const select = $("#commission-device");
  const chosen = select.value;
  select.replaceChildren(el("option", { value: "" }, "every device"),
    ...names.map((n) => el("option", { value: n }, n)));
  if (names.includes(chosen)) select.value = chosen;
}

function showCommission(answer) {
  const rows = answer.checks.map((c) => el("tr", { className: `check-${c.result}` },
    el("td", {}, c.device), el("td", {}, c.check),
    el("td", { className: `result-${c.result}` }, c.result),
    el("td", {}, c.figure || "–"), el("td", {}, c.finding || "")));
  $("#commission-checks tbody").replaceChildren(...rows);
  $("#commission-checks").hidden = false;
  const n = answer.problems;
  const summary = $("#commission-summary");
  summary.textContent = `${answer.cell}: ${answer.device || "every device"}, ${answer.moved ? "with" : "without"} ` +
    `the arm's move: ${n} problem${n === 1 ? "" : "s"} found` + (n ? ": fix them and run the self-test again" : "") +
    ` (${answer.seconds.toFixed(1)} s).`;
  summary.className = n ? "note error" : "note";
}

async function runCommission() {
  if (commissionUi.running) return;
  const device = $("#commission-device").value || null;
  const move = $("#commission-move").checked;
  const button = $("#commission-run");
  commissionUi.running = true;
  button.disabled = true;
  $("#commission-summary").className = "note";
  $("#commission-summary").textContent = `Testing ${device || "every device"}` +
    (move ? ", the arm moves 5 mm and back…" : "…");
  try {
    const answer = await command("POST", "/cell/commission", { device, move });
    showCommission(answer);
    say(`Self-test done: ${answer.problems} problem${answer.problems === 1 ? "" : "s"} found`);
  } catch (err) {
    $("#commission-summary").textContent = err.message;
    $("#commission-summary").className = "note error";
    say(err.message, true);
  } finally {
    commissionUi.running = false;
    button.disabled = false;
    refreshCell();
  }
}

function wireCommission() {
  $("#commission-run").addEventListener("click", runCommission);
  commissionDevices();
  setInterval(commissionDevices, 3000);  // the cell's devices, once console.js has read them
}

wireCommission();
