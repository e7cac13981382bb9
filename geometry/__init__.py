"""Shared math below both calibration/ and drivers/: SE(3) transforms and tool orientations, pinhole
projection and face rasterising, and the IRB 120's nominal kinematics.

Only numpy, scipy and pinocchio (geometry.irb120) are imported here, never drivers, calibration or cellctl.
The simulated world's randomly drawn errors stay in drivers/sim; the nominal values they perturb live here.
"""
