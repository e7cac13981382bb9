"""HTTPS for the daemon: which binds need it, the certificate it serves, the pin its clients keep.

The HTTP API carries the bearer token, so in clear on a plant network it gives the cell away. Bound to
anything but loopback, the daemon serves HTTPS, or refuses to start (unless the cell file says
`http: {allow_plain: true}`). On loopback it stays plain HTTP unless TLS is asked for (`http: {tls: true}`,
a `cert_file`, or `cellctl serve --tls`).

The certificate is the cell file's (`cert_file`, `key_file`), or one made at first start in the store:
`<store>/tls/daemon.crt` and `daemon.key` (mode 0600), self-signed, its subject alternative names the
host names and addresses the daemon answers on (plus `http.names`). It is kept across restarts, so a
client's pin stays good: `cellctl --ca daemon.crt` (or $CELLCTL_CA), Chromium by its SPKI hash
(`spki_pin`), Prometheus by `tls_config: {ca_file: ...}`.
"""

from __future__ import annotations

import base64
import datetime
import hashlib
import ipaddress
import logging
import os
import socket
import stat
from dataclasses import dataclass
from pathlib import Path

from cellctl.config import CellFile, CellFileError
from cellctl.stores.run_folder import write_atomic

__all__ = ["PlainHttpRefused", "TlsFiles", "is_loopback", "make_certificate", "served_names", "spki_pin",
           "tls_for", "url_of"]

TLS_DIR, CERT_FILE, KEY_FILE = "tls", "daemon.crt", "daemon.key"
VALID_DAYS = 3650  # a pinned certificate: renewing it means re-pinning every client, so not every year
WILDCARDS = ("", "0.0.0.0", "::")
log = logging.getLogger("cellctl.startup")


class PlainHttpRefused(CellFileError):
    """A plain-HTTP bind beyond loopback that the cell file does not allow."""


@dataclass(frozen=True)
class TlsFiles:
    cert: Path
    key: Path
    made: bool  # made by the daemon (in its store), not the cell file's

    def uvicorn_options(self) -> dict:
        return {"ssl_certfile": str(self.cert), "ssl_keyfile": str(self.key)}

    def describe(self) -> dict:
        """For the start-up log: where the certificate is and how to recognise it (nothing secret)."""
        pem = self.cert.read_bytes()
        return {"cert": str(self.cert), "sha256": fingerprint(pem), "spki_pin": spki_pin(pem), "made": self.made}


def is_loopback(host: str) -> bool:
    """Does a bind to `host` stay on this machine? (a name counts when everything it resolves to is loopback)"""
    if host in WILDCARDS:
        return False
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        pass
    try:
        addresses = {info[4][0] for info in socket.getaddrinfo(host, None)}
    except OSError:
        return False
    return bool(addresses) and all(ipaddress.ip_address(a.split("%")[0]).is_loopback for a in addresses)


def tls_for(config: CellFile, cell_file: Path, host: str, force: bool = False) -> TlsFiles | None:
    """The certificate and key to serve on `host`, or None for plain HTTP; PlainHttpRefused (before anything
    starts) for plain HTTP beyond loopback without `http: {allow_plain: true}`."""
    http = config.http
    if not (force or http.wants_tls):
        if is_loopback(host) or http.allow_plain:
            return None
        raise PlainHttpRefused(
            f"{cell_file}: refusing plain HTTP on {host or '*'}: beyond this machine the bearer token would cross "
            "the network in clear. Serve HTTPS: `cellctl serve --tls`, or in the cell file `http: {tls: true}` "
            "(a certificate made at first start) or `http: {cert_file: ..., key_file: ...}`; or accept plain "
            "HTTP on the network with `http: {allow_plain: true}`; or bind to 127.0.0.1")
    if http.cert_file is not None:
        base = cell_file.parent
        cert, key = (base / Path(http.cert_file).expanduser(), base / Path(http.key_file).expanduser())
        for name, path in (("cert_file", cert), ("key_file", key)):
            if not path.is_file():
                raise CellFileError(f"{cell_file}: http.{name}: {path} is not a file")
        mode = stat.S_IMODE(key.stat().st_mode)
        if mode & 0o077:
            raise CellFileError(f"{cell_file}: http.key_file: {key} is readable by others (mode {mode:04o}); "
                                f"the key must be the owner's only: chmod 600 {key}")
        return TlsFiles(cert, key, made=False)
    folder = config.store_path() / TLS_DIR
    cert, key = folder / CERT_FILE, folder / KEY_FILE
    names = served_names(host, http.names)
    if cert.is_file() and key.is_file():
        if stat.S_IMODE(key.stat().st_mode) & 0o077:
            os.chmod(key, 0o600)  # someone loosened it: it is a secret, tighten it again (as the token)
        missing = sorted(set(names) - set(certificate_names(cert.read_bytes())))
        if missing:  # kept all the same: a new one would break every client's pin
            log.warning("the daemon's certificate does not name every address it now serves; clients that "
                        "reach it by these are refused", extra={"cert": str(cert), "missing": missing,
                                                                "fix": "delete the certificate and key to make "
                                                                       "a new one, then pin it again"})
        return TlsFiles(cert, key, made=True)
    make_certificate(cert, key, names, common_name=f"cellctl {config.cell.name}")
    log.info("made the daemon's TLS certificate", extra={"cert": str(cert), "names": names})
    return TlsFiles(cert, key, made=True)


def served_names(host: str, extra: list[str] | tuple[str, ...] = ()) -> list[str]:
    """The names and addresses a client may use for a daemon bound to `host`: loopback, this machine's name and
    addresses (all of them for a wildcard bind), the bind address itself, and `extra`."""
    names = ["localhost", "127.0.0.1", "::1"]
    hostname, fqdn = socket.gethostname(), socket.getfqdn()
    names += [hostname, fqdn]
    if host in WILDCARDS:
        for name in {hostname, fqdn}:
            try:
                names += [info[4][0].split("%")[0] for info in socket.getaddrinfo(name, None)]
            except OSError:
                pass  # a host name that does not resolve: the loopback names and `extra` remain
    else:
        names.append(host.strip("[]"))
    names += list(extra)
    return list(dict.fromkeys(n for n in names if n))


def _san(name: str):
    from cryptography import x509

    try:
        return x509.IPAddress(ipaddress.ip_address(name))
    except ValueError:
        return x509.DNSName(name)


def make_certificate(cert_path: Path, key_path: Path, names: list[str], common_name: str = "cellctl") -> None:
    """A self-signed certificate (EC P-256) naming `names`, and its key written owner-only (0600) before the
    certificate: a certificate on disk always has its key beside it."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name[:64])])
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (x509.CertificateBuilder().subject_name(subject).issuer_name(subject).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(days=1))  # a client whose clock lags a little
            .not_valid_after(now + datetime.timedelta(days=VALID_DAYS))
            .add_extension(x509.SubjectAlternativeName([_san(n) for n in names]), critical=False)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH]), critical=False)
            .sign(key, hashes.SHA256()))
    key_pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                serialization.NoEncryption())
    cert_path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(key_path, key_pem, 0o600)
    write_atomic(cert_path, cert.public_bytes(serialization.Encoding.PEM), 0o644)


def _certificate(pem: bytes):
    from cryptography import x509

    return x509.load_pem_x509_certificate(pem)


def certificate_names(pem: bytes) -> list[str]:
    from cryptography import x509

    try:
        sans = _certificate(pem).extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    except x509.ExtensionNotFound:
        return []
    return [str(v) for v in sans.get_values_for_type(x509.DNSName) + sans.get_values_for_type(x509.IPAddress)]


def fingerprint(pem: bytes) -> str:
    """SHA-256 of the certificate (DER), as browsers and `openssl x509 -fingerprint -sha256` show it."""
    from cryptography.hazmat.primitives import hashes

    return _certificate(pem).fingerprint(hashes.SHA256()).hex(":").upper()


def spki_pin(pem: bytes) -> str:
    """Base64 SHA-256 of the certificate's SubjectPublicKeyInfo: Chromium's
    `--ignore-certificate-errors-spki-list` (and HPKP's pin-sha256)."""
    from cryptography.hazmat.primitives import serialization

    spki = _certificate(pem).public_key().public_bytes(serialization.Encoding.DER,
                                                       serialization.PublicFormat.SubjectPublicKeyInfo)
    return base64.b64encode(hashlib.sha256(spki).digest()).decode()


def url_of(scheme: str, bound: tuple) -> str:
    """The URL a client on this machine uses for a socket bound at `bound` (a wildcard bind: via loopback, which
    the certificate names)."""
    host, port = bound[0], bound[1]
    if host in WILDCARDS:
        host = "::1" if host == "::" else "127.0.0.1"
    return f"{scheme}://[{host}]:{port}" if ":" in host else f"{scheme}://{host}:{port}"
