"""The real daemon with its OPC UA server on, and the certificates its clients present.

One daemon per module: on a store copied from the session's calibrated cell (so Locate and
Calibrations/* have something to show), the simulated clock spent partly as wall time.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

from tests.support.daemon import DaemonProcess, write_cell_file
from tests.support.ports import free_port


@dataclass(frozen=True)
class Identity:
    """A client's certificate (PEM and DER files) and key, with the application URI it names."""

    uri: str
    pem: Path
    der: Path
    key: Path


def make_identity(folder: Path, name: str) -> Identity:
    from asyncua.crypto import cert_gen
    from cryptography import x509
    from cryptography.hazmat.primitives.serialization import Encoding
    from cryptography.x509.oid import ExtendedKeyUsageOID

    uri = f"urn:cellctl-test:{name}"
    key = cert_gen.generate_private_key()
    cert = cert_gen.generate_self_signed_app_certificate(
        key, name, {}, [x509.UniformResourceIdentifier(uri), x509.DNSName("localhost")],
        [ExtendedKeyUsageOID.CLIENT_AUTH], days=30)
    out = Identity(uri, folder / f"{name}.pem", folder / f"{name}.der", folder / f"{name}-key.pem")
    out.pem.write_bytes(cert.public_bytes(Encoding.PEM))
    out.der.write_bytes(cert.public_bytes(Encoding.DER))
    out.key.write_bytes(cert_gen.dump_private_key_as_pem(key))
    return out


@pytest.fixture
def new_identity(opcua_cell):
    """Makes a client identity that nothing trusts yet, in the cell's folder."""
    return lambda name: make_identity(opcua_cell.folder, name)




@dataclass
class OpcuaCell:
    daemon: DaemonProcess
    url: str
    client: Identity  # a trusted application certificate
    stranger: Identity  # one the cell file does not list
    operator: Identity  # a user certificate the cell file lists as "operator-anna"
    folder: Path

    @property
    def server_cert(self) -> Path:
        return self.daemon.store / "opcua" / "server-cert.der"


@pytest.fixture(scope="module")
def opcua_cell(tmp_path_factory, calibrated_cell):
    folder = tmp_path_factory.mktemp("opcua")
    client, stranger, operator = (make_identity(folder, n) for n in ("mes", "stranger", "anna"))
    path = write_cell_file(folder, realtime_factor=0.02)
    data = yaml.safe_load(path.read_text())
    port = free_port()
    data["opcua"] = {"enabled": True, "port": port, "trusted_clients": [str(client.pem)],
                     "user_certs": {"operator-anna": str(operator.der)}}
    path.write_text(yaml.safe_dump(data))
    calibrated_cell.store_copy(Path(data["store_dir"])).close()
    with DaemonProcess(path).start() as daemon:
        yield OpcuaCell(daemon, f"opc.tcp://127.0.0.1:{port}/cellctl", client, stranger, operator, folder)
