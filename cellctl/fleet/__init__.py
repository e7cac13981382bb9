"""A fleet of cells: every cell's records replicated to one plant database (PostgreSQL) and one event stream
(MQTT), the cell's own SQLite staying its source of truth. `schema` holds the plant database's versioned
migrations."""
