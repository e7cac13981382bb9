"""`cellctl opcua`: the OPC UA server's client certificates. `certificates` lists the trusted and the rejected
ones; `trust FILE|THUMBPRINT` trusts one from the client's next session on, without a restart.

`trust` goes through the daemon when `--url` (or $CELLCTL_URL) names one, or when a daemon owns the cell's
store (cellctl.startup.ownership): that daemon audits it. With no daemon, it takes the store for the moment and is
audited in the store's own log all the same (`cellctl logs` shows it once the daemon runs). `certificates`
reads the files, beside any owner."""

from __future__ import annotations

import os
import string
from contextlib import contextmanager
from pathlib import Path

from cellctl.cli.args import InputError
from cellctl.cli.verbs import connection_options


def add_opcua_command(sub) -> None:
    opcua = sub.add_parser("opcua", help="the OPC UA server's client certificates: list the trusted and the "
                                         "rejected ones, trust one (no restart)")
    verbs = opcua.add_subparsers(dest="opcua_command", required=True)
    listing = verbs.add_parser("certificates", help="the client application certificates trusted on Sign / "
                                                    "SignAndEncrypt channels, and those refused there")
    listing.add_argument("--json", action="store_true", help="print the service's answer as JSON")
    connection_options(listing, local=True)
    listing.set_defaults(func=certificates)
    trust = verbs.add_parser("trust", help="trust a client certificate from its next session on (no restart)")
    trust.add_argument("certificate", metavar="FILE|THUMBPRINT", help="a certificate file (PEM or DER), or the "
                       "thumbprint of a rejected one (`cellctl opcua certificates` shows it; 8+ leading hex digits)")
    connection_options(trust, local=True)
    trust.set_defaults(func=trust_certificate)


def certificates(args) -> int:
    with _service(args) as (service, _):
        got = service.opcua_certificates()
    if args.json:
        import json

        print(json.dumps(got, indent=2))
        return 0
    print(f"trusted on Sign / SignAndEncrypt ({len(got['trusted'])}): the cell file's opcua.trusted_clients and "
          f"{got['trusted_dir']}")
    for cert in got["trusted"]:
        _print_certificate(cert, cert["source"])
    print(f"rejected ({len(got['rejected'])}), kept in {got['rejected_dir']}"
          + (": trust one with `cellctl opcua trust THUMBPRINT`" if got["rejected"] else ""))
    for cert in got["rejected"]:
        _print_certificate(cert, f"rejected {cert['rejected_at']}" if cert.get("rejected_at") else "rejected")
    return 0


def trust_certificate(args) -> int:
    given = args.certificate
    path = Path(given).expanduser()
    thumbprint, data = None, None
    if path.is_file():
        from cellctl.stores.client_certificates import parse_certificate

        try:
            data = path.read_bytes()
        except OSError as exc:
            raise InputError(f"{given}: cannot read: {exc.strerror}") from None
        parse_certificate(data, given)  # said here, before any daemon is asked
    elif path.exists():
        raise InputError(f"{given} is a folder; give a certificate file (PEM or DER) or a thumbprint")
    elif given and all(c in string.hexdigits + ": " for c in given):
        thumbprint = given
    else:
        raise InputError(f"{given}: no such file, and not a thumbprint (hex digits); give a certificate file (PEM or "
                         "DER), or the thumbprint of a rejected one as `cellctl opcua certificates` shows it")
    with _service(args, writes=True) as (service, caller):
        got = service.trust_opcua_certificate(caller, thumbprint, data)
    cert = got["certificate"]
    what = f"{cert['thumbprint'][:12]} ({cert.get('application_uri') or '-'}, {cert['subject']})"
    if got["already"]:
        print(f"OPC UA client certificate {what} was already trusted: {cert['file']}")
    else:
        print(f"trusted OPC UA client certificate {what} from its next session on: {cert['file']}")
    return 0


def _print_certificate(cert: dict, note: str) -> None:
    if "thumbprint" not in cert:
        print(f"  {'?':<12}  {cert['problem']}\n  {'':<12}  {cert['file']}")
        return
    until = cert["not_after"][:10] + (" (EXPIRED)" if cert["expired"] else "")
    print(f"  {cert['thumbprint'][:12]}  {cert.get('application_uri') or '-'} ({cert['subject']}), valid until {until}")
    print(f"  {'':<12}  {cert['file']} ({note})")


@contextmanager
def _service(args, writes: bool = False):
    """(service, caller) for the command: the daemon's when --url / $CELLCTL_URL names one; else the store's own,
    where a write takes the store (cellctl.startup.ownership) and, when a daemon owns it, goes through that daemon."""
    from cellctl.cli import verbs
    from cellctl.service import Caller

    command = f"cellctl opcua {args.opcua_command}"
    caller = Caller(verbs.client_name(), os.environ.get("CELLCTL_LOCK"), f"cli opcua {args.opcua_command}")
    url = verbs.daemon_url(args)
    if url:
        with _remote(url, verbs.token(args), verbs.ca(args)) as service:
            yield service, caller
        return
    store = verbs.store_dir(args)
    if store is None:
        raise InputError(f"{command}: give --config CELL_FILE or --store DIR / $CELLCTL_STORE (its store), or "
                         "--url URL / $CELLCTL_URL (the daemon)")
    from cellctl.config import load_cell_file
    from cellctl.startup.ownership import CellOwned, own_store

    config = load_cell_file(args.config, routines=False)[0] if args.config else None  # its trusted_clients
    store = store.expanduser()
    if not writes:  # reading the files beside an owner is safe
        yield _local(config, store, None), caller
        return
    try:
        owned = own_store(store, f"{command} (local)", verb=f"{command} {args.certificate}")
    except CellOwned as exc:
        with _remote(*verbs.owner_daemon(args, exc, "going through it")) as service:
            yield service, caller
        return
    with owned:
        from dataclasses import replace

        from cellctl.stores.jobs import DB_FILE, JobStore

        # the audit log is the store's own: `cellctl logs` shows the trust once the daemon runs (and the plant)
        jobs = JobStore(store / DB_FILE, replicate=config is not None and config.fleet is not None)
        try:
            yield _local(config, store, jobs), replace(caller, credential="local")
        finally:
            jobs.close()


@contextmanager
def _remote(url: str, token: str | None, ca: str | None):
    from cellctl.service.remote import RemoteService

    with RemoteService(url, token, ca=ca) as service:
        yield service


def _local(config, store: Path, jobs):
    from cellctl.service.local import LocalService

    return LocalService(config, None, audit_log=jobs, store_dir=store)  # no calibration store: these verbs need none
