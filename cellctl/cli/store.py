"""`cellctl store`: check the store's databases, back the store up, restore a backup (cellctl/stores/backup.py).

The store is named by `--store DIR`, $CELLCTL_STORE or the cell file of `--config`. A backup is taken beside a
running daemon (SQLite's online backup API: a consistent snapshot) or without one; a restore is refused while a
process owns the store."""

from __future__ import annotations

import argparse
from pathlib import Path

from cellctl.cli.args import InputError
from cellctl.cli.verbs import EXIT_OK, ca, client_name, daemon_url, store_dir, token

# the stores and the ownership locks are imported by the commands that use them: `cellctl --help` stays light


def add_store_command(sub) -> None:
    store = sub.add_parser("store", help="the cell's store: check its databases, back it up, restore a backup")
    verbs = store.add_subparsers(dest="store_command", required=True)
    check = verbs.add_parser("check", help="run SQLite's quick integrity check on the store's databases")
    _named(check)
    check.set_defaults(func=check_store)
    backup = verbs.add_parser("backup", help="back the store up (its databases through SQLite's online backup, "
                                             "with the run folders) into a new timestamped folder; works beside a "
                                             "running daemon")
    _named(backup)
    backup.add_argument("--to", metavar="DIR", help="folder of the backups (default: the cell file's "
                                                    "store.backup.to, else <store>-backups beside the store)")
    backup.add_argument("--keep", type=int, metavar="N", help="then keep only the newest N backups in that folder")
    backup.add_argument("--url", help="ask the daemon to take it (default: $CELLCTL_URL; none: read the store "
                                      "directly), into the cell file's store.backup.to, keeping its keep")
    backup.add_argument("--token", help="the daemon's token (default: $CELLCTL_TOKEN, or the store's token file)")
    backup.add_argument("--ca", metavar="FILE", help="an https:// daemon's certificate to trust (default: $CELLCTL_CA)")
    backup.set_defaults(func=backup_store)
    restore = verbs.add_parser("restore", help="put a backup in place of the store (refused while a daemon owns "
                                               "it); the replaced store is kept beside it")
    restore.add_argument("backup", metavar="BACKUP", help="a cellctl-backup-* folder")
    _named(restore)
    restore.set_defaults(func=restore_store)


def _named(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", help="cell file (its store; its store.backup section)")
    p.add_argument("--store", help="the store folder instead of --config (default: $CELLCTL_STORE)")


def _store(args) -> Path:
    found = store_dir(args)
    if found is None:
        raise InputError(f"store {args.store_command} needs --config FILE, --store DIR or $CELLCTL_STORE")
    return found


def _backups(args, store: Path) -> Path:
    from cellctl.stores.backup import default_backups

    if getattr(args, "to", None):
        return Path(args.to)
    if args.config:
        from cellctl.config import load_cell_file

        settings = load_cell_file(args.config, routines=False)[0].store.backup
        if settings is not None:
            return settings.folder(store)
    return default_backups(store)


def check_store(args) -> int:
    from cellctl.stores.backup import check_store as check

    store = _store(args)
    hint = f" --config {args.config}" if args.config else f" --store {store}"
    check(store, _backups(args, store), hint)
    print(f"{store}: the databases pass SQLite's quick check")
    return 0


def backup_store(args) -> int:
    from cellctl.stores.backup import backup

    if args.keep is not None and args.keep < 1:
        raise InputError(f"--keep {args.keep}: keep at least 1 backup")
    if daemon_url(args):
        return _backup_through(args)
    store = _store(args)
    cell, min_free_mb = "", 0.0
    if args.config:
        from cellctl.config import load_cell_file

        config = load_cell_file(args.config, routines=False)[0]
        cell, min_free_mb = config.cell.name, config.store.min_free_mb
    try:
        made = backup(store, _backups(args, store), cell=cell, keep=args.keep, min_free_mb=min_free_mb)
    except OSError as exc:  # e.g. a store of the daemon's service user, unreadable to this one
        raise InputError(f"cannot back up {store}: {exc}; run it as the daemon's user, or give --to DIR") from None
    print(f"backed up {store} into {made}")
    return 0


def _backup_through(args) -> int:
    """The daemon takes it (its user reads the store): where and how many to keep are its cell file's."""
    import os

    from cellctl.service import Caller
    from cellctl.service.remote import RemoteService

    if args.to or args.keep is not None:
        raise InputError("--to and --keep are the daemon's to choose (its cell file's store.backup); drop them, "
                         "or back up without --url / $CELLCTL_URL")
    service = RemoteService(daemon_url(args), token(args), ca=ca(args))
    try:
        made = service.backup_store(Caller(client_name(), os.environ.get("CELLCTL_LOCK"), "cli store backup"))
    finally:
        service.close()
    print(f"the daemon at {service.url} backed its store up into {made['backup']}")
    return EXIT_OK


def restore_store(args) -> int:
    from cellctl.startup.ownership import own_store
    from cellctl.stores.backup import restore

    store = _store(args)
    backup_dir = Path(args.backup)
    if not backup_dir.is_dir():
        raise InputError(f"{backup_dir} is no folder: name a cellctl-backup-* folder (`cellctl store backup` "
                         "prints where it wrote one)")
    with own_store(store, "cellctl store restore", verb=None):  # no daemon may serve the store meanwhile
        try:
            kept = restore(backup_dir, store)
        except OSError as exc:  # the store is as it was: the swap is the last step, and one rename
            raise InputError(f"cannot restore {backup_dir} into {store}: {exc}; the store is unchanged (its "
                             "folder and the one beside it must be on one filesystem, writable by this user)") from None
    print(f"restored {backup_dir} into {store}" + (f"; the store it replaced is kept in {kept}" if kept else ""))
    print("start the daemon: a job that was running when the backup was taken comes back faulted; acknowledge it, "
          "then resume it")
    return 0
