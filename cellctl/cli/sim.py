"""`cellctl sim`: one protocol simulator of a cell file's simulated world, on its own.

For commissioning a driver by hand or from another program (a UR polyscope-less test, a Modbus
poller): `cellctl sim abb --config config/sim-microcell.yaml` serves the simulated arm over the
open_abb protocol until Ctrl-C or SIGTERM. Cells that list `sim.servers` start the same simulators
themselves, so routines need nothing of this. A simulator takes no ownership of the cell (cellctl.startup.ownership):
it plays the device, and the process driving it owns the cell; its ports are its lock, and one in use is
refused naming the port and what holds it.
"""

from __future__ import annotations

import signal
import threading
from pathlib import Path

from drivers.sim.protocols import SIMULATORS

from cellctl.cli.args import InputError, parse_params


class SimServeError(InputError):
    """Bad input to `cellctl sim` (exit status 2)."""


def add_sim_command(sub) -> None:
    sim = sub.add_parser("sim", help="serve a protocol simulator (abb, ur, epick, vgc10) of the cell's simulated "
                                     "world, or write a simulated camera's frames as files")
    which = sim.add_subparsers(dest="protocol", required=True)
    for protocol in SIMULATORS:
        p = which.add_parser(protocol, help=f"the {protocol} protocol simulator (until Ctrl-C / SIGTERM)")
        p.add_argument("--config", required=True, help="cell file with a sim: section")
        p.add_argument("--host", default="127.0.0.1", help="loopback address to bind (ur: 127.0.0.x, fixed ports)")
        if protocol != "ur":
            p.add_argument("--port", type=int, help="default: the protocol's standard port; 0: a free one")
        if protocol == "abb":
            p.add_argument("--logger-port", type=int, help="the logger (pose stream) port; default: --port + 1 "
                                                           "(a free one with --port 0); 0: a free one")
            p.add_argument("--dialect", choices=("open_abb", "cellctl"),
                           help="reply format: open_abb (default: the public SERVER.mod's, no terminator, for "
                                "independent open_abb clients) or cellctl (ended by '#', as CellctlServer.mod)")
        if protocol == "epick":
            p.add_argument("--serial", metavar="DEV", help="serve RTU on this serial device instead of TCP "
                                                             "(e.g. one end of `socat -d -d pty,raw,echo=0 pty,raw,echo=0`)")
        example = "slow_reply_s=0.3" if protocol == "ur" else "reply_delay_s=0.01"
        p.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                       help=f"simulator setting or fault knob (e.g. {example}); an unknown one is refused with "
                            "the list of allowed ones")
        p.set_defaults(func=cmd_sim)
    files = which.add_parser("camera-files", help="write frames of a simulated camera as PNGs and an FFV1 video")
    files.add_argument("--config", required=True, help="cell file with a sim: section")
    files.add_argument("--out", required=True, help="directory to write into")
    files.add_argument("--camera", help="camera of the sim section (default: the first)")
    files.add_argument("--frames", type=int, default=8)
    files.add_argument("--fps", type=float, default=10.0)
    files.set_defaults(func=cmd_camera_files)


def _sim_cell(path: str):
    from cellctl.config import load_cell_file

    config, _ = load_cell_file(path, routines=False)  # a simulator runs no routine: their sections are not its
    if config.sim is None:
        raise SimServeError(f"{path}: the cell file has no 'sim:' section; a simulator needs a simulated world")
    return config


def cmd_sim(args) -> int:
    config = _sim_cell(args.config)
    port = getattr(args, "port", None)
    if port is not None and not 0 <= port <= 65535:
        raise SimServeError(f"--port {port}: expected 1..65535, or 0 for a free port")
    logger_port = getattr(args, "logger_port", None)
    if logger_port is not None and not 0 <= logger_port <= 65535:
        raise SimServeError(f"--logger-port {logger_port}: expected 1..65535, or 0 for a free port")
    if logger_port is not None and logger_port != 0 and logger_port == port:
        raise SimServeError(f"--logger-port {logger_port}: the same as --port; give two ports")
    options = parse_params(args.option)
    if args.protocol == "abb":  # on its own, the simulator answers as the public server does unless told
        given = options.get("reply_dialect")
        if args.dialect is not None and given is not None and given != args.dialect:
            raise SimServeError(f"--dialect {args.dialect} and --option reply_dialect={given} disagree; give one")
        options["reply_dialect"] = given or args.dialect or "open_abb"
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:  # the handlers are this command's only: restored however it ends (tests call main() in-process)
        server, spec = _start(args, config, port, logger_port, options)
        where = {"abb": lambda: f"{spec.host}:{server.motion_port} (logger {server.logger_port}), "
                                f"{server.reply_dialect} replies",
                 "ur": lambda: f"{spec.host} (dashboard 29999, primary 30001, secondary 30002, script 30003, "
                               "RTDE 30004)"}.get(args.protocol, lambda: server.where)()
        print(f"cellctl sim: {args.protocol} simulator of '{config.cell.name}' serving on {where}; "
              "Ctrl-C or SIGTERM stops it", flush=True)
        try:
            stop.wait()
        finally:
            server.close()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    print(f"cellctl sim: {args.protocol} simulator stopped", flush=True)
    return 0


def _start(args, config, port, logger_port, options):
    """The running simulator and its SimServer spec; SimServeError (exit 2) for an option or address it refuses:
    the message lists the allowed options, or says the address is taken."""
    from drivers.sim.kinds import build_world
    from drivers.sim.micro.config import SimServer
    from drivers.sim.servers import start_server

    from cellctl.errors import ServiceError
    from cellctl.startup.ownership import check_port_free

    fix = "pick another --host (its ports are fixed)" if args.protocol == "ur" else "pick another --port or --host"
    try:  # a port in use is named with what holds it, before any simulator (or its library) starts
        for taken in _ports(args, port, logger_port):
            check_port_free(args.host, taken, f"{args.protocol} simulator", fix)
    except ServiceError as exc:
        raise SimServeError(str(exc)) from None
    try:
        spec = SimServer(protocol=args.protocol, host=args.host, port=port, options=options,
                         serial_port=getattr(args, "serial", None))
        limits = config.arm.options.get("limits")
        if logger_port is not None:  # a cell file's sim.servers entry has no logger port: start it here
            from drivers.sim.servers.abb import MOTION_PORT, start

            return start(build_world(config.sim), spec.host, MOTION_PORT if port is None else port,
                         logger_port=logger_port, options=options, limits=limits), spec
        return start_server(spec, build_world(config.sim), limits), spec
    except (ValueError, TypeError) as exc:  # unknown or bad option: the message lists the allowed ones
        raise SimServeError(f"{args.protocol} simulator: {exc}") from None
    except OSError as exc:  # taken since the check, not a local address, or no such serial device
        raise SimServeError(f"{args.protocol} simulator cannot listen: {exc.strerror or exc}; {fix}") from None


def _ports(args, port: int | None, logger_port: int | None) -> list[int]:
    """The TCP ports the simulator is to listen on, as its server module chooses them (0: a free one)."""
    from importlib import import_module

    if getattr(args, "serial", None):
        return []
    if args.protocol == "ur":
        from drivers.sim.servers.ur.server import PORTS

        return list(PORTS.values())
    server = import_module(f"drivers.sim.servers.{args.protocol}")
    if args.protocol == "abb":
        motion = server.MOTION_PORT if port is None else port
        return [motion, (motion + 1 if motion else 0) if logger_port is None else logger_port]
    return [server.TCP_PORT if port is None else port]


def cmd_camera_files(args) -> int:
    from drivers.limits import WorkspaceBox
    from drivers.sim.servers.camera_files import serve

    config = _sim_cell(args.config)
    if args.camera is not None and args.camera not in config.sim.cameras:
        raise SimServeError(f"--camera {args.camera!r}: not a camera of the sim section; "
                            f"allowed: {', '.join(sorted(config.sim.cameras))}")
    if args.frames < 1 or args.fps <= 0:
        raise SimServeError("--frames must be at least 1 and --fps above 0")
    limits = config.arm.options.get("limits")
    files = serve(config.sim, Path(args.out), args.camera, args.frames, args.fps,
                  WorkspaceBox(**limits) if limits else None)
    print(f"{len(files.images)} frames of {files.camera} ({files.resolution[0]}x{files.resolution[1]}): "
          f"{files.sequence}, {files.video}")
    return 0
