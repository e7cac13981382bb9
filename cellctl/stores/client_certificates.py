"""The OPC UA client certificates of a cell: those it trusts and those it turned away, in the store's `opcua/`.

- Trusted on Sign / SignAndEncrypt channels: the cell file's `opcua.trusted_clients` and every certificate file
  (DER or PEM) in `<store>/opcua/trusted/`. The folder is read at each new secure session, so a certificate put
  there (by `cellctl opcua trust`, or copied by hand) counts from the next session on, without a restart.
- `<store>/opcua/rejected/`: the certificate of each secure channel refused as untrusted, kept once (a retry
  finds it there) so an engineer can see who knocked and trust it. Oldest first out beyond MAX_REJECTED.

Certificates are kept as DER, named by their thumbprint (the SHA-1 of the DER, as OPC UA names certificates)
and written atomically. The layout is the `trusted/` and `rejected/` PKI folders of open62541 and UA-.NET.
Plain files and no asyncua: the service and the CLI use it without an OPC UA server.
"""

from __future__ import annotations

import hashlib
import string
import threading
from datetime import datetime, timezone
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives.serialization import Encoding

from cellctl.errors import InvalidRequest, NotFound
from cellctl.stores.run_folder import write_atomic

MAX_REJECTED = 200  # a client making a new certificate at every try cannot fill the disk
MIN_PREFIX = 8  # hex digits of a thumbprint that name a certificate; fewer could trust the wrong one by a slip
SHOWN = 12  # hex digits of a thumbprint in listings and messages
CERT_SUFFIXES = (".der", ".pem", ".crt", ".cer")
_WRITES = threading.Lock()  # write_atomic's temporary name is per process: one writer at a time


def thumbprint(der: bytes) -> str:
    return hashlib.sha1(der).hexdigest()  # noqa: S324 - OPC UA's certificate thumbprint is SHA-1 by definition


def parse_certificate(data: bytes, what: str) -> bytes:
    """A certificate (PEM or DER) as DER; InvalidRequest naming `what` when it is not one."""
    try:
        cert = x509.load_pem_x509_certificate(data) if b"-----BEGIN" in data else x509.load_der_x509_certificate(data)
    except ValueError:
        raise InvalidRequest(f"{what} is not an X.509 certificate (PEM or DER)") from None
    return cert.public_bytes(Encoding.DER)


def read_certificate(path: str | Path, what: str) -> bytes:
    """A certificate file (DER or PEM) as DER; a clear error naming `what` (the cell file's key) when it is not one."""
    try:
        data = Path(path).expanduser().read_bytes()
    except OSError as exc:
        raise InvalidRequest(f"{what}: cannot read {path}: {exc.strerror}") from None
    return parse_certificate(data, f"{what}: {path}")


class ClientCertificates:
    """The trusted and rejected client application certificates of one store.

    `folder`: the store's `opcua/`; `pinned`: the cell file's trusted certificates, {file as written: DER}."""

    def __init__(self, folder: Path, pinned: dict[str, bytes] | None = None):
        self.trusted_dir, self.rejected_dir = Path(folder) / "trusted", Path(folder) / "rejected"
        self.pinned = dict(pinned or {})

    # -- what the server asks ----------------------------------------------------------------------------
    def is_trusted(self, der: bytes) -> bool:
        return der in self.pinned.values() or any(d == der for _, d in _files(self.trusted_dir))

    def reject(self, der: bytes) -> bool:
        """Keep an untrusted certificate in rejected/ (True), unless it is there already (False)."""
        path = self.rejected_dir / f"{thumbprint(der)}.der"
        with _WRITES:
            if path.exists():
                return False
            self.rejected_dir.mkdir(parents=True, exist_ok=True)
            write_atomic(path, der, 0o644)
            kept = sorted(self.rejected_dir.glob("*.der"), key=lambda p: p.stat().st_mtime)
            for old in kept[:-MAX_REJECTED]:
                old.unlink(missing_ok=True)
        return True

    # -- what an engineer does -----------------------------------------------------------------------
    def listing(self) -> dict:
        """{"trusted": [...], "rejected": [...]}, each a certificate's thumbprint, subject, application URI,
        validity, file and source ("cell file" or "store"); a file in the folders that is no certificate is
        listed with its `problem`."""
        trusted = [describe(der, path, "cell file") for path, der in self.pinned.items()]
        trusted += [describe(der, path, "store") for path, der in _files(self.trusted_dir, with_unreadable=True)]
        rejected = [dict(describe(der, path, "store"), rejected_at=_mtime(path))
                    for path, der in _files(self.rejected_dir, with_unreadable=True)]
        return {"trusted": trusted, "rejected": rejected, "trusted_dir": str(self.trusted_dir),
                "rejected_dir": str(self.rejected_dir)}

    def find(self, text: str) -> bytes:
        """The certificate a thumbprint (or its first MIN_PREFIX+ hex digits; `:` and spaces ignored) names,
        among the rejected and the trusted ones."""
        prefix = "".join(c for c in text.lower() if c not in ": ")
        if not prefix or any(c not in string.hexdigits for c in prefix):
            raise InvalidRequest(f"thumbprint: {text!r} is not hexadecimal; give a certificate's thumbprint (its "
                                 f"first {MIN_PREFIX} digits or more) as `cellctl opcua certificates` shows it")
        if len(prefix) < MIN_PREFIX:
            raise InvalidRequest(f"thumbprint: {text!r} is too short; give at least {MIN_PREFIX} hex digits")
        known = {thumbprint(der): der for der in [*self.pinned.values(), *(d for _, d in _files(self.trusted_dir)),
                                                  *(d for _, d in _files(self.rejected_dir))]}
        matches = sorted(t for t in known if t.startswith(prefix))
        if len(matches) > 1:
            raise InvalidRequest(f"thumbprint: {text!r} is ambiguous; it starts {len(matches)} certificates: "
                                 f"{', '.join(t[:SHOWN] for t in matches)}; give more digits")
        if not matches:
            rejected = [thumbprint(d)[:SHOWN] for _, d in _files(self.rejected_dir)]
            raise NotFound(f"thumbprint: no certificate {prefix} among the rejected or trusted ones (rejected: "
                           f"{', '.join(rejected) or 'none'}); `cellctl opcua certificates` lists them")
        return known[matches[0]]

    def trust(self, der: bytes) -> dict:
        """Trust a certificate from the next session on: into trusted/, then out of rejected/ (so a crash between
        leaves it trusted, never lost). {"certificate": its description, "already": it was trusted before}."""
        name = f"{thumbprint(der)}.der"
        already = self.is_trusted(der)
        with _WRITES:
            if not already:
                self.trusted_dir.mkdir(parents=True, exist_ok=True)
                write_atomic(self.trusted_dir / name, der, 0o644)
            (self.rejected_dir / name).unlink(missing_ok=True)
        where = next((p for p, d in self.pinned.items() if d == der), None) if already else None
        if where is None:
            where = next(p for p, d in _files(self.trusted_dir) if d == der)
        return {"certificate": describe(der, where, "cell file" if where in self.pinned else "store"),
                "already": already}


def describe(der: bytes | None, path: str | Path, source: str) -> dict:
    """A certificate as the listings show it."""
    out = {"file": str(path), "source": source}
    if der is None:
        return dict(out, problem="not an X.509 certificate (PEM or DER)")
    cert = x509.load_der_x509_certificate(der)
    try:
        names = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        uris = names.get_values_for_type(x509.UniformResourceIdentifier)
    except (x509.ExtensionNotFound, ValueError):
        uris = []
    until = cert.not_valid_after_utc
    return dict(out, thumbprint=thumbprint(der), subject=cert.subject.rfc4514_string(),
                application_uri=uris[0] if uris else None, not_after=until.isoformat(),
                expired=until < datetime.now(timezone.utc))


def _mtime(path: Path) -> str | None:
    try:
        return datetime.fromtimestamp(path.stat().st_mtime, timezone.utc).isoformat(timespec="seconds")
    except OSError:  # trusted meanwhile
        return None


def _files(folder: Path, with_unreadable: bool = False) -> list[tuple[Path, bytes | None]]:
    """(path, DER) of each certificate file in a folder, by name; files that are no certificate only
    `with_unreadable` (as None), never the temporary files of a write in progress (dot files)."""
    if not folder.is_dir():
        return []
    out = []
    for path in sorted(folder.iterdir()):
        if path.name.startswith(".") or path.suffix.lower() not in CERT_SUFFIXES or not path.is_file():
            continue
        try:
            out.append((path, parse_certificate(path.read_bytes(), str(path))))
        except (InvalidRequest, OSError):
            if with_unreadable:
                out.append((path, None))
    return out
