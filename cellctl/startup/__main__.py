"""`python -m cellctl.startup --config FILE [--host H] [--port P] [--tls]`: what `cellctl serve` runs."""

import argparse
import sys

from cellctl.startup import TLS_HELP
from cellctl.startup.daemon import DEFAULT_PORT, serve


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="cellctl serve", description="run the cell daemon")
    parser.add_argument("--config", required=True, help="cell file (YAML)")
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1: this machine only)")
    parser.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"TCP port (default {DEFAULT_PORT}; 0: any free)")
    parser.add_argument("--tls", action="store_true", help=TLS_HELP)
    parser.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"])
    args = parser.parse_args(argv)
    from cellctl.config import CellFileError
    from cellctl.errors import ServiceError

    try:
        return serve(args.config, args.host, args.port, args.log_level, tls=args.tls)
    except (CellFileError, ServiceError) as exc:
        print(f"cellctl serve: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
