"""The features a cell knows in a frame: the nozzle (seen from below, its end face is a bright ring around the
dark bore) and spheres (bright discs: placed, at the supply, or held, where a held sphere hides the nozzle).

A ring and a disc are told apart by the level at the centre: the bore of a ring is background, a disc is lit
there. Bright features only, as the cell's cameras see them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.vision.centroid import Blob, find_blobs

KINDS = ("nozzle", "sphere")


@dataclass(frozen=True)
class Feature:
    kind: str  # one of KINDS
    blob: Blob


def find_features(image) -> list[Feature]:
    """Every measurable bright feature of the frame with its kind, in find_blobs' order (rows, then u)."""
    img = np.asarray(image)
    return [Feature(feature_kind(img, b), b) for b in find_blobs(img)]


def feature_kind(image: np.ndarray, blob: Blob) -> str:
    """'nozzle' if the blob's centre is darker than half its contrast above the background around it (a ring's
    bore), else 'sphere'."""
    radius = blob.diameter_px / 2
    reach = int(np.ceil(radius + 9))  # a window around the blob: the background band fits in it
    u0, v0 = max(int(blob.u) - reach, 0), max(int(blob.v) - reach, 0)
    win = image[v0:int(blob.v) + reach + 1, u0:int(blob.u) + reach + 1].astype(np.float64)
    rows, cols = np.indices(win.shape)
    r = np.hypot(cols + u0 - blob.u, rows + v0 - blob.v)
    centre = win[r <= max(1.0, radius / 6)]
    around = win[(r > radius + 3) & (r <= radius + 8)]
    if centre.size == 0 or around.size == 0:
        return "sphere"
    lift = float(np.median(centre)) - float(np.median(around))
    return "nozzle" if lift < blob.contrast / 2 else "sphere"
