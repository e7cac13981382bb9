"""The contract suites run against the in-process simulated fakes, and registry errors."""

import pytest

from drivers.interfaces import NotConnected
from drivers.registry import DriverContext, backend_class

from tests.conftest import microcell_data
from tests.support.contract import ArmContract, CameraContract, GripperContract

DATA = microcell_data()


def _sim_factory(kind, options, microcell_sim):
    context = DriverContext(sim_config=microcell_sim)
    return lambda: backend_class(kind, "sim").create(kind, options, context)


class TestSimArm(ArmContract):
    @pytest.fixture
    def make_device(self, microcell_sim):
        return _sim_factory("arm", {"limits": DATA["arm"]["limits"]}, microcell_sim)


class TestSimGripper(GripperContract):
    @pytest.fixture
    def make_device(self, microcell_sim):
        return _sim_factory("gripper", {}, microcell_sim)


class TestSimCamera(CameraContract):
    @pytest.fixture
    def make_device(self, microcell_sim):
        return _sim_factory("camera", {"sim_camera": "cam1"}, microcell_sim)


def test_unknown_backend_names_the_allowed_ones():
    from drivers.registry import UnknownBackend

    with pytest.raises(UnknownBackend, match="allowed: abb, sim, sim-irb120, sim-ur5e, sim-vr, ur"):
        backend_class("arm", "kuka")
    with pytest.raises(UnknownBackend, match="unknown device kind"):
        backend_class("conveyor", "sim")


def test_console_operator_waits_for_enter_and_says_when_nobody_answers():
    import io

    from drivers.operators.terminal import ConsoleOperator

    out = io.StringIO()
    operator = ConsoleOperator("operator", stdin=io.StringIO("\n"), stdout=out)
    operator.connect()
    operator.request("Lay the dot grid on area1")
    assert "OPERATOR: Lay the dot grid on area1" in out.getvalue()
    with pytest.raises(NotConnected, match="no operator input"):
        operator.request("Take the grid away")  # stdin is at its end
