"""The cell daemon: owns the cell's devices, runs jobs one at a time, serves the HTTP API.

    cellctl.daemon.serve(config_path, host="127.0.0.1", port=8470)

Modules: `jobs` (job records and their state machine in SQLite, the audit log),
`worker` (the worker thread and the cell it owns), `api` (FastAPI app), `auth`
(token and operator lock), `events` (progress event stream), `service` (start-up,
shutdown, systemd notification, JSON-lines logs), `overlay` (what the console draws over a
camera's frame); `console/` holds the web console's static files, served at /console/.
"""

__all__ = ["DEFAULT_PORT", "TLS_HELP", "serve"]

# `--tls` of `cellctl serve` and of `python -m cellctl.daemon`: here, where the CLI reads it without loading tls.py
TLS_HELP = ("serve HTTPS (the cell file's certificate, else one made in the store at first start); beyond loopback "
            "HTTPS is needed unless the cell file says http: {allow_plain: true}")


def __getattr__(name: str):
    """`serve`, `DEFAULT_PORT`: imported on first use, so a client reading the token (`.auth`) or the TLS
    help does not load the daemon's web framework and the whole cell."""
    if name in ("DEFAULT_PORT", "serve"):
        from . import service

        return getattr(service, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
