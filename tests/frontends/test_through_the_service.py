"""Every front end goes through the service: the checks, the ranges and the audit happen there, once.

An in-process `cellctl run` is checked as a daemon's job is and audited in the store's audit log; a local-store
`cellctl calibrations activate` is audited too; the lock's TTL, finite pixels and the seed's range are the
service's, whichever front end asks (OPC UA's wire is tested in tests/opcua/test_opcua.py)."""

import json

import pytest

from cellctl.cli import main
from cellctl.config import load_cell_file
from cellctl.errors import InvalidRequest
from cellctl.service import Caller
from cellctl.service.auth import OperatorLock
from cellctl.service.local import LocalService
from cellctl.stores.calibrations import CalibrationStore
from cellctl.stores.jobs import DB_FILE, JobStore

from tests.conftest import MICROCELL

TINY = ["--param", "rows=3", "--param", "cols=3", "--param", "n_verify=2", "--param", "passes=1"]


def audit(store) -> list[dict]:
    log = JobStore(store / DB_FILE)
    try:
        return log.audit_log()
    finally:
        log.close()


def run_cli(*args) -> int:
    return main([str(a) for a in args])


def test_an_in_process_run_is_checked_and_audited_as_a_daemon_job(tmp_path, isolated_store, capsys):
    assert run_cli("run", "virtual-grid", "--config", MICROCELL, "--out", tmp_path / "ok", "--seed", 3, "--quiet",
                   *TINY) == 0
    # the service's own checks: a non-finite parameter (which the CLI's YAML reads as a float) and the seed's range
    assert run_cli("run", "virtual-grid", "--config", MICROCELL, "--out", tmp_path / "nan", "--quiet",
                   "--param", "outlier_sigma=.nan") == 2
    assert "params.outlier_sigma: must be a finite number" in capsys.readouterr().err
    assert run_cli("run", "virtual-grid", "--config", MICROCELL, "--out", tmp_path / "seed", "--seed", -3) == 2
    assert "seed: -3; allowed: a simulation seed from 0 to 4294967295" in capsys.readouterr().err
    assert not (tmp_path / "nan").exists() and not (tmp_path / "seed").exists()  # refused before anything ran
    runs = [e for e in audit(isolated_store) if e["action"] == "cli run (in-process)"]
    assert [(e["target"], e["who"]) for e in runs] == [("virtual-grid", "local")] * 3
    assert runs[0]["outcome"] == "ok" and json.loads(runs[0]["detail"])["out"] == str(tmp_path / "ok")
    assert runs[1]["outcome"].startswith("refused 422: params.outlier_sigma: must be a finite number")
    assert runs[2]["outcome"].startswith("refused 422: seed: -3")


def test_a_local_store_activate_is_audited_as_over_http(tmp_path, isolated_store, capsys):
    store = CalibrationStore(isolated_store)
    result = {"routine": "virtual-grid", "model": {"kind": "planar"}, "stats": {}}
    first, _ = (store.save("cam1", result, "", tmp_path) for _ in range(2))
    assert run_cli("calibrations", "--config", MICROCELL, "activate", first.id) == 0
    assert store.active("cam1").id == first.id
    assert run_cli("calibrations", "--config", MICROCELL, "activate", 999) == 2
    entries = [e for e in audit(isolated_store) if e["action"] == "cli calibrations"]
    assert [(e["target"], e["who"], e["outcome"][:11]) for e in entries] == [
        (f"calibration {first.id}", "local", "ok"), ("calibration 999", "local", "refused 404")]


@pytest.fixture
def service(isolated_store):
    config, text = load_cell_file(MICROCELL)
    log = JobStore(isolated_store / DB_FILE)
    yield LocalService(config, CalibrationStore(isolated_store), lock=OperatorLock(), audit_log=log, cell_text=text)
    log.close()


def test_the_lock_ttl_is_capped_by_the_service_for_every_front_end(service):
    caller = Caller("mes@opcua", via="OPC UA Lock/Acquire", credential="opcua-user")
    for ttl in (86401.0, 0.0, float("nan")):
        with pytest.raises(InvalidRequest, match=r"ttl_s: .*; allowed: seconds > 0, at most 86400 \(a day\)"):
            service.acquire_lock(caller, "MES", ttl)
    assert service.acquire_lock(caller, "MES", 86400.0)["holder"] == "MES"
    outcomes = [e["outcome"][:11] for e in service._audit_log.audit_log()]
    assert outcomes == ["refused 422"] * 3 + ["ok"]


def test_pixels_must_be_finite_and_seeds_in_range_whoever_asks(service):
    with pytest.raises(InvalidRequest, match=r"u_px, v_px: nan, 1.0; allowed: finite pixel coordinates"):
        service.locate("cam1", float("nan"), 1.0)
    with pytest.raises(InvalidRequest, match="seed: 4294967296; allowed: a simulation seed from 0 to 4294967295, or none"):
        service._check_job("virtual-grid", {}, 2**32)
