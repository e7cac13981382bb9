"""The sequences: routines run one after the other as one job, each into its own folder of the job's.

A light module (no numerics): the CLI's `run` choices and the listings read it without loading a routine."""

from __future__ import annotations

from cellctl.errors import NotFound

# Routines run in the order the seed's calibration needs: camera 1 first (it measures the tool),
# then the tool, then area2 (its spheres are placed with the calibrated tool), then the on-board camera.
SEQUENCES = {"calibrate-cell": ("virtual-grid", "rotation-sweep", "virtual-grid-area2", "onboard-camera"),
             "calibrate-and-place": ("virtual-grid", "rotation-sweep", "virtual-grid-area2", "onboard-camera",
                                     "place-test"),
             # everything seed 001 compares: the hybrid strategies first, so the virtual grids end up active
             "seed-001": ("hybrid", "hybrid.area2", "virtual-grid", "rotation-sweep", "virtual-grid-area2",
                          "onboard-camera", "place-test")}


def item_folder(sequence: str, item: str) -> str:
    """The run folder of one routine of a sequence, inside the sequence's folder (e.g. "03-hybrid-area2")."""
    items = SEQUENCES[sequence]
    if item not in items:
        raise NotFound(f"item: {item!r} is not part of {sequence} (its items: {', '.join(items)})")
    return f"{items.index(item) + 1:02d}-{item.replace('.', '-')}"


def item_progress(sequence: str, item: str | None, step: int, total: int | None) -> str:
    """A job's progress: "12/56" steps, and for a sequence "routine 2/4: step 12/56" (a routine plans its steps
    when it starts, so the later routines' steps are not known before), running or ended alike."""
    steps = f"{step}/{total if total is not None else '?'}"
    number = item_number(sequence, item)
    return steps if number is None else f"routine {number}: step {steps}"


def item_number(sequence: str, item: str | None) -> str | None:
    """"2/4" for the second of a sequence's four routines; None for a routine run on its own."""
    items = SEQUENCES.get(sequence)
    if items is None or item not in items:
        return None
    return f"{items.index(item) + 1}/{len(items)}"
