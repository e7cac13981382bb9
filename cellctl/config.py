"""The cell file: YAML validated by typed models.

Unknown keys and out-of-range values are errors that name the key, the value and
what is allowed. Each device's own options are validated by its backend's
`Settings` model, so the mock and the real device are chosen in the same place
(`backend: sim` or `backend: abb`) and checked the same way.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any, Literal, Union

import yaml
from pydantic import BaseModel, ConfigDict, Discriminator, Field, Tag, ValidationError, model_validator

from drivers.registry import UnknownBackend, backend_class
from drivers.sim import kinds

from calibration.routines import routine_class, routine_names  # names from file names; a class on first use
from calibration.routines.base import Area

from cellctl.textfile import NotUtf8, decode_utf8


class CellFileError(ValueError):
    """The cell file is wrong; the message lists every problem with its key path."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class DeviceConfig(BaseModel):
    """`backend` picks the driver; every other key is that driver's option."""

    model_config = ConfigDict(extra="allow", frozen=True)
    backend: str

    @property
    def options(self) -> dict[str, Any]:
        return dict(self.model_extra or {})


class AreaConfig(_Strict):
    camera: str
    centre_mm: tuple[float, float]
    size_mm: tuple[float, float] = Field(..., description="approximate field of view in robot coordinates")
    z_mm: float = Field(..., description="tool height that puts the feature in focus")
    alpha_cal_deg: float = Field(0.0, ge=-360, le=360)

    @model_validator(mode="after")
    def _positive(self):
        if min(self.size_mm) <= 0:
            raise ValueError(f"size_mm must be positive, got {list(self.size_mm)}")
        return self

    def to_area(self, name: str) -> Area:
        return Area(
            name=name,
            camera=self.camera,
            centre=(self.centre_mm[0] * 1e-3, self.centre_mm[1] * 1e-3),
            size=(self.size_mm[0] * 1e-3, self.size_mm[1] * 1e-3),
            z=self.z_mm * 1e-3,
            alpha_cal=math.radians(self.alpha_cal_deg),
        )


class CellInfo(_Strict):
    name: str
    description: str = ""


# `sim:` is a union tagged by its `world`, one member per row of the world-kind table (drivers/sim/kinds.py)
SimSection = Annotated[Union[tuple(Annotated[kind.config, Tag(name)] for name, kind in kinds.WORLD_KINDS.items())],
                       Discriminator(kinds.world_kind)]


class HealthSchedule(_Strict):
    """Checks the daemon runs by itself (opt-in): a `check` job every `every_h` hours, when the cell is idle and
    nobody holds the operator lock."""

    every_h: float = Field(..., gt=0, le=24 * 366, description="hours between checks (from the last one)")
    at_start: bool = Field(False, description="also check as soon as the daemon has started")
    targets: list[str] | None = Field(None, min_length=1, description="default: every target the check knows")
    update: bool = Field(False, description="touch up what drifted (else the verdict only)")


class BackupSettings(_Strict):
    """Backups of the store the daemon takes on its own (cellctl/stores/backup.py), as `cellctl store backup`."""

    every_h: float = Field(..., gt=0, le=24 * 365, allow_inf_nan=False, description="hours between two backups")
    keep: int = Field(7, ge=1, le=10_000, description="how many backups to keep (the oldest go first)")
    to: str | None = Field(None, description="folder of the backups; default: <store>-backups beside the store "
                                             "(put it on another disk to survive the store's disk)")

    def folder(self, store: Path) -> Path:
        from cellctl.stores.backup import default_backups

        return Path(self.to).expanduser() if self.to else default_backups(store)


class StoreSettings(_Strict):
    """The store's disk (cellctl/stores/disk_space.py): below `min_free_mb` free on its filesystem the daemon
    refuses new jobs, resumptions and saved images (HTTP 507), and says how much is free and what fills it."""

    # 100 MB: room for a job's images and records, and low enough that a CI machine or a small SD card still runs
    min_free_mb: float = Field(100.0, ge=0, le=10_000_000, allow_inf_nan=False,
                               description="free space (MB) to keep on the store's filesystem; 0: never refuse")
    backup: BackupSettings | None = Field(None, description="scheduled backups of the store (none unless set)")


class OperatorLockSettings(_Strict):
    """The operator lock (cellctl/service/auth.py): who commands the cell now."""

    break_after_idle_s: float = Field(60.0, ge=0, le=86_400, description="a lock can be broken (cellctl lock "
                                      "break) once its holder has neither renewed it nor commanded with it for "
                                      "this long; an open console renews its lease every 10 s")


class NamedPosition(_Strict):
    """A pose to go to by name (cellctl move-to --position NAME): the tool pointing down turned by alpha_deg, or,
    on a six-axis arm, any orientation as a unit quaternion."""

    x_mm: float = Field(..., allow_inf_nan=False)
    y_mm: float = Field(..., allow_inf_nan=False)
    z_mm: float = Field(..., allow_inf_nan=False)
    alpha_deg: float = Field(0.0, ge=-360, le=360)
    quaternion_wxyz: tuple[float, float, float, float] | None = Field(None, description="six-axis arms: w, x, y, z")

    @model_validator(mode="after")
    def _unit(self):
        if self.quaternion_wxyz is not None and abs(math.hypot(*self.quaternion_wxyz) - 1.0) > 1e-3:
            raise ValueError(f"quaternion_wxyz {list(self.quaternion_wxyz)} is not a unit quaternion (norm "
                             f"{math.hypot(*self.quaternion_wxyz):.4f}; allowed: norm 1 within 0.001)")
        return self


class ManualSettings(_Strict):
    """Manual motion (cellctl jog, move-to, grip, release and the console's jog panel): by the holder of the
    operator lock only, slower than a job, each move checked against the workspace box and the joint limits
    before it is sent, and audited."""

    speed_pct: float = Field(10.0, gt=0, le=100, description="manual speed, % of the arm's own speed limit (never "
                             "above 250 mm/s, the reduced speed of ISO 10218-1 for a person near the arm)")
    max_step_mm: float = Field(50.0, gt=0, le=1000, description="longest single jog step")
    max_step_deg: float = Field(30.0, gt=0, le=180, description="largest single jog turn")
    heartbeat_timeout_s: float = Field(0.15, ge=0.05, le=2.0, description="a move stops when its client has not "
                                       "said it is still there (the dead-man heartbeat) for this long")
    positions: dict[str, NamedPosition] = Field(default_factory=dict, description="named poses to go to")


class OpcuaSettings(_Strict):
    """The OPC UA server for the MES (cellctl.opcua), started by the daemon.

    Anonymous sessions browse and read; calling a method needs a user: any name with the daemon's token as
    password, or one of `user_certs`. Secure channels (Basic256Sha256, Sign and SignAndEncrypt) accept the
    client application certificates of `trusted_clients` and of the store's opcua/trusted/ only (an untrusted
    one is kept in opcua/rejected/: `cellctl opcua trust`); None ignores the client's certificate and is
    offered on loopback binds alone."""

    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = Field(4840, ge=0, le=65535, description="0: any free port (tests)")
    security: list[Literal["none", "sign", "sign_encrypt"]] = Field(
        ["none", "sign", "sign_encrypt"], min_length=1,
        description="endpoints offered; 'none' only when bound to loopback")
    trusted_clients: list[str] = Field(default_factory=list,
                                       description="client application certificates (DER or PEM files) "
                                                   "trusted on Sign / SignAndEncrypt channels")
    user_certs: dict[str, str] = Field(default_factory=dict,
                                       description="user name -> X.509 user certificate file allowed to call methods")


class HttpSettings(_Strict):
    """The daemon's HTTP API (cellctl.startup.tls): HTTPS, or plain HTTP only where the token stays on this machine.

    Bound beyond loopback the daemon serves HTTPS (its certificate from `cert_file`/`key_file`, else one it
    makes at first start in its store, key 0600) and refuses to start on plain HTTP unless `allow_plain`.
    Relative paths are taken from the cell file's folder."""

    tls: bool | None = Field(None, description="serve HTTPS; default: when cert_file is given (`cellctl serve "
                                               "--tls` also turns it on)")
    cert_file: str | None = Field(None, description="PEM certificate (chain) the daemon serves")
    key_file: str | None = Field(None, description="its PEM private key (owner-only: mode 0600)")
    names: list[str] = Field(default_factory=list, description="extra host names / IP addresses for the "
                                                               "certificate the daemon makes (its SANs)")
    allow_plain: bool = Field(False, description="accept plain HTTP on a non-loopback address (the bearer token "
                                                 "crosses the network in clear)")

    @model_validator(mode="after")
    def _pair(self):
        if (self.cert_file is None) != (self.key_file is None):
            raise ValueError("cert_file and key_file go together: give both, or neither (the daemon then "
                             "makes its own certificate)")
        if self.tls is False and self.cert_file is not None:
            raise ValueError("tls: false with a cert_file: remove one of them")
        return self

    @property
    def wants_tls(self) -> bool:
        return bool(self.tls) or self.cert_file is not None


class MqttTls(_Strict):
    ca_file: str | None = Field(None, description="CA certificate(s) to trust for the broker (PEM); default: the "
                                                   "system's")
    cert_file: str | None = Field(None, description="client certificate (PEM), for a broker that asks for one")
    key_file: str | None = Field(None, description="its private key (owner-only: mode 0600)")


class FleetPostgres(_Strict):
    dsn_file: str | None = Field(None, description="file holding the plant database's libpq DSN or URI, with its "
                                                   "password (owner-only: mode 0600)")
    dsn_env: str | None = Field(None, description="environment variable holding the DSN instead")

    @model_validator(mode="after")
    def _one(self):
        if (self.dsn_file is None) == (self.dsn_env is None):
            raise ValueError("give dsn_file or dsn_env, exactly one")
        return self


class FleetMqtt(_Strict):
    host: str
    port: int = Field(1883, ge=1, le=65535)
    topic_prefix: str = Field(..., min_length=1, pattern=r"^[^/#+\s](?:[^#+\s]*[^/#+\s])?$",
                              description="ISA-95 path such as plant/area/line: no wildcards, no leading or trailing /")
    username: str | None = None
    password_file: str | None = Field(None, description="file holding the password (owner-only: mode 0600)")
    password_env: str | None = Field(None, description="environment variable holding the password instead")
    tls: MqttTls | None = Field(None, description="connect over TLS (then port is usually 8883)")
    keepalive_s: int = Field(30, ge=5, le=3600, description="MQTT keep-alive: the broker sets status to offline "
                                                            "about 1.5 keep-alives after the cell falls silent "
                                                            "(Mosquitto 2.0: up to 5 s more)")
    progress_interval_s: float = Field(2.0, ge=0.1, le=3600, description="at most one progress event per job "
                                                                          "in this time")

    @model_validator(mode="after")
    def _password(self):
        if self.password_file is not None and self.password_env is not None:
            raise ValueError("give password_file or password_env, not both")
        if (self.password_file or self.password_env) and not self.username:
            raise ValueError("a password needs a username")
        return self


class FleetSettings(_Strict):
    """This cell in a fleet (cellctl.fleet): its records replicated to the plant database and the event stream.
    Both sinks are optional; the cell runs the same whether or not they are reachable."""

    cell_id: str | None = Field(None, min_length=1, max_length=64, pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]*$",
                                description="the cell's name in the plant (default: cell.name)")
    api_url: str | None = Field(None, description="the URL the plant shows for this cell's API (default: the "
                                                  "daemon's own)")
    postgres: FleetPostgres | None = None
    mqtt: FleetMqtt | None = None
    heartbeat_s: float = Field(10.0, ge=1, le=3600, description="how often the cell says it is alive (last_seen)")


class CellFile(_Strict):
    cell: CellInfo
    arm: DeviceConfig
    gripper: DeviceConfig | None = None
    operator: DeviceConfig = DeviceConfig(backend="console")
    cameras: dict[str, DeviceConfig] = Field(..., min_length=1)
    areas: dict[str, AreaConfig] = Field(default_factory=dict)
    routines: dict[str, dict[str, Any]] = Field(default_factory=dict, description="default parameters per routine")
    store_dir: str | None = Field(None, description="calibration store; default $XDG_DATA_HOME/cellctl/<cell name>")
    store: StoreSettings = Field(StoreSettings(), description="the store's disk: free space to keep")
    sim: SimSection | None = None
    health: HealthSchedule | None = Field(None, description="calibration checks on a schedule (the daemon)")
    http: HttpSettings = HttpSettings()
    opcua: OpcuaSettings = OpcuaSettings()
    operator_lock: OperatorLockSettings = OperatorLockSettings()
    manual: ManualSettings = ManualSettings()
    fleet: FleetSettings | None = Field(None, description="replication to the plant database and event stream")

    @model_validator(mode="after")
    def _cross_references(self):
        for name, area in self.areas.items():
            if area.camera not in self.cameras:
                raise ValueError(
                    f"areas.{name}.camera: {area.camera!r} is not a camera of this cell "
                    f"(defined: {', '.join(sorted(self.cameras))})"
                )
        return self

    def devices(self):
        """(kind, name, DeviceConfig) for every device."""
        yield "arm", "arm", self.arm
        if self.gripper is not None:
            yield "gripper", "gripper", self.gripper
        yield "operator", "operator", self.operator
        for name, cam in self.cameras.items():
            yield "camera", name, cam

    def store_path(self) -> Path:
        """Where calibrations are kept: $CELLCTL_STORE, else store_dir, else the user's data directory."""
        import os

        if os.environ.get("CELLCTL_STORE"):
            return Path(os.environ["CELLCTL_STORE"])
        if self.store_dir:
            return Path(self.store_dir).expanduser()
        data = Path(os.environ.get("XDG_DATA_HOME") or Path.home() / ".local" / "share")
        return data / "cellctl" / self.cell.name

    @property
    def fleet_name(self) -> str:
        """The cell's name in the plant."""
        return (self.fleet.cell_id if self.fleet and self.fleet.cell_id else None) or self.cell.name

    def areas_by_name(self) -> dict[str, Area]:
        return {name: a.to_area(name) for name, a in self.areas.items()}


# a simulated six-axis arm is of its world's model; a real arm says its own (arm.model, backends ur and abb)
SIM_ARM_MODELS = {"sim-ur5e": "ur5e", "sim-irb120": "irb120"}


def arm_model_of(config: CellFile) -> str | None:
    """The model of the cell's arm ("ur5e", "irb120", ...): a simulated six-axis arm's, else the arm's `model`
    setting (backends ur and abb), None when the cell file does not say."""
    if config.arm.backend in SIM_ARM_MODELS:
        return SIM_ARM_MODELS[config.arm.backend]
    model = config.arm.options.get("model")
    return str(model) if model else None


def load_cell_file(path: str | Path, routines: bool = True) -> tuple[CellFile, str]:
    """The validated cell file and its text (kept with every result it produces).

    A file may start from another (`extends: other.yaml`, relative to it) and change only what
    differs: mappings merge key by key, anything else replaces. The text is then the merged file,
    so a result still carries the whole cell it ran on.

    `routines=False` leaves the `routines:` sections unchecked (checking them imports their routines): for
    callers that only need the cell's store or devices.
    """
    path = Path(path)
    text = _read(path)
    data = _yaml(text, str(path))
    if isinstance(data, dict) and "extends" in data:
        data = _resolve_extends(path, data, (path.resolve(),))
        text = f"# {path}, with everything it extends merged in\n" + yaml.safe_dump(data, sort_keys=False)
    return parse_cell_file(text, str(path), routines), text


def _read(path: Path) -> str:
    try:
        return decode_utf8(path.read_bytes())
    except OSError as exc:
        raise CellFileError(f"{path}: cannot read the cell file: {exc.strerror or exc}") from None
    except NotUtf8 as exc:
        raise CellFileError(f"{path}: {exc}: save the cell file as UTF-8") from None


def _yaml(text: str, source: str):
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise CellFileError(f"{source}: not valid YAML: {exc}") from None


def _resolve_extends(path: Path, data: dict, seen: tuple[Path, ...]) -> dict:
    data = dict(data)
    base_name = data.pop("extends")
    if not isinstance(base_name, str) or not base_name:
        raise CellFileError(f"{path}: extends: expected the path of another cell file, got {base_name!r}")
    base_path = (path.parent / base_name).resolve()
    if base_path in seen:
        raise CellFileError(f"{path}: extends: {base_name} extends this file again (a cycle)")
    base = _yaml(_read(base_path), str(base_path))
    if not isinstance(base, dict):
        raise CellFileError(f"{base_path}: the cell file must be a mapping with keys cell, arm, cameras, ...")
    if "extends" in base:
        base = _resolve_extends(base_path, base, (*seen, base_path))
    return _merge(base, data)


def _merge(base: dict, changes: dict) -> dict:
    out = dict(base)
    for key, value in changes.items():
        out[key] = _merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def parse_cell_file(text: str, source: str = "<cell file>", routines: bool = True) -> CellFile:
    data = _yaml(text, source)
    if not isinstance(data, dict):
        raise CellFileError(f"{source}: the cell file must be a mapping with keys cell, arm, cameras, ...")
    try:
        cell = CellFile.model_validate(data)
    except ValidationError as exc:
        raise CellFileError(f"{source}: invalid cell file:\n" + _format(exc)) from None
    problems = []
    for kind, name, dev in cell.devices():
        key = f"cameras.{name}" if kind == "camera" else kind
        try:
            cls = backend_class(kind, dev.backend)
        except UnknownBackend as exc:
            problems.append(f"  {key}.backend: {exc}")
            continue
        try:
            cls.Settings(**dev.options)
        except ValidationError as exc:
            problems += ["  " + line.replace("  ", f"  {key}.", 1).strip() for line in _format(exc).splitlines()]
        if kinds.is_fake(kind, dev.backend):
            problems += _fake_problems(cell.sim, kind, name, key, dev)
    if routines:
        problems += _routine_problems(cell)
    if problems:
        raise CellFileError(f"{source}: invalid cell file:\n" + "\n".join(problems))
    return cell


def _routine_problems(cell: CellFile) -> list[str]:
    """Each `routines:` section (`NAME`, or `NAME.AREA` for a routine on one area) against that routine's
    parameters, as a run takes them: its known names, and each value of the type and range the routine allows."""
    if not cell.routines:
        return []
    problems = []
    for key, section in cell.routines.items():
        name, _, area = key.partition(".")
        if name not in routine_names():
            problems.append(f"  routines.{key}: unknown routine {name!r}; allowed: {', '.join(routine_names())}")
            continue
        params = routine_class(name).Params
        if area and "area" not in params.model_fields:
            problems.append(f"  routines.{key}: {name} takes no area (it has no 'area' parameter); use routines.{name}")
            continue
        if area and area not in cell.areas:
            problems.append(f"  routines.{key}: {area!r} is not an area of this cell (defined: "
                            f"{', '.join(sorted(cell.areas)) or 'none'})")
            continue
        # an area's section is taken over its routine's (reported there), as routine_params merges them
        values = {**cell.routines.get(name, {}), "area": area, **section} if area else section
        try:
            params.model_validate(values)
        except ValidationError as exc:
            for err in exc.errors():
                field = err["loc"][0] if err["loc"] else None
                if err["type"] == "missing" or (area and field is not None and field not in section):
                    continue  # a run gives what is missing; the base section's own errors are reported there
                where = ".".join(str(p) for p in (key, *err["loc"]))
                if err["type"] == "extra_forbidden":
                    problems.append(f"  routines.{where}: unknown parameter of {name} (got {err['input']!r}); "
                                    f"allowed: {', '.join(params.model_fields)}")
                else:
                    problems.append(f"  routines.{where}: {err['msg']} (got {err['input']!r})")
    return problems


def _fake_problems(sim, kind: str, name: str, key: str, dev: DeviceConfig) -> list[str]:
    """What is wrong with a simulated device: no world to run on, a fake of another kind of world, no camera
    of the sim section to render."""
    if sim is None:
        return [f"  {key}.backend: {dev.backend!r} needs a 'sim:' section describing the simulated world"]
    world = kinds.world_kind(sim)
    if not kinds.offers(sim, kind, dev.backend):
        fakes = kinds.WORLD_KINDS[world].fakes
        allowed = f"allowed: {fakes[kind].backend}" if kind in fakes else f"the {world} world simulates no {kind}"
        return [f"  {key}.backend: {dev.backend!r} does not run on the simulated world (sim.world: {world}); {allowed}"]
    sim_name = dev.options.get("sim_camera", name)
    if kind == "camera" and sim_name not in sim.cameras:
        return [f"  cameras.{name}: no sim.cameras.{sim_name} describes this simulated camera"]
    return []


def _format(exc: ValidationError) -> str:
    lines = []
    for err in exc.errors():
        # a tagged union (sim: by its `world`) puts the tag into the path: leave it out
        key = ".".join(str(p) for p in err["loc"] if p not in kinds.WORLD_KINDS) or "(top level)"
        value = err.get("input")
        shown = "" if isinstance(value, dict) else f" (got {value!r})"
        msg = err["msg"]
        if err["type"] == "extra_forbidden":
            msg = "unknown key"
        lines.append(f"  {key}: {msg}{shown}")
    return "\n".join(lines)
