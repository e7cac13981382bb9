"""A simulated six-axis cell for hand-eye calibration: a UR5e, a camera on its wrist, a camera over the table,
a ChArUco board on the table and a small one on the flange.

`config.HandEyeWorldConfig` is the cell file's `sim:` section with `world: ur5e-handeye`; the world-kind table
(drivers/sim/kinds.py) builds `world.HandEyeWorld` from it, which `devices.SimUr5eArm` drives and
`drivers.sim.devices.SimCamera` renders. The true arm (DH and joint-zero errors), the true camera mounts and
intrinsics, the boards' true poses and printing scales stay here: calibration code never imports this package.
"""
