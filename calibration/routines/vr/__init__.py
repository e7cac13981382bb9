"""Seed 000's VR cell: model matching, coarse and fine, the approach with the simultaneous update, and the
paper's experiments (`_common`: the cell's geometry and scenes, `_samples`: what a view records)."""
