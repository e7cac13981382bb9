"""Seed 001's simulated micro cell: `config` (its `sim:` section), `world` (the SCARA-like stage, the cameras and
the spheres, with their hidden truth), `truth` (what the truth of a run reads of it)."""
