"""Seed 002's IRB 120 cell: CSM / VW-CSM positioning (`_samples`: the marker sets and their reading,
`_experiments`: the paper's tables)."""

ALIASES = {"csm": "csm-positioning"}  # `cellctl fit csm`: csm-positioning's view parameters
