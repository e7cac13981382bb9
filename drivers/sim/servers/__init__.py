"""Protocol-level simulators: the simulated world behind the real wire protocols.

Each module serves one protocol on loopback so the real drivers in `drivers/arms`,
`drivers/grippers` and `drivers/cameras` can be tested over real sockets and serial
ports. Every server module offers `serve(world_config, host, port, ..., stop)` that
blocks until `stop` is set (or SIGTERM, from `cellctl sim`), and fault knobs for tests.
"""
