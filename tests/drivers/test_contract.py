"""The contract every backend of an interface honours (re-run against each backend as they are added)."""

import pytest

from drivers.interfaces import Arm, Camera, DeviceState, Gripper, NotConnected, Pose
from drivers.registry import DriverContext, backend_class, backend_names
from tests.conftest import microcell_data

DATA = microcell_data()
OPTIONS = {"arm": {"limits": DATA["arm"]["limits"]}, "gripper": {}, "camera": {"sim_camera": "cam1"}}
PROTOCOLS = {"arm": Arm, "gripper": Gripper, "camera": Camera}
CASES = [(kind, backend) for kind in ("arm", "gripper", "camera") for backend in backend_names(kind) if backend == "sim"]


def make(kind, backend, microcell_sim):
    context = DriverContext(sim_config=microcell_sim)
    return backend_class(kind, backend).create(kind, OPTIONS[kind], context)


def command(device, kind):
    if kind == "arm":
        return device.pose()
    if kind == "gripper":
        return device.status()
    return device.capture()


@pytest.mark.parametrize("kind, backend", CASES)
def test_lifecycle(kind, backend, microcell_sim):
    device = make(kind, backend, microcell_sim)
    assert isinstance(device, PROTOCOLS[kind])
    assert device.state is DeviceState.CREATED
    device.stop()  # safe before connect
    with pytest.raises(NotConnected, match="connect"):
        command(device, kind)
    device.connect()
    assert device.state is DeviceState.READY
    command(device, kind)
    device.stop()
    device.stop()  # idempotent
    device.close()
    device.close()
    assert device.state is DeviceState.CLOSED
    with pytest.raises(NotConnected):
        command(device, kind)


def test_arm_refuses_before_moving(microcell_sim):
    from drivers.interfaces import MotionRejected

    arm = make("arm", "sim", microcell_sim)
    arm.connect()
    before = arm.pose()
    with pytest.raises(MotionRejected):
        arm.move_linear(Pose(1.0, 0.0, 0.0))
    assert arm.pose() == before


def test_unknown_backend_names_the_allowed_ones():
    from drivers.registry import UnknownBackend

    with pytest.raises(UnknownBackend, match="allowed: sim"):
        backend_class("arm", "kuka")
    with pytest.raises(UnknownBackend, match="unknown device kind"):
        backend_class("conveyor", "sim")


def test_console_operator_waits_for_enter_and_says_when_nobody_answers():
    import io

    from drivers.console import ConsoleOperator

    out = io.StringIO()
    operator = ConsoleOperator("operator", stdin=io.StringIO("\n"), stdout=out)
    operator.connect()
    operator.request("Lay the dot grid on area1")
    assert "OPERATOR: Lay the dot grid on area1" in out.getvalue()
    with pytest.raises(NotConnected, match="no operator input"):
        operator.request("Take the grid away")  # stdin is at its end
