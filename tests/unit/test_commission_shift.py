"""The self-test's view shift (cellctl/service/commission.py image_shift): a camera on the arm sees every feature
move by the whole move, further than the features lie apart; the shift is the translation most features share, not
each feature's nearest neighbour (which paired each sphere with the next one: 2.02 mm seen for a 5 mm move)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from cellctl.service.commission import image_shift

SPHERES = [(1072, 782), (1555, 800), (1058, 1184), (1541, 1203)]  # as cam3 saw them on the micro cell, ~480 px apart


def frame(points, shift=(0.0, 0.0), size=(1944, 2592)) -> np.ndarray:
    img = np.full(size, 20, np.uint8)
    for u, v in points:
        centre = (u + shift[0], v + shift[1])
        if 0 <= centre[0] < size[1] and 0 <= centre[1] < size[0]:
            cv2.circle(img, (round(centre[0] * 16), round(centre[1] * 16)), 40 * 16, 200, -1, cv2.LINE_AA, shift=4)
    return img


@pytest.mark.parametrize("shift", [(807.0, 31.0), (-300.0, 420.0), (3.0, -2.0)])
def test_a_shift_beyond_the_features_spacing_is_measured_whole(shift):
    px, how, uv0, uv1 = image_shift(frame(SPHERES), frame(SPHERES, shift))
    assert px == pytest.approx(np.hypot(*shift), abs=0.5)
    assert np.subtract(uv1, uv0) == pytest.approx(shift, abs=0.5)
    kept = sum(0 <= u + shift[0] < 2592 and 0 <= v + shift[1] < 1944 for u, v in SPHERES)
    assert how == f"{kept} features tracked"


def test_features_that_leave_the_view_or_appear_do_not_spoil_the_shift():
    extra = SPHERES + [(300, 300)]  # in view before only
    px, _, uv0, uv1 = image_shift(frame(extra), frame(SPHERES + [(2000, 1700)], (500.0, 0.0)))
    assert px == pytest.approx(500.0, abs=0.5) and np.subtract(uv1, uv0) == pytest.approx((500.0, 0.0), abs=0.5)


def test_nothing_to_track_is_none():
    assert image_shift(frame([]), frame(SPHERES)) is None
