"""Seed 001's micro cell: the virtual grid, the hybrid strategies, the rotation sweep, the on-board camera and
the placing tests built on them, and the sequences that run them in the order the cell's calibration needs."""

from calibration.routines.sequence import Item, Sequence

# camera 1 first (it measures the tool), then the tool, then area2 (its spheres are placed with the calibrated
# tool), then the on-board camera
CALIBRATE = ("virtual-grid", "rotation-sweep", "virtual-grid-area2", "onboard-camera")

SEQUENCES = (
    Sequence.of("calibrate-cell", *CALIBRATE),
    Sequence.of("calibrate-and-place", *CALIBRATE, "place-test"),
    # everything seed 001 compares: the hybrid strategies first, so the virtual grids end up active
    Sequence.of("seed-001", "hybrid", Item("hybrid.area2", "hybrid", {"area": "area2"}), *CALIBRATE, "place-test"),
)
