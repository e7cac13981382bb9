"""The plant database's migrations on a real PostgreSQL: applied once, in order, by one of many cells at once,
and refused with a clear message by a cellctl older than the database."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import psycopg
import pytest

from cellctl.fleet.schema import MIGRATIONS, migrate

TABLES = {"cells", "jobs", "job_states", "samples", "results", "calibrations", "health_checks", "audit"}


def test_many_cells_migrate_one_database_at_once(postgres):
    def one(_):
        with psycopg.connect(postgres.dsn) as conn:
            return migrate(conn)

    with ThreadPoolExecutor(6) as pool:
        versions = list(pool.map(one, range(6)))
    assert versions == [MIGRATIONS[-1][0]] * 6
    with psycopg.connect(postgres.dsn) as conn:
        applied = conn.execute("SELECT version FROM schema_migrations ORDER BY version").fetchall()
        assert [v for (v,) in applied] == [v for v, _, _ in MIGRATIONS]  # each once
        tables = {t for (t,) in conn.execute("SELECT tablename FROM pg_tables WHERE schemaname = 'public'")}
        assert TABLES <= tables
        assert migrate(conn) == MIGRATIONS[-1][0]  # again: nothing to do


def test_a_database_newer_than_this_cellctl_is_refused(postgres):
    with psycopg.connect(postgres.dsn) as conn:
        migrate(conn)
        conn.execute("INSERT INTO schema_migrations (version, description) VALUES (999, 'from the future')")
        conn.commit()
        with pytest.raises(RuntimeError, match="schema version 999, newer than this cellctl knows"):
            migrate(conn)
        conn.execute("DELETE FROM schema_migrations WHERE version = 999")
        conn.commit()
