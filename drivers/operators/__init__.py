"""The person at the cell: `terminal` (answers typed at the daemon's terminal) and `web` (answers given at the
daemon's web console, through its operator desk)."""
