"""The dead-man of a manual move (cellctl/core/manual.py) with the cell file's default heartbeat time-out: a held
jog whose client goes silent stops within 0.2 s of motion after its last heartbeat, a released one within the
segment under way; a segment the arm refuses ends the move there. On a fake arm that records what it is sent."""

from __future__ import annotations

import threading
from types import SimpleNamespace

import pytest

from drivers.interfaces import MotionRejected, Pose

from cellctl.config import ManualSettings
from cellctl.core.manual import SEGMENT_S, ManualMotion, motion_after
from cellctl.core.manual_path import segments

SPEED = 0.01  # m/s


class Arm:
    def __init__(self, refuse_beyond_y: float = 1.0):
        self.sent: list[Pose] = []
        self.refuse_beyond_y = refuse_beyond_y

    def move_linear(self, target: Pose, speed=None) -> None:
        if target.y > self.refuse_beyond_y:
            raise MotionRejected(f"y={target.y:.4f} beyond the limit; nothing moved")
        self.sent.append(target)

    def pose(self) -> Pose:
        return self.sent[-1] if self.sent else Pose(0.0, 0.0, 0.0)

    def stop(self) -> None:
        pass


def held_jog(arm: Arm, timeout_s: float):
    """A ManualMotion running a held jog along y (1 m of path), and the event set when it ends."""
    ended = threading.Event()
    worker = SimpleNamespace(cells=SimpleNamespace(cell=SimpleNamespace(arm=arm), last_pose=None))
    runner = ManualMotion(worker, lambda kind, data: None)
    claim = SimpleNamespace(__exit__=lambda *exc: None)
    path = segments(Pose(0.0, 0.0, 0.0), Pose(0.0, 1.0, 0.0), SPEED, SEGMENT_S)
    runner.start("test", "jog-hold", "y + held", Pose(0.0, 0.0, 0.0), path, SPEED, True, timeout_s, claim, arm,
                 lambda target: None, lambda motion: ended.set())
    return runner, ended


def test_a_silent_client_stops_a_held_jog_within_200_ms_of_motion():
    timeout = ManualSettings().heartbeat_timeout_s
    arm = Arm()
    runner, ended = held_jog(arm, timeout)
    assert ended.wait(30)  # no heartbeat ever comes after the start
    end = runner.status()["last"]
    assert end["stopped_by"] == "heartbeat lost" and end["state"] == "stopped"
    assert 0 < end["coast_s"] <= 0.2, end
    assert end["delta_mm"][1] == pytest.approx(len(arm.sent) * SPEED * SEGMENT_S * 1e3)
    assert len(arm.sent) * SEGMENT_S <= 0.2 + 1e-9  # the motion sent at all: no more than that


def test_a_release_stops_it_within_the_segment_under_way_and_a_refused_segment_ends_it():
    arm = Arm()
    runner, ended = held_jog(arm, 5.0)
    motion = runner.status()["current"]["motion"]
    while len(arm.sent) < 4:
        runner.heartbeat(motion)
        threading.Event().wait(0.01)
    runner.stop(motion)
    assert ended.wait(30)
    end = runner.status()["last"]
    assert end["stopped_by"] == "released" and end["coast_s"] <= SEGMENT_S

    arm = Arm(refuse_beyond_y=0.0021)  # the fifth segment (2.5 mm) is refused
    runner, ended = held_jog(arm, 5.0)
    motion = runner.status()["current"]["motion"]
    while not ended.is_set():
        runner.heartbeat(motion)
        ended.wait(0.01)
    end = runner.status()["last"]
    assert end["stopped_by"] == "limit" and "beyond the limit" in end["reason"] and len(arm.sent) == 4


def test_motion_after_counts_only_what_was_sent_after_the_stop():
    sent = [(0.0, 0.05), (0.05, 0.05), (0.5, 0.05)]  # a stall between the second and the third: no motion
    assert motion_after(sent, 0.07) == pytest.approx(0.03 + 0.05)
    assert motion_after(sent, 1.0) == 0.0
