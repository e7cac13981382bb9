"""The dashboard server (port 29999): one text line per request, one line per reply.

On connect the server greets with `Connected: Universal Robots Dashboard Server`.
Replies follow PolyScope 5's wording where clients check it (ur_rtde compares
`Stopped`, `Starting program`, `Protective stop releasing`, and searches the
PolyscopeVersion reply for `\\d+.\\d+.\\d+.\\d+`). An unknown request is answered
`could not understand: '<request>'`.
"""

from __future__ import annotations

from drivers.sim.servers.ur.controller import (
    IDLE,
    POWER_OFF,
    PROTECTIVE_STOP,
    ROBOT_MODES,
    RUNNING,
    SAFETY_MODES,
    STOPPED,
    Controller,
)
from drivers.sim.servers.ur.script import resume

WELCOME = "Connected: Universal Robots Dashboard Server"
_PROGRAM_STATES = {0: "STOPPING", 1: "STOPPED", 2: "PLAYING", 3: "PAUSING", 4: "PAUSED", 5: "RESUMING"}


def answer(controller: Controller, request: str) -> tuple[str, bool]:
    """The reply to one request line, and whether the server closes the connection after it."""
    c = controller
    text = request.strip()
    cmd = text.lower()
    major, minor, bugfix, build = c.options.version
    with c.lock:
        if cmd == "polyscopeversion":
            return f"URSoftware {major}.{minor}.{bugfix}.{build} (Jan 01 2024)", False
        if cmd == "version":
            return f"Version: {major}.{minor}.{bugfix}.{build}", False
        if cmd == "get serial number":
            return c.options.serial_number, False
        if cmd == "get robot model":
            return c.options.robot_model, False
        if cmd == "robotmode":
            return f"Robotmode: {ROBOT_MODES[c.robot_mode]}", False
        if cmd == "safetymode":
            return f"Safetymode: {SAFETY_MODES[c.safety_mode]}", False
        if cmd == "safetystatus":
            return f"Safetystatus: {SAFETY_MODES[c.safety_mode]}", False
        if cmd == "is in remote control":
            return ("true" if c.options.remote_control else "false"), False
        if cmd == "power on":
            if c.robot_mode == POWER_OFF:
                c.robot_mode = IDLE
                c.note("powered on (IDLE)")
            return "Powering on", False
        if cmd == "power off":
            c.stop_program("power off")
            c.robot_mode = POWER_OFF
            c.note("powered off")
            return "Powering off", False
        if cmd == "brake release":
            if c.robot_mode == POWER_OFF:
                return "Failed to execute: brake release (robot is powered off)", False
            c.robot_mode = RUNNING
            return "Brake releasing", False
        if cmd == "unlock protective stop":
            return c.unlock_protective_stop(), False
        if cmd == "close safety popup":
            return "closing safety popup", False
        if cmd == "close popup":
            return "closing popup", False
        if cmd.startswith("popup "):
            return "showing popup", False
        if cmd == "restart safety":
            if c.safety_mode == PROTECTIVE_STOP:
                c.safety_mode = 1
            c.robot_mode = POWER_OFF
            c.stop_program("restart safety")
            return "Restarting safety", False
        if cmd == "stop":
            c.stop_program("dashboard stop")
            return "Stopped", False
        if cmd == "play":
            if resume(c.script, c):
                c.note("program resumed (dashboard play)")
                return "Starting program", False
            return "Failed to execute: play", False
        if cmd == "pause":
            if c.runtime_state == 2:
                c.runtime_state = 4
                return "Pausing program", False
            return "Failed to execute: pause", False
        if cmd == "running":
            return f"Program running: {'true' if c.runtime_state == 2 else 'false'}", False
        if cmd == "programstate":
            name = "rtde_control" if c.runtime_state != STOPPED else "<unnamed>"
            return f"{_PROGRAM_STATES.get(c.runtime_state, 'STOPPED')} {name}", False
        if cmd == "get loaded program":
            return "No program loaded", False
        if cmd == "isprogramsaved":
            return "true <unnamed>", False
        if cmd.startswith("load "):
            return f"File not found: {text[5:]}", False
        if cmd.startswith("addtolog "):
            return "Added log message", False
        if cmd.startswith("setuserrole "):
            return "Setting user role: " + text[12:], False
        if cmd == "quit":
            return "Disconnected", True
        if cmd == "shutdown":
            return "Shutting down", True
    return f"could not understand: '{text}'", False
