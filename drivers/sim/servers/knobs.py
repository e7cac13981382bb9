"""The link fault knobs every socket simulator shares (ABB, EPick, VGC10: `--option` of `cellctl sim`, `options:`
of a cell file's sim.servers), each value checked by name: a knob that cannot work is refused at start, never
taken and misbehaving later."""

from __future__ import annotations


def check_link_knobs(faults) -> None:
    """ValueError naming the knob, its value and what is allowed."""
    drop = faults.drop_after_messages
    if drop is not None and (type(drop) is not int or drop < 1):
        raise ValueError(f"drop_after_messages={drop!r}: a whole number of messages >= 1, or none")
    delay = faults.reply_delay_s
    if type(delay) not in (int, float) or not 0 <= delay <= 60:
        raise ValueError(f"reply_delay_s={delay!r}: seconds, 0 to 60")
    if type(faults.malformed_replies) is not bool:
        raise ValueError(f"malformed_replies={faults.malformed_replies!r}: true or false")
