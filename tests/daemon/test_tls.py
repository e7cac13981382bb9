"""HTTPS beyond loopback (cellctl.startup.tls): a plain bind to 0.0.0.0 is refused before anything starts unless
the cell file allows it; with TLS the daemon serves the certificate it made (key 0600, kept across restarts) or
the cell file's, and the CLI (--ca / $CELLCTL_CA) and the console in Chromium (its SPKI pinned) work through
the pinned certificate, and fail clearly without it."""

from __future__ import annotations

import os
import socket
import ssl
import stat
import subprocess
import sys
from pathlib import Path

import httpx
import pytest
import yaml

from cellctl import cli
from cellctl.config import CellFileError, load_cell_file, parse_cell_file
from cellctl.startup import tls

from tests.support.chromium import CHROMIUM, CHROMIUM_ARGS
from tests.support.console import open_console
from tests.support.daemon import ROOT, DaemonProcess, wait_for, write_cell_file

TINY = {"rows": 3, "cols": 3, "n_verify": 0, "passes": 1}


def with_http(cell_file: Path, http: dict) -> Path:
    data = yaml.safe_load(cell_file.read_text())
    data["http"] = http
    cell_file.write_text(yaml.safe_dump(data))
    return cell_file


def served_certificate(url: str) -> bytes:
    """The DER certificate the daemon presents (not verified: that is what is compared)."""
    host, port = url.split("//")[1].rsplit(":", 1)
    return ssl.PEM_cert_to_DER_cert(ssl.get_server_certificate((host, int(port))))


def pem_to_der(path: Path) -> bytes:
    return ssl.PEM_cert_to_DER_cert(path.read_text())


@pytest.fixture(scope="module")
def tls_daemon(tmp_path_factory):
    """The daemon on every address (0.0.0.0) with --tls: HTTPS with a certificate it made at first start."""
    cell_file = write_cell_file(tmp_path_factory.mktemp("tls"), realtime_factor=0.05)
    with DaemonProcess(cell_file, args=("--host", "0.0.0.0", "--tls")).start() as d:
        yield d


def test_plain_http_beyond_loopback_is_refused_before_anything_starts(tmp_path):
    cell_file = write_cell_file(tmp_path)
    run = subprocess.run([sys.executable, "-m", "cellctl.cli", "serve", "--config", str(cell_file), "--host",
                          "0.0.0.0", "--port", "0"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert run.returncode == 2, run
    assert "refusing plain HTTP on 0.0.0.0" in run.stderr
    for remedy in ("--tls", "http: {tls: true}", "cert_file", "allow_plain: true", "127.0.0.1"):
        assert remedy in run.stderr, remedy
    store = tmp_path / "store"
    assert not (store / "daemon.token").exists() and not (store / "daemon.sqlite").exists()  # nothing started


def test_plain_http_beyond_loopback_when_the_cell_file_allows_it(tmp_path):
    cell_file = with_http(write_cell_file(tmp_path), {"allow_plain": True})
    with DaemonProcess(cell_file, args=("--host", "0.0.0.0")).start() as d, d.client(token=None) as c:
        assert d.url.startswith("http://127.0.0.1:")
        assert c.get("/health").json()["ok"]
    assert not (tmp_path / "store" / "tls").exists()


def test_https_serves_the_certificate_it_made_with_its_key_owner_only(tls_daemon):
    d = tls_daemon
    assert d.url.startswith("https://127.0.0.1:")  # daemon.url: a wildcard bind named by its loopback address
    cert, key = d.store / "tls" / "daemon.crt", d.store / "tls" / "daemon.key"
    assert stat.S_IMODE(key.stat().st_mode) == 0o600
    assert served_certificate(d.url) == pem_to_der(cert)
    names = tls.certificate_names(cert.read_bytes())
    assert {"127.0.0.1", "::1", "localhost", socket.gethostname()} <= set(names)
    with d.client(token=None) as c:
        assert c.get("/health").json()["ok"]
    with pytest.raises(httpx.ConnectError, match="CERTIFICATE_VERIFY_FAILED"):
        httpx.get(d.url + "/health")  # the system's CAs do not know it: only a pinned client talks to it
    with pytest.raises(httpx.HTTPError):
        httpx.get(d.url.replace("https:", "http:") + "/health", timeout=5)  # no plain HTTP on the TLS port
    logs = d.log_path.read_text()
    ready = next(e for e in d.logs() if e.get("msg") == "ready")
    assert ready["tls"]["spki_pin"] == tls.spki_pin(cert.read_bytes()) and ready["url"] == d.url
    assert d.token not in logs and "PRIVATE KEY" not in logs


def test_the_cli_works_through_the_pinned_certificate_and_fails_clearly_without(tls_daemon, capsys, monkeypatch):
    d = tls_daemon
    monkeypatch.delenv("CELLCTL_CA", raising=False)
    monkeypatch.setenv("CELLCTL_TOKEN", d.token)
    assert cli.main(["status", "--url", d.url, "--ca", str(d.ca)]) == 0
    assert d.url in capsys.readouterr().out
    assert cli.main(["status", "--url", d.url]) == 1
    err = capsys.readouterr().err
    assert "certificate is not trusted" in err and "--ca FILE or $CELLCTL_CA" in err
    assert cli.main(["status", "--url", d.url, "--ca", str(d.store / "nothing.pem")]) == 2
    assert "nothing.pem is not a file" in capsys.readouterr().err
    # $CELLCTL_CA, and a command with the token: a job run to its end
    monkeypatch.setenv("CELLCTL_CA", str(d.ca))
    assert cli.main(["run", "virtual-grid", "--url", d.url, "--seed", "5", "--wait", "--quiet"]
                    + [f"--param={k}={v}" for k, v in TINY.items()]) == 0
    assert "done" in capsys.readouterr().out
    with d.client() as c:  # Prometheus scrapes the same way: pinned, no token
        assert "cellctl_jobs" in c.get("/metrics").text


def test_the_certificate_is_kept_across_restarts(tmp_path):
    cell_file = write_cell_file(tmp_path)
    with DaemonProcess(cell_file, args=("--tls",)).start() as d:  # on loopback too, when asked
        assert d.url.startswith("https://127.0.0.1:")
        first = served_certificate(d.url)
    with DaemonProcess(cell_file, args=("--tls",)).start() as d:
        assert served_certificate(d.url) == first  # every client's pin stays good


def test_the_cell_files_certificate_and_its_key_mode(tmp_path):
    certs = tmp_path / "pki"
    tls.make_certificate(certs / "cell.crt", certs / "cell.key", ["localhost", "127.0.0.1"], "the plant's cell 3")
    cell_file = with_http(write_cell_file(tmp_path), {"cert_file": "pki/cell.crt", "key_file": "pki/cell.key"})
    with DaemonProcess(cell_file).start() as d:  # a cert_file turns TLS on, paths from the cell file's folder
        assert d.url.startswith("https://")
        assert served_certificate(d.url) == pem_to_der(certs / "cell.crt")
    assert not (tmp_path / "store" / "tls").exists()
    os.chmod(certs / "cell.key", 0o644)
    loose = r"http.key_file: .*cell.key is readable by others \(mode 0644\).*chmod 600"
    with pytest.raises(CellFileError, match=loose):
        tls.tls_for(load_cell_file(cell_file)[0], cell_file, "127.0.0.1")
    missing = with_http(write_cell_file(tmp_path), {"cert_file": "pki/none.crt", "key_file": "pki/cell.key"})
    with pytest.raises(CellFileError, match=r"http.cert_file: .*none.crt is not a file"):
        tls.tls_for(load_cell_file(missing)[0], missing, "0.0.0.0")


@pytest.mark.parametrize("http, problem", [
    ({"alow_plain": True}, "http.alow_plain: unknown key"),
    ({"cert_file": "a.pem"}, "cert_file and key_file go together"),
    ({"tls": False, "cert_file": "a.pem", "key_file": "a.key"}, "tls: false with a cert_file"),
    ({"allow_plain": "sometimes"}, "http.allow_plain"),
])
def test_the_http_section_names_what_is_wrong(http, problem):
    text = (ROOT / "config" / "sim-microcell.yaml").read_text() + "\n" + yaml.safe_dump({"http": http})
    with pytest.raises(CellFileError, match=problem.replace(".", r"\.")):
        parse_cell_file(text)


@pytest.mark.parametrize("host, loopback", [("127.0.0.1", True), ("127.0.0.5", True), ("::1", True),
                                            ("localhost", True), ("0.0.0.0", False), ("::", False),
                                            ("", False), ("192.0.2.7", False)])
def test_which_binds_stay_on_this_machine(host, loopback):
    assert tls.is_loopback(host) is loopback


def test_the_console_works_in_chromium_through_the_pinned_certificate(tls_daemon):
    if not CHROMIUM.exists():
        pytest.fail(f"{CHROMIUM} is missing: run tools/ensure-system (apt-get install chromium)")
    from playwright.sync_api import Error, sync_playwright

    d = tls_daemon
    pin = tls.spki_pin(d.ca.read_bytes())
    with sync_playwright() as p:
        unpinned = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS, headless=True)
        try:
            with pytest.raises(Error, match="ERR_CERT_AUTHORITY_INVALID"):
                unpinned.new_page().goto(d.url + "/")
        finally:
            unpinned.close()
        browser = p.chromium.launch(executable_path=str(CHROMIUM), headless=True,
                                    args=[*CHROMIUM_ARGS, f"--ignore-certificate-errors-spki-list={pin}"])
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 1000})
            page.set_default_timeout(30_000)
            errors = []
            page.on("pageerror", lambda exc: errors.append(str(exc)))
            open_console(page, d)
            assert page.url.startswith("https://")
            page.wait_for_function("document.querySelector('#conn').textContent === 'live'")  # the event stream
            page.fill("#token-input", d.token)
            page.click("#token-form button")
            page.select_option("#routine", "virtual-grid")
            for name, value in TINY.items():
                page.fill(f"#param-{name}", str(value))
            page.fill("#seed", "5")
            with d.client(token=None) as c:
                last = max((j["id"] for j in c.get("/jobs").json()["jobs"]), default=0)
                page.click("#start")
                page.wait_for_function(f"document.querySelector('#job-title').textContent.startsWith('{last + 1}:')")
                job = wait_for(c, last + 1, {"done"})  # the console's job, submitted over HTTPS
            assert job["params"] == TINY
            page.wait_for_function("document.querySelector('#job-state').textContent === 'done'")
            assert not errors, errors
        finally:
            browser.close()
