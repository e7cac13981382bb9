"""Plays the part of the URScript program that ur_rtde uploads (`def rtde_control(): ... end`).

The simulator does not interpret URScript. It recognises ur_rtde's control script and
runs, in its place, the register protocol that script implements:

- at start it writes output_int_register_0 = 1 ("ready") and clears the async
  progress register (output_int_register_2);
- each cycle it reads the command id in input_int_register_0; a new non-zero id is
  processed with its arguments from the input registers, then output_int_register_0 =
  2 ("done"); a 0 sets it back to 1; id 255 ends the program (runtime state STOPPED);
- moves: 1 moveJ (q in input_double_register_0..5: the UR5e joint angles of
  kinematics.py), 2 moveJ_IK and 3 moveL (pose in 0..5), 4 moveL_FK (q), speed in 6,
  acceleration in 7, input_int_register_1 = 1 for asynchronous; an async move reports
  its progress in output_int_register_2 (bit 15 running, bits 24-30 operation id,
  bits 16-22 write count); a target out of the UR5e's reach (checked along the straight
  path) or off its branch is a script error;
- 15 speedStop, 16 servoStop, 33 stopL and 34 stopJ stop the motion (deceleration in
  input_double_register_0, async flag in input_int_register_1), 29 setTcp (pose in
  0..5), 31 triggerProtectiveStop, 35 setWatchdog (accepted, not enforced), 43/44
  getForwardKinematics (43: the current TCP pose; 44: the UR5e's forward kinematics of q in
  0..5 with the TCP offset in 6..11; result in output_double_register_0..5);
- any other command (servo/speed streaming, force mode, kinematics queries …) is not
  emulated: the program stops with a script error naming the command, so a client
  fails loudly instead of reading made-up results.

The register offset (`global reg_offset_int = N`, 24 with ur_rtde's upper-range flag)
is read from the uploaded text. A blocking step of the real script (a synchronous
move, a stop) runs in a worker thread; the script's loop waits for it as the real
one waits for `movel` to return.
"""

from __future__ import annotations

import re
import threading

from drivers.sim.servers.ur.controller import (
    PAUSED,
    PLAYING,
    Controller,
)

READY, DONE = 1, 2
REALTIME = {6, 9, 10, 11, 24, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71}
COMMAND_NAMES = {1: "moveJ", 2: "moveJ_IK", 3: "moveL", 4: "moveL_FK", 15: "speedStop", 16: "servoStop",
                 29: "setTcp", 31: "triggerProtectiveStop", 33: "stopL", 34: "stopJ", 35: "setWatchdog",
                 43: "getForwardKinematics", 44: "getForwardKinematics(q, tcp)", 255: "stop script"}
STOP_SCRIPT = 255

# ur_rtde injects the offset after the comment that ends the line: "= # int register offset\n24"
_OFFSET = re.compile(r"global\s+reg_offset_int\s*=\s*(?:#[^\n]*\n)?\s*(\d+)")


def is_rtde_control_script(program: str) -> bool:
    return program.lstrip().startswith("def rtde_control():") and "rtde_cmd()" in program


def register_offset(program: str) -> int:
    match = _OFFSET.search(program)
    return int(match.group(1)) if match else 0


class ControlScript:
    """The emulated `rtde_control` program. `step()` runs once per controller cycle under `controller.lock`."""

    def __init__(self, controller: Controller, reg_offset: int = 0):
        self.c = controller
        self.reg_offset = reg_offset
        self.executing_cmd = False
        self.blocked: threading.Thread | None = None  # the script's main thread is inside a blocking call
        self.blocked_cmd = 0
        self.move_thread: threading.Thread | None = None  # an asynchronous move
        self.async_wr_count = 0
        self.async_op_id = 0
        self.halted = False

    # -- registers --------------------------------------------------------------
    def _in_int(self, i: int) -> int:
        return self.c.in_int[i + self.reg_offset]

    def _in_double(self, i: int) -> float:
        return self.c.in_double[i + self.reg_offset]

    def _out_int(self, i: int, value: int) -> None:
        self.c.out_int[i + self.reg_offset] = value

    def _signal_async(self, value: int) -> None:
        """The script's write_async_progress_register: 0 starts an operation, negative ends it."""
        self.async_wr_count = (self.async_wr_count + 1) % 128
        if value == 0:
            self.async_op_id = (self.async_op_id + 1) % 128
        word = self.async_wr_count * 65536 + self.async_op_id * 16777216
        if value >= 0:
            word += min(value, 32767) + 32768
        self._out_int(2, word)

    # -- life cycle ------------------------------------------------------------------
    def start(self) -> None:
        with self.c.lock:
            self.c.runtime_state = PLAYING
            self._signal_async(-1)
            self._out_int(0, READY)

    def halt(self) -> None:
        """The program is stopped (new upload, dashboard stop, script error): motion in progress stops."""
        self.halted = True
        if self._busy():
            threading.Thread(target=self.c.stop_motion, name="ur-sim-halt", daemon=True).start()

    def _busy(self) -> bool:
        return any(t is not None and t.is_alive() for t in (self.blocked, self.move_thread))

    # -- the main loop, one cycle ----------------------------------------------------------
    def step(self) -> None:
        if self.halted or self.c.runtime_state != PLAYING:
            return
        if self.blocked is not None:
            if self.blocked.is_alive():
                return
            self.blocked = None
            self._finish(self.blocked_cmd)
            return
        cmd = self._in_int(0)
        if cmd in REALTIME:
            self._process(cmd)
            if not self.halted:
                self._out_int(0, READY)
        elif cmd == 0:
            self.executing_cmd = False
            self._out_int(0, READY)
        elif not self.executing_cmd:
            self.executing_cmd = True
            self._process(cmd)

    def _finish(self, cmd: int) -> None:
        if self.halted:
            return
        if cmd == STOP_SCRIPT:
            self.c.stop_program("the client sent 'stop script'")
        else:
            self._out_int(0, DONE)

    def _block_on(self, cmd: int, work) -> None:
        self.blocked_cmd = cmd
        self.blocked = threading.Thread(target=work, name=f"ur-sim-cmd-{cmd}", daemon=True)
        self.blocked.start()

    def _process(self, cmd: int) -> None:
        try:
            if cmd in (1, 2, 3, 4):
                self._move(cmd)
                return
            if cmd in (15, 16, 33, 34):
                asynchronous = cmd in (33, 34) and self._in_int(1) == 1
                self._block_on(cmd, lambda: self._stop_motion(asynchronous))
                return
            if cmd == 31:
                self._block_on(cmd, lambda: self.c.protective_stop("protective_stop() called by the program"))
                return
            if cmd == 29:
                self.c.tcp = tuple(self._in_double(i) for i in range(6))
                self.c.note(f"set_tcp {self.c.tcp}")
            elif cmd in (43, 44):
                self._forward_kinematics(cmd)
            elif cmd == 35:
                self.c.note("set_watchdog accepted (not enforced by the simulator)")
            elif cmd != STOP_SCRIPT:
                raise ValueError(f"command {cmd} is not emulated by the simulator "
                                 f"(emulated: {', '.join(f'{k} {v}' for k, v in COMMAND_NAMES.items())})")
        except ValueError as exc:
            self.c.script_error(str(exc))
            return
        self._finish(cmd)

    def _forward_kinematics(self, cmd: int) -> None:
        """get_forward_kin(): the TCP pose for joints q (input doubles 0..5) and a TCP (6..11), into output 0..5."""
        if cmd == 43:
            pose = self.c.tcp_pose()
        else:
            q, tcp = [self._in_double(i) for i in range(6)], [self._in_double(i) for i in range(6, 12)]
            pose = self.c.tcp_of_joints(q, tcp)
        for i, value in enumerate(pose):
            self.c.out_double[i + self.reg_offset] = value

    # -- motion ------------------------------------------------------------------------------
    def _move(self, cmd: int) -> None:
        args = [self._in_double(i) for i in range(6)]
        speed = self._in_double(6)
        asynchronous = self._in_int(1) == 1
        target, joints = self.c.move_target(cmd, args)  # a script error if the arm cannot go there
        self.c.note(f"{COMMAND_NAMES[cmd]} to {target} (async={asynchronous})")

        def work():
            self._stop_async_move()
            if asynchronous:
                with self.c.lock:
                    self._signal_async(0)
                    self.move_thread = threading.Thread(target=self._async_move, args=(target, speed, joints),
                                                        name="ur-sim-move", daemon=True)
                    self.move_thread.start()
            else:
                self.c.execute_move(target, speed if speed > 0 else None, joints)

        self._block_on(cmd, work)

    def _async_move(self, target, speed, joints=None) -> None:
        self.c.execute_move(target, speed if speed > 0 else None, joints)
        with self.c.lock:
            if self.move_thread is threading.current_thread():
                self.move_thread = None
                self._signal_async(-1)

    def _stop_async_move(self) -> None:
        """Kill a running async move (the script's stop_async_move) and wait until the arm stands."""
        with self.c.lock:
            thread, self.move_thread = self.move_thread, None
            if thread is not None:
                self._signal_async(-1)
        if thread is not None and thread.is_alive():
            self.c.stop_motion()
            thread.join(timeout=30.0)

    def _stop_motion(self, asynchronous: bool) -> None:
        if asynchronous:
            with self.c.lock:
                self._signal_async(0)
        self._stop_async_move()
        self.c.stop_motion()
        if asynchronous:
            with self.c.lock:
                self._signal_async(-1)


def resume(script: ControlScript | None, controller: Controller) -> bool:
    """Dashboard 'play' on a paused program: it continues where it was."""
    if script is not None and controller.runtime_state == PAUSED and not controller.protective_stopped:
        controller.runtime_state = PLAYING
        return True
    return False
