"""One process owns a cell (cellctl.startup.ownership): a second owner is refused before anything is touched.

With a daemon serving the cell: a second `serve` is refused naming it, an in-process `run` goes to it (and its
audit records the job), a local `calibrations activate` is refused, `sim` servers on its port are refused
naming what holds the port, read-only verbs still work. After the owner is killed with -9, the cell is free.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys

import pytest
import yaml

from cellctl.cli import main
from cellctl.config import DeviceConfig, load_cell_file
from cellctl.startup.ownership import OWNER_FILE, CellOwned, Ownership, endpoints, own_cell, own_store

from tests.conftest import MICROCELL
from tests.support.daemon import ROOT, SEED, SMALL, DaemonProcess, write_cell_file

SMALL_ARGS = [arg for key, value in SMALL.items() for arg in ("--param", f"{key}={value}")]


@pytest.fixture(scope="module")
def owner(tmp_path_factory):
    """A daemon serving a cell of its own store: the owner the other tests try to share the cell with."""
    with DaemonProcess(write_cell_file(tmp_path_factory.mktemp("owner"), realtime_factor=0.0)).start() as d:
        yield d


@pytest.fixture
def beside(monkeypatch):
    """This test process as another user of the owner's cell: the cell file names the store, nothing else."""
    for name in ("CELLCTL_STORE", "CELLCTL_URL", "CELLCTL_TOKEN", "CELLCTL_CA"):
        monkeypatch.delenv(name, raising=False)


def cli(*args) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("CELLCTL_STORE", "CELLCTL_URL")}
    return subprocess.run([sys.executable, "-m", "cellctl.cli", *map(str, args)], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=60)


def the_same(d: DaemonProcess) -> tuple:
    """What a second owner could have changed: the daemon's audit, jobs and calibrations, its URL file."""
    with d.client() as c:
        return (c.get("/audit").json()["audit"], c.get("/jobs").json()["jobs"],
                c.get("/calibrations").json()["calibrations"],
                (d.store / "daemon.url").read_text())


def test_a_second_serve_on_the_same_store_is_refused_naming_the_owner(owner):
    before = the_same(owner)
    second = cli("serve", "--config", owner.cell_file, "--port", "0")
    assert second.returncode == 2, second
    assert second.stderr.count("\n") == 1 and "Traceback" not in second.stderr, second.stderr
    for said in (f"the cell's store {owner.store} is owned by pid {owner.proc.pid}", "cellctl serve --config",
                 f"serving {owner.url}", f"cellctl run ROUTINE --url {owner.url}", f"CELLCTL_URL={owner.url}"):
        assert said in second.stderr, said
    assert owner.proc.poll() is None and the_same(owner) == before


def test_serve_on_a_port_in_use_is_one_line_and_exit_2(owner, tmp_path):
    port = int(owner.url.rsplit(":", 1)[1])
    other = write_cell_file(tmp_path)  # a cell of its own: only the port is shared
    second = cli("serve", "--config", other, "--port", port)
    assert second.returncode == 2, second
    assert second.stderr.count("\n") == 1 and "Traceback" not in second.stderr, second.stderr
    assert (f"the HTTP API: port {port} on 127.0.0.1 is in use by pid {owner.proc.pid} (" in second.stderr
            and "pick another with --port" in second.stderr), second.stderr
    store = tmp_path / "store"
    assert not (store / "daemon.sqlite").exists() and not (store / "daemon.token").exists()  # nothing started


def test_serve_with_its_opc_ua_port_in_use_is_one_line_and_exit_2(tmp_path):
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        cell_file = write_cell_file(tmp_path)
        data = yaml.safe_load(cell_file.read_text())
        data["opcua"] = {"enabled": True, "port": port}
        cell_file.write_text(yaml.safe_dump(data))
        second = cli("serve", "--config", cell_file, "--port", "0")
    assert second.returncode == 2, second
    assert second.stderr.count("\n") == 1 and "Traceback" not in second.stderr, second.stderr
    assert f"the OPC UA server: port {port} on 127.0.0.1 is in use by pid {os.getpid()} (" in second.stderr
    assert "set another opcua.port in the cell file" in second.stderr
    assert not (tmp_path / "store" / "daemon.sqlite").exists()


def test_sim_servers_on_a_taken_port_are_refused_naming_what_holds_it(owner, capsys):
    port = int(owner.url.rsplit(":", 1)[1])
    for protocol, ports in (("vgc10", ["--port", port]), ("epick", ["--port", port]),
                            ("abb", ["--port", "0", "--logger-port", port])):
        assert main(["sim", protocol, "--config", str(MICROCELL), *map(str, ports)]) == 2, protocol
        err = capsys.readouterr().err
        assert err.count("\n") == 1, err
        assert f"{protocol} simulator: port {port} on 127.0.0.1 is in use by pid {owner.proc.pid} (" in err, err
        assert "pick another --port" in err


def test_beside_the_daemon_a_run_goes_to_it_writes_are_refused_and_reads_work(owner, beside, tmp_path, capsys):
    cell = str(owner.cell_file)
    out = tmp_path / "here"
    assert main(["run", "virtual-grid", "--config", cell, "--out", str(out), "--seed", str(SEED), "--quiet",
                 *SMALL_ARGS]) == 0
    said = capsys.readouterr()
    assert (f"the cell's store {owner.store} is owned by the daemon at {owner.url} (pid {owner.proc.pid}); "
            "submitting the job there and following it; --out is ignored") in said.err
    assert "queued: virtual-grid" in said.out and ": done" in said.out
    assert not out.exists()  # nothing ran here
    audit, jobs, calibrations, _ = the_same(owner)
    submitted = [e for e in audit if e["action"] == "POST /jobs" and e["outcome"] == "ok"]
    assert submitted and f'"seed": {SEED}' in submitted[-1]["detail"]  # the daemon's audit records the run
    assert jobs[0]["state"] == "done"
    cal_id = calibrations[-1]["id"]

    assert main(["run", "virtual-grid", "--config", cell, "--out", str(out), "--resume"]) == 2
    assert f"cellctl resume JOB --url {owner.url}" in capsys.readouterr().err

    before = the_same(owner)
    assert main(["calibrations", "--config", cell, "--activate", str(cal_id)]) == 2
    err = capsys.readouterr().err
    assert f"is owned by pid {owner.proc.pid}" in err, err
    assert f"go through it: cellctl calibrations activate {cal_id} --url {owner.url}" in err, err
    assert the_same(owner) == before  # nothing activated, nothing audited

    for verb in (["calibrations"], ["health"], ["locate", "--camera", "cam1", "--pixel", "1200", "1000"],
                 ["calibrations", "export", str(cal_id)]):
        assert main([*verb, "--config", cell]) == 0, verb
    assert main(["token", "--config", cell]) == 0 and owner.token in capsys.readouterr().out
    assert main(["check", "--config", cell]) == 0


def test_an_in_process_owner_without_an_api_refuses_a_run(tmp_path, isolated_store, capsys):
    with own_store(isolated_store, "cellctl run virtual-grid"):
        assert main(["run", "virtual-grid", "--config", str(MICROCELL), "--out", str(tmp_path / "run")]) == 2
        err = capsys.readouterr().err
        assert f"is owned by pid {os.getpid()} (cellctl run virtual-grid, since " in err, err
        assert "wait for it to end" in err
    assert not (tmp_path / "run").exists()
    own_store(isolated_store, "again").release()  # given back


def test_two_cell_files_naming_one_robot_cannot_both_drive_it(tmp_path, monkeypatch):
    monkeypatch.setenv("CELLCTL_LOCK_DIR", str(tmp_path / "locks"))
    monkeypatch.delenv("CELLCTL_STORE")
    configs = []
    for name in ("a", "b"):
        path = tmp_path / f"{name}.yaml"
        path.write_text(yaml.safe_dump({"extends": str(ROOT / "config" / "sim-microcell-abb.yaml"),
                                        "store_dir": str(tmp_path / name)}))
        configs.append(load_cell_file(path)[0])
    with own_cell(configs[0], tmp_path / "a", "cellctl serve --config a.yaml"):
        with pytest.raises(CellOwned, match=rf"device endpoint tcp 127\.0\.0\.1:15000 \(arm\) is owned by pid "
                                            rf"{os.getpid()} \(cellctl serve --config a\.yaml"):
            own_cell(configs[1], tmp_path / "b", "cellctl serve --config b.yaml")
        own_store(tmp_path / "b", "b's store was given back").release()


def test_after_the_owner_is_killed_the_cell_is_free_again(tmp_path):
    cell_file = write_cell_file(tmp_path, realtime_factor=0.0)
    with DaemonProcess(cell_file).start() as first:
        first.kill9()
    with DaemonProcess(cell_file).start() as second:
        assert f'"pid": {second.proc.pid},' in (second.store / OWNER_FILE).read_text()
        assert second.url in (second.store / OWNER_FILE).read_text()


class _Cell:
    """Just the devices of a cell file, for endpoints()."""

    def __init__(self, **devices):
        self._devices = devices

    def devices(self):
        for name, (kind, options) in self._devices.items():
            yield kind, name, DeviceConfig(**options)


BOX = {"x_mm": [-500, 500], "y_mm": [-500, 500], "z_mm": [0, 500]}


def locked(kind, **options) -> list[str]:
    if kind == "arm":
        options.setdefault("limits", BOX)
    return [endpoint for _, endpoint in endpoints(_Cell(dev=(kind, options)))]


def test_device_endpoints_are_named_with_the_drivers_defaults_filled_in(tmp_path):
    assert locked("arm", backend="abb", host="10.0.0.5") == locked("arm", backend="abb", host="10.0.0.5",
                                                                   motion_port=5000) == ["tcp 10.0.0.5:5000"]
    assert locked("arm", backend="abb", host="localhost") == locked("arm", backend="abb", host="127.0.0.1")
    assert locked("arm", backend="ur", host="LOCALHOST") == ["tcp 127.0.0.1:30004"]
    assert locked("gripper", backend="epick") == [f"device {os.path.realpath('/dev/ttyUSB0')}"]  # serial by default
    (tmp_path / "ttyUSB7").touch()
    (tmp_path / "gripper").symlink_to(tmp_path / "ttyUSB7")  # a udev name and the device it points at
    assert locked("gripper", backend="epick", serial_port=str(tmp_path / "gripper")) == [f"device {tmp_path}/ttyUSB7"]
    assert locked("gripper", backend="epick", transport="tcp") == ["tcp 127.0.0.1:54321"]
    assert locked("gripper", backend="vgc10") == ["tcp 192.168.1.1:502"]
    assert locked("camera", backend="uvc", source="/dev/video0") == ["device /dev/video0"]
    assert locked("camera", backend="uvc", source=0) == []  # an index names no file another process shares
    assert locked("camera", backend="oak", device="14442C10D13EABCE00") == ["camera 14442C10D13EABCE00"]
    assert locked("arm", backend="sim") == []


def test_fleet_restore_into_an_owned_store_is_refused_before_writing(tmp_path, monkeypatch, capsys):
    from cellctl.fleet import plant

    monkeypatch.setattr(plant, "connect", lambda dsn: __import__("contextlib").nullcontext(None))
    monkeypatch.setattr(plant, "restore_records", lambda conn, cell: ([{"target": "t", "version": 1}], []))
    monkeypatch.setattr(plant, "last_ids", lambda conn, cell: {})
    (tmp_path / "dsn").write_text("postgresql://unused\n")
    (tmp_path / "dsn").chmod(0o600)
    store = tmp_path / "store"
    with own_store(store, "cellctl serve --config cell.yaml"):
        assert main(["fleet", "restore", "--cell", "c1", "--store", str(store),
                     "--dsn-file", str(tmp_path / "dsn")]) == 2
    err = capsys.readouterr().err
    assert f"the cell's store {store} is owned by pid {os.getpid()}" in err and "stop it first" in err, err
    assert sorted(p.name for p in store.iterdir()) == [OWNER_FILE]  # nothing restored


def test_a_lock_file_is_never_opened_through_a_symlink(tmp_path):
    (tmp_path / "elsewhere").write_text("precious\n")
    (tmp_path / "store").mkdir()
    (tmp_path / "store" / OWNER_FILE).symlink_to(tmp_path / "elsewhere")
    with pytest.raises(Exception, match="cannot open its lock"):
        own_store(tmp_path / "store", "cellctl serve")
    assert (tmp_path / "elsewhere").read_text() == "precious\n"


def test_the_owner_record_is_rewritten_in_place_never_left_empty(tmp_path):
    with own_store(tmp_path, "cellctl serve --config a-rather-long-cell-file-name.yaml") as owned:
        owned.serving("http://127.0.0.1:8470")
        assert '"url": "http://127.0.0.1:8470"}\n' in (tmp_path / OWNER_FILE).read_text()
    with Ownership("x", tmp_path) as short:
        short.claim(tmp_path / OWNER_FILE, "the store")
        assert (tmp_path / OWNER_FILE).read_text().count("\n") == 1  # cut to its new length: no old tail


def test_opcua_trust_needs_only_the_store(tmp_path, monkeypatch, capsys):
    for name in ("CELLCTL_URL", "CELLCTL_STORE"):
        monkeypatch.delenv(name, raising=False)
    assert main(["opcua", "certificates", "--store", str(tmp_path)]) == 0
    assert "trusted on Sign / SignAndEncrypt (0)" in capsys.readouterr().out
    with own_store(tmp_path, "cellctl run virtual-grid"):  # an owner with no API: the refusal names the verb
        assert main(["opcua", "trust", "0123456789abcdef", "--store", str(tmp_path)]) == 2
    assert f"is owned by pid {os.getpid()} (cellctl run virtual-grid" in capsys.readouterr().err
