"""The truth of simulated runs: each routine's fit judged against the simulated world's hidden state.

A routine names its function (`truth = "cellctl.truth.micro:virtual_grid_truth"`); the runner calls it after
the fit, on a simulated cell only. These modules read the world, which calibration/ never does. One module per
simulated cell: `micro` (seed 001's micro cell), `csm` (seed 002's IRB 120), `vr` (seed 000's VR cell)."""
