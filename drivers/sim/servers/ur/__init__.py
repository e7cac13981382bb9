"""A simulated Universal Robots controller for ur_rtde and other RTDE clients.

- `rtde.py`: the RTDE wire format (30004) and the variable tables;
- `dashboard.py`: the dashboard server's text protocol (29999);
- `primary.py`: the primary and secondary client interfaces (30001, 30002): version message,
  robot state at 10 Hz, URScript in;
- `script.py`: the emulation of ur_rtde's uploaded control script (register protocol);
- `controller.py`: modes, registers, TCP and the four-axis simulated arm behind them;
- `kinematics.py`: the UR5e joint angles it reports (geometry/ur.py, mounted in the cell);
- `server.py`: the ports, the 500 Hz cycle, `serve()` and `SimulatorProcess` (own process).

Run one: `python -m drivers.sim.servers.ur --host 127.0.0.2 --config config/sim-microcell.yaml`.
A cell whose arm is `backend: ur` and whose cameras are simulated shares its World with the
simulator through `WorldArmSimulator(cell.context.sim_world(), host, limits)` (see drivers/sim/remote.py).
"""

from drivers.sim.servers.ur.controller import UrSimFaults, UrSimOptions
from drivers.sim.servers.ur.server import SimulatorProcess, UrSimulator, WorldArmSimulator, serve

__all__ = ["SimulatorProcess", "UrSimFaults", "UrSimOptions", "UrSimulator", "WorldArmSimulator", "serve"]
