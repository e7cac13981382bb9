"""The protocol simulators a cell can start, by protocol: a light table (no numerics), so `cellctl sim`'s
arguments are built without loading a world.

protocol -> "module:function(world, spec, arm_limits)" that starts it on the cell's world
(drivers/sim/servers.start_server)."""

SIMULATORS: dict[str, str] = {
    "abb": "drivers.sim.servers.abb:start_for_cell",
    "ur": "drivers.sim.servers.ur.server:start_for_cell",
    "epick": "drivers.sim.servers.epick:start_for_cell",
    "vgc10": "drivers.sim.servers.vgc10:start_for_cell",
}
