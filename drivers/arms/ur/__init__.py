"""Universal Robots over RTDE: `arm` (the Arm the cell uses), `rtde_driver` (the driver on ur-rtde's
interfaces), run in `child`, a process of its own, so that ur-rtde crashing takes down that process only."""
