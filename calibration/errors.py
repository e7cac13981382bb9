"""Typed errors of the calibration layer.

Each says what was wrong and what is allowed, so the CLI and the API can pass
the message to the engineer unchanged.
"""


class CalibrationError(Exception):
    """Base class of every calibration-layer error."""


class CalibrationInputError(CalibrationError, ValueError):
    """Samples cannot be fitted: too few, non-finite, degenerate geometry, bad columns."""


class VisionError(CalibrationError):
    """An image could not be measured: no feature, several candidates, feature cut by the border."""


class UnknownName(CalibrationError, LookupError):
    """A routine, area or camera name that the cell does not have; the message lists those it has."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""
