"""ABB robots over a TCP socket: the open_abb protocol.

`driver.AbbArm` talks to `rapid/CellctlServer.mod` running on the controller (replies
ended by '#') or to the public open_abb SERVER.mod (no terminator: framed by the field
count of each request code); `protocol` encodes requests and parses replies (pure
functions). The protocol simulator for tests is `drivers/sim/servers/abb.py`.
"""

from drivers.arms.abb.driver import AbbArm, AbbArmSettings, CommandRejected
from drivers.arms.abb.protocol import MalformedReply, ReplyTimeout, RobotInfo

__all__ = ["AbbArm", "AbbArmSettings", "CommandRejected", "MalformedReply", "ReplyTimeout", "RobotInfo"]
