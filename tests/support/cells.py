"""Cell files the tests write: the committed ABB cells on free ports (the committed files' ports may be taken on a
CI machine), their simulators started by the cell itself."""

from __future__ import annotations

from pathlib import Path

from tests.conftest import ROOT
from tests.support.ports import free_port_pair, free_ports


def write_ur_cell_file(folder: Path, base: str = "sim-microcell-ur.yaml") -> Path:
    """config/`base` (its UR simulator on a loopback address of its own: UR ports are fixed, and cells that share
    the address take turns) with its store in `folder`."""
    path = folder / "ur.yaml"
    path.write_text(f"extends: {ROOT / 'config' / base}\nstore_dir: {folder / 'store'}\n")
    return path


def write_abb_cell_file(folder: Path, extra: str = "", base: str = "sim-microcell-abb.yaml",
                        gripper: bool = True) -> Path:
    """config/`base` on free ports: the arm's motion and logger ports, and with `gripper` the VGC10's; `extra`:
    more top-level keys (a store_dir)."""
    motion = free_port_pair()  # the logger listens on motion + 1
    vgc, = free_ports()
    servers = [f"    - {{protocol: abb, port: {motion}}}"] + ([f"    - {{protocol: vgc10, port: {vgc}}}"] * gripper)
    path = folder / "abb.yaml"
    path.write_text(f"extends: {ROOT / 'config' / base}\n{extra}\n"
                    f"arm: {{motion_port: {motion}, logger_port: {motion + 1}}}\n"
                    + (f"gripper: {{port: {vgc}}}\n" if gripper else "")
                    + "sim:\n  servers:\n" + "\n".join(servers) + "\n")
    return path
