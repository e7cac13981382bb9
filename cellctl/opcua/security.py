"""Who may do what on the OPC UA server: the server's certificate, the users, the trusted clients.

- The server certificate and its key are made at first start in the store (`opcua/`), the key 0600.
- Anonymous sessions browse, read and subscribe; calling a method needs a user: any user name with the
  daemon's token as password, or an X.509 user certificate of the cell file's `opcua.user_certs`.
- Sessions on Sign / SignAndEncrypt channels are opened only by trusted client application certificates
  (cellctl/stores/client_certificates.py: the cell file's `opcua.trusted_clients` and the store's `opcua/trusted/`), compared byte for byte
  (pinned, like the CLI's `--ca`); an untrusted one is refused (BadCertificateUntrusted) and kept in
  `opcua/rejected/`. Under None the client's certificate is ignored (OPC UA Part 4, CreateSession): it proves
  nothing there, and node-opcua or UaExpert send one anyway.
"""

from __future__ import annotations

import contextvars
import hashlib
import ipaddress
import socket
from dataclasses import dataclass, replace
from pathlib import Path

from asyncua import Server, ua
from asyncua.common.utils import ServiceError
from asyncua.crypto import cert_gen
from asyncua.crypto.permission_rules import USER_TYPES, PermissionRuleset, User, UserRole
from cryptography import x509
from cryptography.hazmat.primitives.serialization import Encoding
from cryptography.x509.oid import ExtendedKeyUsageOID

from cellctl.service.auth import secret_matches
from cellctl.stores.client_certificates import ClientCertificates
from cellctl.stores.run_folder import write_atomic

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


@dataclass(frozen=True)
class Channel:
    """The secure channel of a connection: its security, the certificate its client proved it holds, and
    whether that certificate was found trusted when the session was created."""

    secure: bool
    certificate: bytes | None = None
    trusted: bool = False


# The channel of the connection being served. asyncua serves a connection in one task, from OpenSecureChannel
# (where ChannelPolicy sets it) through CreateSession and every request after: each sees its own channel.
# Unset means not known: treated as secure and untrusted (fail closed), and no session is activated on it.
CHANNEL: contextvars.ContextVar[Channel | None] = contextvars.ContextVar("opcua_channel", default=None)


class ChannelPolicy:
    """An endpoint's security policy factory, wrapped: it records the channel each connection opens, and a None
    channel keeps no client certificate (one sent there would otherwise pass for an X.509 user unproven)."""

    def __init__(self, factory):
        self._factory = factory
        self.secure = factory.mode != ua.MessageSecurityMode.None_

    def matches(self, uri, mode=None) -> bool:
        return self._factory.matches(uri, mode)

    def create(self, peer_certificate):
        policy = self._factory.create(peer_certificate if self.secure else None)
        CHANNEL.set(Channel(self.secure, policy.peer_certificate if self.secure else None))
        return policy

    def __getattr__(self, name):  # mode, cls, ...: the factory's
        return getattr(self._factory, name)


class CellServer(Server):
    """asyncua's server with each endpoint's policy factory wrapped in a ChannelPolicy, before it listens."""

    async def _setup_server_nodes(self) -> None:
        await super()._setup_server_nodes()
        self._policies[:] = [ChannelPolicy(p) for p in self._policies]


class SessionRules(PermissionRuleset):
    """Anonymous: browse, read, subscribe. A user: that and method calls. Nobody writes (no variable is an input).
    On a secure channel nothing at all unless its certificate is trusted: CreateSession checked it, but asyncua
    checks nothing when the client leaves it out there, nor for a session re-activated on a new channel."""

    def __init__(self, certificates: ClientCertificates):
        super().__init__()
        self.certificates = certificates

    def check_validity(self, user, action_type_id, body) -> bool:
        CURRENT_USER.set(user if isinstance(user, CellUser) else None)
        if not self._admits(CHANNEL.get()):
            return False
        if action_type_id == _CALL:
            return isinstance(user, CellUser) and user.role is UserRole.User
        return action_type_id in _READ_ONLY

    def _admits(self, channel: Channel | None) -> bool:
        if channel is None:
            return False
        if channel.secure and not channel.trusted:
            if not (channel.certificate and self.certificates.is_trusted(channel.certificate)):
                return False
            CHANNEL.set(replace(channel, trusted=True))  # this connection's later requests need not look again
        return True


class CellUsers:
    """The user manager: the daemon's token as password (any name), or a configured user certificate."""

    def __init__(self, token: str, user_certs: dict[str, bytes]):
        self._token = token
        self._certs = {hashlib.sha256(der).digest(): name for name, der in user_certs.items()}

    def get_user(self, iserver, username=None, password=None, certificate=None) -> CellUser | None:
        """None refuses the session (BadUserAccessDenied). asyncua passes the secure channel's client certificate
        as `certificate` for every token but a user name: a certificate not listed leaves the session anonymous.

        A channel no endpoint's policy opened is refused: asyncua lets a client ask for None on a server that
        offers no None endpoint (it keeps its initial None policy, which checks no permissions at all)."""
        if CHANNEL.get() is None:
            return None
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
    """The certificate validator of CreateSession. Under None it ignores the certificate (Part 4, CreateSession).
    On a secure channel the session's certificate must be the channel's, and trusted; an untrusted one is refused
    and kept in rejected/ (once: a retry finds it there)."""

    def __init__(self, certificates: ClientCertificates):
        self.certificates = certificates

    async def __call__(self, cert: x509.Certificate, app_description) -> None:
        channel = CHANNEL.get() or Channel(secure=True)
        if not channel.secure:
            return
        der = cert.public_bytes(Encoding.DER)
        if der != channel.certificate:
            raise ServiceError(ua.StatusCodes.BadCertificateInvalid)
        # on the event loop, not in a thread: the files are small, and one writer keeps one copy
        if not self.certificates.is_trusted(der):
            self.certificates.reject(der)
            raise ServiceError(ua.StatusCodes.BadCertificateUntrusted)
        CHANNEL.set(replace(channel, trusted=True))


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
