"""A simulated six-axis cell (ABB IRB 120, two uncalibrated cameras) for camera-space manipulation (seed 002).

`config.SixAxisWorldConfig` is the cell file's `sim:` section with `world: irb120-csm`; the world-kind
table (drivers/sim/kinds.py) builds `world.SixAxisWorld` from it, which `devices.SimSixAxisArm` drives
and `drivers.sim.devices.SimCamera` renders. The true robot (DH errors, joint zero offsets) and the true
cameras stay here: calibration code never imports this package.
"""
