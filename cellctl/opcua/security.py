"""Who may do what on the OPC UA server: the server's certificate, the users, the trusted clients.

- The server certificate and its key are made at first start in the store (`opcua/`), the key 0600.
- Anonymous sessions browse, read and subscribe; calling a method needs a user: any user name with the
  daemon's token as password, or an X.509 user certificate of the cell file's `opcua.user_certs`.
- Sign / SignAndEncrypt channels are opened only by the client application certificates the cell file
  trusts (`opcua.trusted_clients`), compared byte for byte (pinned, like the CLI's `--ca`).
"""

from __future__ import annotations

import contextvars
import hashlib
import ipaddress
import socket
from dataclasses import dataclass
from pathlib import Path

from asyncua import ua
from asyncua.common.utils import ServiceError
from asyncua.crypto import cert_gen
from asyncua.crypto.permission_rules import USER_TYPES, PermissionRuleset, User, UserRole
from cryptography import x509
from cryptography.hazmat.primitives.serialization import Encoding
from cryptography.x509.oid import ExtendedKeyUsageOID

from ..daemon.auth import secret_matches
from ..store import write_atomic
from ..errors import InvalidRequest

CERT_FILE, KEY_FILE = "server-cert.der", "server-key.pem"


@dataclass
class CellUser(User):
    """A session's user: the name the audit records, how it proved itself, and the operator lock it holds."""

    credential: str = "anonymous"
    lock_id: str | None = None


# The user of the request being served: the permission check runs in the same task just before the method.
CURRENT_USER: contextvars.ContextVar[CellUser | None] = contextvars.ContextVar("opcua_user", default=None)

_CALL = ua.NodeId(ua.ObjectIds.CallRequest_Encoding_DefaultBinary)
_WRITE = ua.NodeId(ua.ObjectIds.WriteRequest_Encoding_DefaultBinary)
_READ_ONLY = {ua.NodeId(t) for t in USER_TYPES} - {_CALL, _WRITE}


class SessionRules(PermissionRuleset):
    """Anonymous: browse, read, subscribe. A user: that and method calls. Nobody writes (no variable is an input)."""

    def check_validity(self, user, action_type_id, body) -> bool:
        CURRENT_USER.set(user if isinstance(user, CellUser) else None)
        if action_type_id == _CALL:
            return isinstance(user, CellUser) and user.role is UserRole.User
        return action_type_id in _READ_ONLY


class CellUsers:
    """The user manager: the daemon's token as password (any name), or a configured user certificate."""

    def __init__(self, token: str, user_certs: dict[str, bytes]):
        self._token = token
        self._certs = {hashlib.sha256(der).digest(): name for name, der in user_certs.items()}

    def get_user(self, iserver, username=None, password=None, certificate=None) -> CellUser | None:
        """None refuses the session (BadUserAccessDenied). asyncua passes the secure channel's client certificate
        as `certificate` for every token but a user name: a certificate not listed leaves the session anonymous."""
        if username is not None:
            if password is None or not secret_matches(str(password), self._token):
                return None
            return CellUser(role=UserRole.User, name=username or "opcua", credential="token")
        if certificate:
            der = certificate if isinstance(certificate, bytes) else certificate.public_bytes(Encoding.DER)
            name = self._certs.get(hashlib.sha256(der).digest())
            if name:
                return CellUser(role=UserRole.User, name=name, credential="x509 certificate")
        return CellUser(role=UserRole.Anonymous, name=None)


class TrustedClients:
    """The certificate validator of CreateSession: the client's application certificate must be one of these."""

    def __init__(self, certificates: list[bytes]):
        self._pinned = {hashlib.sha256(der).digest() for der in certificates}

    async def __call__(self, cert: x509.Certificate, app_description) -> None:
        if hashlib.sha256(cert.public_bytes(Encoding.DER)).digest() not in self._pinned:
            raise ServiceError(ua.StatusCodes.BadCertificateUntrusted)


def read_certificate(path: str | Path, what: str) -> bytes:
    """A certificate file (DER or PEM) as DER; a clear error naming the cell file's key when it is not one."""
    try:
        data = Path(path).expanduser().read_bytes()
    except OSError as exc:
        raise InvalidRequest(f"{what}: cannot read {path}: {exc.strerror}") from None
    try:
        cert = x509.load_pem_x509_certificate(data) if b"-----BEGIN" in data else x509.load_der_x509_certificate(data)
    except ValueError:
        raise InvalidRequest(f"{what}: {path} is not an X.509 certificate (PEM or DER)") from None
    return cert.public_bytes(Encoding.DER)


def server_certificate(folder: Path, app_uri: str, host: str) -> tuple[Path, Path]:
    """(certificate, key) of the server, made at first start: RSA 2048, SHA-256, ten years, naming the
    application URI and the host it serves (its name, and its address when it is one)."""
    cert_path, key_path = folder / CERT_FILE, folder / KEY_FILE
    if cert_path.is_file() and key_path.is_file():
        return cert_path, key_path
    folder.mkdir(parents=True, exist_ok=True)
    key = cert_gen.generate_private_key()
    names: list[x509.GeneralName] = [x509.UniformResourceIdentifier(app_uri), x509.DNSName(socket.gethostname()),
                                     x509.DNSName("localhost")]
    try:
        names.append(x509.IPAddress(ipaddress.ip_address(host)))
    except ValueError:
        names.append(x509.DNSName(host))
    cert = cert_gen.generate_self_signed_app_certificate(
        key, "cellctl", {}, names, [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH], days=3650)
    write_atomic(key_path, cert_gen.dump_private_key_as_pem(key), 0o600)  # the key before its certificate
    write_atomic(cert_path, cert.public_bytes(Encoding.DER), 0o644)
    return cert_path, key_path
