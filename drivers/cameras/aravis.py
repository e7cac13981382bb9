"""GenICam cameras through Aravis: `backend: genicam` with `library: aravis` (options: `GenICamSettings`).

Aravis speaks GigE Vision (GVCP control, GVSP stream, over UDP) and USB3 Vision itself, so no
vendor SDK or GenTL producer is needed. Python reaches it through GObject introspection:
PyGObject (the `aravis` extra of pyproject.toml) and Debian's `gir1.2-aravis-0.8`
(`tools/ensure-system`); both are imported only when such a camera connects.

Choosing the camera: `address` opens the GigE Vision camera at that IP address directly (no
broadcast discovery; `serial`/`model`, when given, are checked against it); without it, Aravis
discovers the cameras (a broadcast on every network interface) and `serial`, `model` and `index`
choose one, as with harvesters.

Settings go through the same code as the harvesters path (`GenICamBase._configure`), with
Aravis's range and access checks on, so a value outside the camera's range, a read-only feature
or an absent one is refused by name. Aravis's register cache is off: a read is the camera's
answer (`read_feature`, `applied`).

Capture: free-run hands back the frames queued before the call and returns the next complete
one; software trigger executes TriggerSoftware and returns the frame it produced. Incomplete
frames (lost packets Aravis could not get resent) are dropped and counted in the time-out's
message. The device timestamp is the buffer's (ns -> s; Aravis converts the camera's ticks),
`meta["device_frame_id"]` the GVSP block id.

A camera that vanishes: a capture that gets no frame within its time-out asks the camera for
its control-channel register; when it no longer answers (Aravis's GVCP time-out, about 2.5 s) or
no longer grants this host control (it restarted), the capture raises `CaptureTimeout` saying
the link is down and the camera is FAULTED: the next call raises `ConnectionLost` until
`connect()` succeeds again. Aravis's heartbeat reports a lost control too (`control-lost`), and a
command the camera does not acknowledge (the software trigger) is `ConnectionLost` at once.
Releasing a camera that is gone blocks inside Aravis for several seconds (it tries to give
control back), so that happens on a background thread.
"""

from __future__ import annotations

import threading
import time
from typing import Any

from drivers.cameras._common import CameraSettingError, Grabbed
from drivers.cameras._genicam import DeviceInfo, Features, GenICamBase, GenICamSettings
from drivers.interfaces import CaptureTimeout, ConnectionLost, DeviceState

# PFNC codes of the formats the driver converts (GigE Vision carries the code in each frame's leader)
_PIXEL_FORMATS = {
    0x01080001: "Mono8", 0x01100003: "Mono10", 0x01100005: "Mono12", 0x01100025: "Mono14",
    0x01100007: "Mono16", 0x02180014: "RGB8", 0x02180015: "BGR8", 0x02200016: "RGBa8", 0x02200017: "BGRa8",
}
_CCP = 0x0A00  # GigE Vision bootstrap register: control channel privilege (bit 1 control, bit 0 exclusive)
_GENCP_VERSION = 0x0000  # the first bootstrap register of a USB3 Vision device
# ArvDeviceError codes that mean the link (or our control of the camera) is gone, not a refused value
_LINK_ERRORS = {"not-connected", "transfer-error", "timeout", "not-controller", "protocol-error-access-denied"}


def _aravis():
    """Aravis and GLib through GObject introspection, or a clear error saying what to install."""
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis, GLib
    except ImportError as exc:
        raise CameraSettingError(f"library: aravis needs PyGObject in this Python ({exc}); install cellctl with "
                                 "its aravis extra (pip install -e '.[aravis]') after tools/ensure-system") from exc
    except ValueError as exc:  # the typelib is absent: "Namespace Aravis not available"
        raise CameraSettingError(f"library: aravis needs Aravis's introspection data ({exc}); install Debian's "
                                 "gir1.2-aravis-0.8 (tools/ensure-system)") from exc
    return Aravis, GLib


class AravisCamera(GenICamBase):
    """A GenICam camera through Aravis (built by `GenICamCamera.create` for `library: aravis`)."""

    Settings = GenICamSettings

    def __init__(self, name: str, settings: GenICamSettings):
        super().__init__(name, settings)
        self._camera = None  # Aravis.Camera
        self._device = None  # Aravis.Device (GvDevice for GigE Vision)
        self._stream = None  # Aravis.Stream
        self._control_lost = threading.Event()  # set by Aravis's heartbeat thread
        self._lost_handler: int | None = None
        self._acquiring = False
        self._where = settings.address or "?"

    # -- hooks -------------------------------------------------------------
    def _open(self) -> tuple[int, int]:
        Aravis, GLib = _aravis()
        s = self.settings
        self._control_lost.clear()
        if s.address is not None:
            device_id = self._where = s.address
        else:
            chosen = self._discover(Aravis)
            device_id, self._where = chosen.id, chosen.address or chosen.id
        try:
            self._camera = Aravis.Camera.new(device_id)
        except GLib.Error as exc:
            what = (f"no GigE Vision camera answers at {s.address}" if s.address
                    else f"camera {device_id!r} did not open")
            raise ConnectionLost(f"{self.name}: {what} ({exc.message}); check the address, the cable and the "
                                 "camera's power, and that no other program controls it") from exc
        self._device = self._camera.get_device()
        if isinstance(self._device, Aravis.GvDevice) and not self._device.is_controller():
            raise ConnectionLost(f"{self.name}: the camera at {self._where} is controlled by another program "
                                 "(another cell, a viewer); close it there, then connect() again")
        if s.address is not None:
            self._check_identity(GLib)
        self._device.set_range_check_policy(Aravis.RangeCheckPolicy.ENABLE)
        self._device.set_access_check_policy(Aravis.AccessCheckPolicy.ENABLE)
        self._device.set_register_cache_policy(Aravis.RegisterCachePolicy.DISABLE)
        lost = self._control_lost
        self._lost_handler = self._device.connect("control-lost", lambda _device: lost.set())
        features = self._features()
        self._write(features, "acquisition", ["AcquisitionMode"], "Continuous", quiet=True)
        self._configure(features)
        width, height = int(features.get("Width")), int(features.get("Height"))
        try:
            self._stream = self._camera.create_stream(None, None)
            payload = self._camera.get_payload()
        except GLib.Error as exc:
            raise ConnectionLost(f"{self.name}: the camera at {self._where} opened no stream ({exc.message}); "
                                 "check the network (firewall, packet size), then connect() again") from exc
        for _ in range(s.num_buffers):
            self._stream.push_buffer(Aravis.Buffer.new_allocate(payload))
        features.execute("AcquisitionStart")
        self._acquiring = True
        return width, height

    def _discover(self, Aravis) -> DeviceInfo:
        """The camera the settings choose among those Aravis discovers (listed in order of device id)."""
        Aravis.update_device_list()
        devices = sorted((DeviceInfo(Aravis.get_device_model(i), Aravis.get_device_serial_nbr(i),
                                     Aravis.get_device_id(i), Aravis.get_device_address(i))
                          for i in range(Aravis.get_n_devices())), key=lambda d: d.id or "")
        return devices[self._choose_device(devices, "among the cameras Aravis discovered")]

    def _check_identity(self, GLib) -> None:
        """With an address: the camera found there is the one serial/model name, or a clear error."""
        s = self.settings
        found = {}
        for key, asked, read in (("serial", s.serial, self._camera.get_device_serial_number),
                                 ("model", s.model, self._camera.get_model_name)):
            if asked is not None:
                try:
                    found[key] = read()
                except GLib.Error as exc:
                    found[key] = f"unreadable ({exc.message})"
        wrong = [f"{key} {found[key]!r}, not {asked!r}" for key, asked in (("serial", s.serial), ("model", s.model))
                 if asked is not None and found[key] != asked]
        if wrong:
            raise CameraSettingError(f"{self.name}: the camera at {s.address} has {' and '.join(wrong)}; "
                                     "check the address or the serial/model in the cell file")

    def _features(self) -> Features:
        return _AravisFeatures(self)

    def _grab(self, timeout_s: float) -> Grabbed:
        Aravis, _ = _aravis()
        if self._control_lost.is_set():
            raise self._fault(ConnectionLost(f"{self.name}: the camera at {self._where} no longer grants this host "
                                             "control (it restarted, or another program took it); connect() again"))
        self._drop_queued()
        try:
            if self._software_trigger:
                self._features().execute("TriggerSoftware")
        except ConnectionLost as exc:
            raise self._fault(exc) from exc
        deadline = time.monotonic() + timeout_s
        incomplete: list[str] = []
        while (left := deadline - time.monotonic()) > 0:
            buffer = self._stream.timeout_pop_buffer(max(1, int(left * 1e6)))
            if buffer is None:
                break
            host = time.monotonic()
            try:
                status = buffer.get_status()
                if status != Aravis.BufferStatus.SUCCESS:
                    incomplete.append(status.value_nick)
                    continue
                return self._decode(buffer, host)
            finally:
                self._stream.push_buffer(buffer)
        dropped = f" ({len(incomplete)} incomplete frame(s) dropped: {', '.join(sorted(set(incomplete)))})" \
            if incomplete else ""
        down = self._link_problem()
        if down:
            raise self._fault(CaptureTimeout(
                f"{self.name}: no frame within {timeout_s:g} s{dropped}, and the camera at {self._where} {down}: "
                "the link is down; check the cable and the camera's power, then connect() again"))
        raise CaptureTimeout(f"{self.name}: no frame within {timeout_s:g} s{dropped}; check the trigger, the cable, "
                             "the frame rate and the packet size")

    def _drop_queued(self) -> None:
        """Hand back frames that completed before this call (stale after a move)."""
        while (stale := self._stream.try_pop_buffer()) is not None:
            self._stream.push_buffer(stale)

    def _decode(self, buffer, host: float) -> Grabbed:
        code = buffer.get_image_pixel_format()
        fmt = _PIXEL_FORMATS.get(code, f"PFNC 0x{code:08x}")
        image = self._image(buffer.get_image_data(), fmt, buffer.get_image_width(), buffer.get_image_height())
        meta = self._meta(fmt)
        meta["device_frame_id"] = int(buffer.get_frame_id())
        ticks_ns = buffer.get_timestamp()
        return Grabbed(image, ticks_ns * 1e-9 if ticks_ns else None, host, self._exposure_s, meta)

    def _link_problem(self) -> str | None:
        """Why the camera cannot be reached (after a capture got no frame), or None when it still answers."""
        Aravis, GLib = _aravis()
        if self._control_lost.is_set():
            return "no longer grants this host control"
        gige = isinstance(self._device, Aravis.GvDevice)
        try:
            value = self._device.read_register(_CCP if gige else _GENCP_VERSION)
        except GLib.Error as exc:
            return f"does not answer ({exc.message})"
        if gige and not value & 0x3:
            return "no longer grants this host control (it restarted?)"
        return None

    def _release(self) -> None:
        """Stop and let go of the camera; one that is gone is let go on a background thread (Aravis blocks)."""
        if self._camera is None:
            self._stream = self._device = None
            return
        healthy = self._state is not DeviceState.FAULTED and not self._control_lost.is_set()
        if isinstance(self._device, _aravis()[0].GvDevice) and not self._device.is_controller():
            healthy = False  # giving back a control it never had waits for the camera's answer in vain
        if self._lost_handler is not None:
            self._device.disconnect(self._lost_handler)
            self._lost_handler = None
        if healthy and self._acquiring:
            try:
                self._features().execute("AcquisitionStop")
            except ConnectionLost:
                healthy = False
            except _aravis()[1].Error:  # refused: the camera is still there, and is let go all the same
                pass
        self._acquiring = False
        doomed = [self._stream, self._camera, self._device]  # the only references: dropping them frees them
        self._stream = self._camera = self._device = None
        if healthy:
            doomed.clear()  # gives control back at once, so a new connect() can take it
        else:
            threading.Thread(target=doomed.clear, name=f"{self.name}-aravis-release", daemon=True).start()


class _AravisFeatures(Features):
    """Features through an Aravis device, by node type; a link error is ConnectionLost.

    The device is read from the camera at each call, never kept: an error's traceback holds these objects,
    and a kept device would then be freed wherever the garbage collector runs, blocking that thread for
    seconds while Aravis gives control back to a camera that is gone (see `AravisCamera._release`)."""

    def __init__(self, camera: AravisCamera):
        self.Aravis, GLib = _aravis()
        self._GLib = GLib
        self._owner = camera
        self.errors = (GLib.Error, ValueError, TypeError)

    @property
    def _device(self):
        if self._owner._device is None:
            raise ConnectionLost(f"{self._name}: the camera is not connected; connect() first")
        return self._owner._device

    @property
    def _name(self) -> str:
        return self._owner.name

    @property
    def _where(self) -> str:
        return self._owner._where

    def _node(self, name: str):
        node = self._device.get_feature(name)
        if node is None:
            raise ValueError(f"no feature {name}")
        return node

    def _call(self, method: str, *args):
        try:
            return getattr(self._device, method)(*args)
        except self._GLib.Error as exc:
            if self._is_link_error(exc):
                raise ConnectionLost(f"{self._name}: the camera at {self._where} did not answer {args[0]} "
                                     f"({exc.message}); check the cable and the camera's power, then connect() "
                                     "again") from exc
            raise

    def _is_link_error(self, exc) -> bool:
        if exc.domain != "arv-device-error-quark":
            return False
        return any(int(v) == exc.code for v in self.Aravis.DeviceError.__enum_values__.values()
                   if v.value_nick in _LINK_ERRORS)

    def has(self, name: str) -> bool:
        return self._device.get_feature(name) is not None

    def get(self, name: str) -> Any:
        A = self.Aravis
        node = self._node(name)
        if isinstance(node, A.GcEnumeration) or isinstance(node, A.GcString):
            return self._call("get_string_feature_value", name)
        if isinstance(node, A.GcFloat):
            return self._call("get_float_feature_value", name)
        if isinstance(node, A.GcInteger):
            return self._call("get_integer_feature_value", name)
        if isinstance(node, A.GcBoolean):
            return self._call("get_boolean_feature_value", name)
        raise TypeError(f"{name} is a {type(node).__name__}, which has no value to read")

    def set(self, name: str, value: Any) -> None:
        A = self.Aravis
        node = self._node(name)
        if isinstance(node, A.GcEnumeration) or isinstance(node, A.GcString):
            self._call("set_string_feature_value", name, str(value))
        elif isinstance(node, A.GcFloat):
            self._call("set_float_feature_value", name, float(value))
        elif isinstance(node, A.GcInteger):
            if isinstance(value, bool) or float(value) != int(value):
                raise ValueError(f"{name} takes whole numbers, not {value!r}")
            self._call("set_integer_feature_value", name, int(value))
        elif isinstance(node, A.GcBoolean):
            self._call("set_boolean_feature_value", name, bool(value))
        else:
            raise TypeError(f"{name} is a {type(node).__name__}, which takes no value")

    def entries(self, name: str) -> list[str]:
        return list(self._call("dup_available_enumeration_feature_values_as_strings", name))

    def execute(self, name: str) -> None:
        self._call("execute_command", name)
