"""A simulated six-axis cell (ABB IRB 120, two uncalibrated cameras) for camera-space manipulation (seed 002).

`config.SixAxisWorldConfig` is the cell file's `sim:` section with `world: irb120-csm`; its
`build_world()` gives `world.SixAxisWorld`, which `devices.SimSixAxisArm` and `devices.SimCsmCamera`
drive and render. The true robot (DH errors, joint zero offsets) and the true cameras stay here:
calibration code never imports this package.
"""
