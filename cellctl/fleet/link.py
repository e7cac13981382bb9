"""A cell's link to its fleet: the sinks its cell file names, the outboxes of its two stores, one replicator."""

from __future__ import annotations

import subprocess
from importlib import metadata
from pathlib import Path

from cellctl.config import CellFile
from cellctl.fleet import secrets
from cellctl.fleet.replicator import Replicator, Sink
from cellctl.stores.outbox import Outbox


def software_revision() -> str:
    """cellctl's version, with the git commit it runs from when there is one."""
    version = metadata.version("cellctl")
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=Path(__file__).parent, timeout=5,
                                capture_output=True, text=True).stdout.strip()
    except (OSError, subprocess.TimeoutExpired):
        commit = ""
    return f"{version}+{commit}" if commit else version


def sinks(config: CellFile, base: Path, api_url: str = "") -> list[Sink]:
    """The sinks of the cell file's fleet: section, their credentials read now (a bad one: CredentialError)."""
    fleet = config.fleet
    if fleet is None:
        return []
    info = {"description": config.cell.description, "software_revision": software_revision(),
            "api_url": fleet.api_url or api_url}
    out: list[Sink] = []
    if fleet.postgres is not None:
        from cellctl.fleet.postgres import PostgresSink

        dsn = secrets.read("fleet.postgres", fleet.postgres.dsn_file, fleet.postgres.dsn_env, base)
        out.append(PostgresSink(dsn, config.fleet_name, info))
    if fleet.mqtt is not None:
        from cellctl.fleet.mqtt import MqttSink

        password = secrets.read("fleet.mqtt password", fleet.mqtt.password_file, fleet.mqtt.password_env, base)
        out.append(MqttSink(fleet.mqtt, config.fleet_name, password, base_dir=base, info=info))
    return out


def replicator(config: CellFile, base: Path, databases: dict[str, Path], api_url: str = "") -> Replicator | None:
    """The replicator over the stores' databases (source name -> SQLite file), or None outside a fleet."""
    chosen = sinks(config, base, api_url)
    if not chosen:
        return None
    outboxes = [Outbox(path, source) for source, path in databases.items()]
    return Replicator(outboxes, chosen, heartbeat_s=config.fleet.heartbeat_s)
