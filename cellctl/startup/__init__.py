"""Start-up: wires the cell, the stores, the service and its front ends into the daemon.

    cellctl.startup.serve(config_path, host="127.0.0.1", port=8470)

Modules: `daemon` (start-up, shutdown, systemd notification, JSON-lines logs), `ownership`
(one daemon per store), `tls` (the certificate the daemon serves).
"""

__all__ = ["DEFAULT_PORT", "TLS_HELP", "serve"]

# `--tls` of `cellctl serve` and of `python -m cellctl.startup`: here, where the CLI reads it without loading tls.py
TLS_HELP = ("serve HTTPS (the cell file's certificate, else one made in the store at first start); beyond loopback "
            "HTTPS is needed unless the cell file says http: {allow_plain: true}")


def __getattr__(name: str):
    """`serve`, `DEFAULT_PORT`: imported on first use, so a client reading the token (`.auth`) or the TLS
    help does not load the daemon's web framework and the whole cell."""
    if name in ("DEFAULT_PORT", "serve"):
        from cellctl.startup import daemon

        return getattr(daemon, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
