"""What a cell keeps: `jobs` (job records, their states and the audit, SQLite), `calibrations` (versioned
calibrations with their samples and checks, SQLite), `run_folder` (a run's samples.csv, run.json, images and
result files), `outbox` (records waiting for the fleet's replication), `client_certificates` (the OPC UA client
certificates trusted and rejected)."""
