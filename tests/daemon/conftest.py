"""Fixtures of the daemon tests (helpers in daemon_helpers.py)."""

from daemon_helpers import reference, start_daemon  # noqa: F401  (fixtures)
