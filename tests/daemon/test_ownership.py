"""One process owns a cell (cellctl.ownership): a second owner is refused before anything is touched.

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
from daemon_helpers import ROOT, SEED, SMALL, DaemonProcess, write_cell_file

from cellctl.cli import main
from cellctl.config import load_cell_file
from cellctl.ownership import OWNER_FILE, CellOwned, own_cell, own_store
from tests.conftest import MICROCELL

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
    assert f"is owned by pid {owner.proc.pid}" in err and f"--url {owner.url}" in err, err
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
        with pytest.raises(CellOwned, match=rf"device endpoint 127\.0\.0\.1:15000 \(arm\) is owned by pid "
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
