"""Which OPC UA client certificates the cell trusts: the store's trusted/ and rejected/ folders (stores/client_certificates.py), the
server's checks per channel (security.py: None ignores the certificate, a secure channel needs a trusted one),
and the trust verb over HTTP and the CLI, with its refusals; asyncua as the client."""

from __future__ import annotations

import contextvars
import json
import os
import subprocess
import sys

import pytest
from asyncua import ua
from asyncua.crypto.security_policies import SecurityPolicyFactory, SecurityPolicyNone
from cryptography import x509
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.hazmat.primitives.serialization import Encoding

from cellctl.errors import InvalidRequest, NotFound
from cellctl.opcua.security import CHANNEL, Channel, ChannelPolicy, SessionRules
from cellctl.stores import client_certificates as trust
from cellctl.stores.client_certificates import ClientCertificates, thumbprint

from tests.support.opcua import D, S, Session, run


def certificate(name: str) -> bytes:
    """A small self-signed certificate (EC: quick to make) naming an application URI, as DER."""
    from datetime import datetime, timedelta, timezone

    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(x509.oid.NameOID.COMMON_NAME, name)])
    now = datetime.now(timezone.utc)
    cert = (x509.CertificateBuilder().subject_name(subject).issuer_name(subject).public_key(key.public_key())
            .serial_number(x509.random_serial_number()).not_valid_before(now).not_valid_after(now + timedelta(days=9))
            .add_extension(x509.SubjectAlternativeName([x509.UniformResourceIdentifier(f"urn:test:{name}")]), False)
            .sign(key, hashes.SHA256()))
    return cert.public_bytes(Encoding.DER)


# -- the folders -----------------------------------------------------------------------------------------------


def test_a_rejected_certificate_is_kept_once_then_moved_to_trusted(tmp_path):
    store = ClientCertificates(tmp_path / "opcua")
    der = certificate("mes")
    assert not store.is_trusted(der)
    assert store.reject(der) is True
    kept = tmp_path / "opcua" / "rejected" / f"{thumbprint(der)}.der"
    assert kept.read_bytes() == der
    first = kept.stat().st_mtime_ns
    assert store.reject(der) is False and kept.stat().st_mtime_ns == first  # a retry writes nothing
    listed = store.listing()
    assert listed["trusted"] == [] and [c["thumbprint"] for c in listed["rejected"]] == [thumbprint(der)]
    assert listed["rejected"][0]["application_uri"] == "urn:test:mes" and listed["rejected"][0]["rejected_at"]

    got = store.trust(store.find(thumbprint(der)[:8].upper()))  # a prefix, in any case
    assert got["already"] is False and got["certificate"]["source"] == "store"
    assert store.is_trusted(der) and not kept.exists()
    assert (tmp_path / "opcua" / "trusted" / f"{thumbprint(der)}.der").read_bytes() == der
    assert store.trust(der)["already"] is True  # again: nothing changes
    assert [p.name for p in (tmp_path / "opcua").rglob("*") if p.name.startswith(".")] == []  # no temporary left


def test_the_trusted_set_is_the_cell_files_and_the_trusted_folder(tmp_path):
    pinned, copied, other = certificate("pinned"), certificate("copied"), certificate("other")
    folder = tmp_path / "opcua" / "trusted"
    folder.mkdir(parents=True)
    # copied by hand as PEM under any name, as with other OPC UA servers; a stray file is listed, never trusted
    (folder / "line 4 MES.pem").write_bytes(x509.load_der_x509_certificate(copied).public_bytes(Encoding.PEM))
    (folder / "notes.crt").write_text("not a certificate")
    store = ClientCertificates(tmp_path / "opcua", {"pki/pinned.der": pinned})
    assert store.is_trusted(pinned) and store.is_trusted(copied) and not store.is_trusted(other)
    listed = {c.get("thumbprint", c["file"]): c for c in store.listing()["trusted"]}
    assert (listed[thumbprint(pinned)]["source"], listed[thumbprint(pinned)]["file"]) == ("cell file", "pki/pinned.der")
    assert listed[thumbprint(copied)]["subject"] == "CN=copied"
    assert "not an X.509 certificate" in listed[str(folder / "notes.crt")]["problem"]
    assert store.trust(pinned) == {"certificate": listed[thumbprint(pinned)], "already": True}
    assert not (folder / f"{thumbprint(pinned)}.der").exists()  # already trusted: no copy made


def test_a_thumbprint_names_one_certificate_or_says_why_not(tmp_path, monkeypatch):
    store = ClientCertificates(tmp_path / "opcua")
    ders = []
    while len({thumbprint(d)[0] for d in ders}) == len(ders):  # until two share their first digit (≤ 17 certs)
        ders.append(certificate(f"c{len(ders)}"))
        store.reject(ders[-1])
    first = thumbprint(ders[0])
    with pytest.raises(InvalidRequest, match="'xyz-1' is not hexadecimal"):
        store.find("xyz-1")
    with pytest.raises(InvalidRequest, match="too short; give at least 8 hex digits"):
        store.find(first[:5])
    with pytest.raises(NotFound, match="no certificate 00000000 among the rejected or trusted ones"):
        store.find("0000:0000")
    assert store.find(":".join(first[i:i + 2] for i in range(0, 40, 2))) == ders[0]  # as UaExpert shows it
    monkeypatch.setattr(trust, "MIN_PREFIX", 1)
    shared = thumbprint(ders[-1])[0]
    with pytest.raises(InvalidRequest, match=f"'{shared}' is ambiguous; it starts 2 certificates: "):
        store.find(shared)


def test_no_more_than_max_rejected_are_kept(tmp_path, monkeypatch):
    monkeypatch.setattr(trust, "MAX_REJECTED", 3)
    store = ClientCertificates(tmp_path / "opcua")
    ders = [certificate(f"c{i}") for i in range(5)]
    for i, der in enumerate(ders):
        store.reject(der)
        path = tmp_path / "opcua" / "rejected" / f"{thumbprint(der)}.der"
        os.utime(path, ns=(i * 10**9, i * 10**9))  # their order, whatever the file system's clock resolution
    assert sorted(c["thumbprint"] for c in store.listing()["rejected"]) == sorted(thumbprint(d) for d in ders[2:])


# -- the channel's checks ------------------------------------------------------------------------------------------


def test_a_none_channel_keeps_no_client_certificate_and_a_secure_one_needs_trust(tmp_path):
    der = certificate("anyone")

    def open_channel(policy, mode):
        wrapped = ChannelPolicy(SecurityPolicyFactory(policy, mode))
        return wrapped.create(der).peer_certificate, CHANNEL.get()

    # asyncua keeps one sent under None, where it would pass for an X.509 user with no proof of its key
    assert SecurityPolicyFactory(SecurityPolicyNone, ua.MessageSecurityMode.None_).create(der).peer_certificate == der
    peer, channel = contextvars.copy_context().run(open_channel, SecurityPolicyNone, ua.MessageSecurityMode.None_)
    assert not peer and channel == Channel(secure=False)
    read = ua.NodeId(ua.ObjectIds.ReadRequest_Encoding_DefaultBinary)
    certificates = ClientCertificates(tmp_path / "opcua")
    rules = SessionRules(certificates)

    def allowed(channel):
        CHANNEL.set(channel)
        return rules.check_validity(None, read, b""), CHANNEL.get()

    assert contextvars.copy_context().run(allowed, Channel(secure=False))[0]
    assert not contextvars.copy_context().run(allowed, None)[0]  # not known: refused
    # a secure channel whose certificate CreateSession never validated (left out, or a session re-activated
    # on a new channel): only when it is trusted, and then once for the connection
    assert not contextvars.copy_context().run(allowed, Channel(secure=True, certificate=der))[0]
    assert not contextvars.copy_context().run(allowed, Channel(secure=True))[0]
    certificates.trust(der)
    assert contextvars.copy_context().run(allowed, Channel(secure=True, certificate=der)) == (
        True, Channel(secure=True, certificate=der, trusted=True))


# -- the server and the verb -------------------------------------------------------------------------------------


def locate_args():
    return ua.Variant("cam1", S), ua.Variant(1224.0, D), ua.Variant(1025.0, D)


def kept(cell, der_path) -> list:
    folder = cell.daemon.store / "opcua" / "rejected"
    t = thumbprint(der_path.read_bytes())
    return [p.name for p in folder.iterdir() if t in p.name] if folder.is_dir() else []


def test_under_none_an_untrusted_application_certificate_is_ignored_and_gives_no_rights(opcua_cell, new_identity):
    newcomer = new_identity("none-newcomer")

    async def go():
        # asyncua sends the certificate in CreateSession (and as an X.509 user nobody listed)
        async with Session(opcua_cell, user_cert=newcomer) as s:
            assert await s.read("Identification/Name") == "sim-microcell"
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                await s.call("Locate", *locate_args())
    run(go())
    assert kept(opcua_cell, newcomer.der) == []


def test_an_untrusted_certificate_is_refused_kept_once_and_trusted_over_http_without_a_restart(opcua_cell,
                                                                                                    new_identity):
    newcomer = new_identity("secure-newcomer")
    t = thumbprint(newcomer.der.read_bytes())
    secure = (newcomer, ua.MessageSecurityMode.SignAndEncrypt)

    async def refused():
        with pytest.raises(ua.uaerrors.BadCertificateUntrusted):
            async with Session(opcua_cell, secure=secure):
                pass

    run(refused())
    assert kept(opcua_cell, newcomer.der) == [f"{t}.der"]
    run(refused())
    assert kept(opcua_cell, newcomer.der) == [f"{t}.der"]
    with opcua_cell.daemon.client() as http:
        listed = http.get("/opcua/certificates").json()
        assert t in [c["thumbprint"] for c in listed["rejected"]]
        mes = thumbprint(opcua_cell.client.der.read_bytes())
        assert [c["source"] for c in listed["trusted"] if c["thumbprint"] == mes] == ["cell file"]
        got = http.post("/opcua/certificates/trust", json={"thumbprint": t[:12]})
        assert got.status_code == 200, got.text
        assert got.json()["certificate"]["thumbprint"] == t and got.json()["already"] is False

    async def trusted():
        async with Session(opcua_cell, "mes", opcua_cell.daemon.token, secure=secure) as s:
            await s.call("Locate", *locate_args())
    run(trusted())
    assert kept(opcua_cell, newcomer.der) == []
    with opcua_cell.daemon.client() as http:
        audit = [a for a in http.get("/audit").json()["audit"] if a["target"] == f"opc ua certificate {t}"]
    assert [(a["action"], a["outcome"]) for a in audit] == [("POST /opcua/certificates/trust", "ok")]


def test_trust_refusals_name_what_was_wrong(opcua_cell):
    cases = [({}, 422, "give a certificate's thumbprint or the certificate itself"),
             ({"thumbprint": "zz-top"}, 422, "'zz-top' is not hexadecimal"),
             ({"thumbprint": "abc"}, 422, "too short"),
             ({"thumbprint": "0" * 40}, 404, "no certificate 0000000000000000000000000000000000000000"),
             ({"certificate_pem": "-----BEGIN CERTIFICATE-----\nAAAA\n-----END CERTIFICATE-----\n"}, 422,
              "certificate is not an X.509 certificate"),
             ({"thumbprint": "0" * 40, "certificate_pem": "x"}, 422, "one of the two")]
    with opcua_cell.daemon.client() as http:
        for body, status, message in cases:
            got = http.post("/opcua/certificates/trust", json=body)
            assert got.status_code == status and message in got.json()["detail"], (body, got.text)
        assert opcua_cell.daemon.client(token=None).post("/opcua/certificates/trust", json={}).status_code == 401
        audit = [a for a in http.get("/audit").json()["audit"] if a["action"] == "POST /opcua/certificates/trust"]
    assert sum(a["outcome"].startswith("refused") for a in audit) >= len(cases)


def cellctl(*args: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith("CELLCTL_")}
    return subprocess.run([sys.executable, "-m", "cellctl.cli", *args], capture_output=True, text=True, timeout=60,
                          env=env)


def test_the_cli_trusts_a_certificate_file_through_the_daemon_and_refuses_what_is_none(opcua_cell, new_identity):
    newcomer = new_identity("cli-newcomer")
    t = thumbprint(newcomer.der.read_bytes())
    where = ("--url", opcua_cell.daemon.url, "--token", opcua_cell.daemon.token)
    done = cellctl("opcua", "trust", str(newcomer.der), *where)  # DER on this side, PEM on the wire
    assert done.returncode == 0 and f"trusted OPC UA client certificate {t[:12]}" in done.stdout, done.stderr
    again = cellctl("opcua", "trust", str(newcomer.pem), *where)
    assert again.returncode == 0 and "was already trusted" in again.stdout
    listed = json.loads(cellctl("opcua", "certificates", "--json", *where).stdout)
    assert t in [c["thumbprint"] for c in listed["trusted"]]
    text = cellctl("opcua", "certificates", "--config", str(opcua_cell.daemon.cell_file))  # the files, beside it
    assert text.returncode == 0 and t[:12] in text.stdout and "urn:cellctl-test:cli-newcomer" in text.stdout

    key = cellctl("opcua", "trust", str(newcomer.key), *where)
    assert key.returncode == 2
    assert key.stderr.strip() == f"cellctl: error: {newcomer.key} is not an X.509 certificate (PEM or DER)"
    missing = cellctl("opcua", "trust", "no-such-file.der", *where)
    assert missing.returncode == 2 and "no such file, and not a thumbprint" in missing.stderr
    unknown = cellctl("opcua", "trust", "0123456789", *where)
    assert unknown.returncode == 2 and "no certificate 0123456789" in unknown.stderr
    for out in (key, missing, unknown):
        assert "Traceback" not in out.stderr and len(out.stderr.strip().splitlines()) == 1

    async def trusted():
        async with Session(opcua_cell, secure=(newcomer, ua.MessageSecurityMode.Sign)) as s:
            assert await s.read("Identification/Name") == "sim-microcell"
    run(trusted())


def test_with_no_daemon_the_cli_trusts_on_the_store_and_audits_there(tmp_path):
    from cellctl.startup.daemon import DB_FILE
    from cellctl.stores.jobs import JobStore

    from tests.support.daemon import write_cell_file

    cell_file = write_cell_file(tmp_path)
    der = tmp_path / "mes.der"
    der.write_bytes(certificate("mes"))
    done = cellctl("opcua", "trust", str(der), "--config", str(cell_file))
    assert done.returncode == 0, done.stderr
    store = tmp_path / "store"
    assert (store / "opcua" / "trusted" / f"{thumbprint(der.read_bytes())}.der").is_file()
    jobs = JobStore(store / DB_FILE)
    try:
        audit = jobs.audit_log()
    finally:
        jobs.close()
    assert [(a["who"], a["action"], a["target"], a["outcome"]) for a in audit] == [
        ("local", "cli opcua trust", f"opc ua certificate {thumbprint(der.read_bytes())}", "ok")]


def test_a_secure_only_server_activates_no_session_on_a_channel_asking_for_none(tmp_path):
    """asyncua keeps its initial None policy for a client asking for None where no endpoint offers it, and that
    policy checks no permissions: such a session must not be activated (it could browse and read)."""
    from asyncua import Client

    from cellctl.opcua.security import CellServer, CellUsers, TrustedClients, server_certificate

    from tests.support.ports import free_port

    async def go():
        clients = ClientCertificates(tmp_path / "opcua")
        cert, key = server_certificate(tmp_path / "opcua", "urn:cellctl:secure-only", "127.0.0.1")
        server = CellServer(user_manager=CellUsers("token", {}))
        await server.init()
        url = f"opc.tcp://127.0.0.1:{free_port()}/cellctl"
        server.set_endpoint(url)
        await server.load_certificate(str(cert))
        await server.load_private_key(str(key))
        server.set_security_policy([ua.SecurityPolicyType.Basic256Sha256_Sign,
                                    ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt],
                                   permission_ruleset=SessionRules(clients))
        server.set_identity_tokens([ua.AnonymousIdentityToken, ua.UserNameIdentityToken])
        server.set_certificate_validator(TrustedClients(clients))
        await server.start()
        client = Client(url)
        try:
            # the steps of connect(), without the client's own check that the server offers None
            await client.connect_socket()
            await client.send_hello()
            await client.open_secure_channel()
            with pytest.raises(ua.UaError, match="No matching endpoints"):
                await client.create_session()  # the server made the session; the client alone objects
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                await client.activate_session()
            with pytest.raises(ua.uaerrors.BadSessionNotActivated):
                await client.nodes.server.read_browse_name()
        finally:
            client.disconnect_socket()
            await server.stop()

    run(go())
