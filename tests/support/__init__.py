"""What the tests share: waiting on an event (`wait`), free ports (`ports`), the daemon as a process (`daemon`)
and its load (`daemon_load`), the plant's servers (`servers`), a wire peer that plays a protocol's other end
(`wire`), the driver contracts (`contract`), the browser (`chromium`), and the cells and sessions several
folders use (`cells`, `console`, `operator`, `opcua`). Imported as `tests.support.X`; no test module imports
another."""
