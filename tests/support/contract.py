"""The contract of each driver interface, written once and run against every backend.

A backend's test module subclasses `ArmContract`, `GripperContract` or
`CameraContract` and provides a `make_device` fixture: a factory returning a new,
not yet connected device (the in-process fake, or the real driver pointed at its
protocol simulator). pytest then runs every test below against it.
"""

from __future__ import annotations

import math

import pytest

from drivers.interfaces import (
    Arm,
    Camera,
    ConnectionLost,
    DeviceState,
    Frame,
    Gripper,
    GripperStatus,
    MotionRejected,
    NotConnected,
    Pose,
)


class DeviceContract:
    protocol: type

    def command(self, device):
        raise NotImplementedError

    def test_lifecycle(self, make_device):
        device = make_device()
        assert isinstance(device, self.protocol)
        assert device.state is DeviceState.CREATED
        device.stop()  # safe before connect
        with pytest.raises(NotConnected, match="connect"):
            self.command(device)
        device.connect()
        assert device.state is DeviceState.READY
        self.command(device)
        device.stop()
        device.stop()  # idempotent
        device.close()
        device.close()
        assert device.state is DeviceState.CLOSED
        with pytest.raises(NotConnected):
            self.command(device)


class ArmContract(DeviceContract):
    """`reachable` is a pose inside the backend's workspace box; moves go a little way from it."""

    protocol = Arm
    reachable = Pose(0.050, 0.040, 0.010, 0.0)

    def command(self, device):
        return device.pose()

    def test_moves_and_reports_the_pose(self, make_device):
        arm = make_device()
        arm.connect()
        try:
            for dx, dalpha in ((0.0, 0.0), (0.002, math.radians(30))):
                target = Pose(self.reachable.x + dx, self.reachable.y, self.reachable.z, self.reachable.alpha + dalpha)
                arm.move_linear(target)
                got = arm.pose()
                assert math.dist(got.xyz, target.xyz) < 1e-5
                assert abs(math.remainder(got.alpha - target.alpha, math.tau)) < 1e-4
            assert len(arm.joints().positions) >= 4
        finally:
            arm.close()

    def test_refuses_before_moving(self, make_device):
        arm = make_device()
        arm.connect()
        try:
            arm.move_linear(self.reachable)
            before = arm.pose()
            with pytest.raises(MotionRejected, match="workspace box"):
                arm.move_linear(Pose(self.reachable.x + 5.0, self.reachable.y, self.reachable.z))
            assert math.dist(arm.pose().xyz, before.xyz) < 1e-6
        finally:
            arm.close()


class GripperContract(DeviceContract):
    protocol = Gripper

    def command(self, device):
        return device.status()

    def test_grip_and_release_with_nothing_under_the_nozzle(self, make_device):
        gripper = make_device()
        gripper.connect()
        try:
            assert gripper.grip() is False
            status = gripper.status()
            assert isinstance(status, GripperStatus)
            assert not status.object_detected
            gripper.release()
            assert not gripper.status().gripping
        finally:
            gripper.close()


def assert_faulted_until_connect(gripper, faults) -> None:
    """After its link dropped (the simulator's `faults.drop_after_messages`): the gripper is FAULTED and
    refuses with ConnectionLost naming connect(); once the link is allowed again, connect() brings it back."""
    assert gripper.state is DeviceState.FAULTED
    with pytest.raises(ConnectionLost, match="connect"):
        gripper.grip()
    faults.drop_after_messages = None
    gripper.connect()
    assert gripper.grip() is False  # nothing under the nozzle


class CameraContract(DeviceContract):
    protocol = Camera

    def command(self, device):
        return device.capture()

    def test_frames_have_the_announced_size_and_rising_ids(self, make_device):
        camera = make_device()
        camera.connect()
        try:
            width, height = camera.resolution
            first, second = camera.capture(), camera.capture()
            for frame in (first, second):
                assert isinstance(frame, Frame)
                assert frame.image.shape[:2] == (height, width)
                assert frame.image.size > 0
            assert second.frame_id > first.frame_id
            assert second.host_timestamp_s >= first.host_timestamp_s
        finally:
            camera.close()
