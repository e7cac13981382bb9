"""Fixtures of the daemon tests (helpers in daemon_helpers.py)."""

from daemon_helpers import start_daemon  # noqa: F401  (a fixture)
