"""The core: a cell and what runs on it, below the service and above the stores.

`cell` (devices built from the cell file), `orchestrator` (a routine's steps, persisted one by one, paused,
resumed), `runs` (one routine or sequence, start to finish: parameters, collection, fit, truth, result files),
`report` (report.md and its plots), `worker` (the daemon's thread that owns the cell and runs jobs one at a
time), `events` (the progress event stream)."""
