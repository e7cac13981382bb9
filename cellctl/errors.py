"""What the cell's service refuses, and why: one error type per kind of refusal.

Every front end maps these once: HTTP to the status code they carry, the CLI to its
exit status, OPC UA to a Bad status code. The message names what was wrong and what
is allowed, so it can be shown as it is.
"""

from __future__ import annotations


class ServiceError(Exception):
    """A request the cell refused; nothing changed."""

    status = 400

    def __init__(self, message: str, problems: list[dict] | None = None):
        super().__init__(message)
        self.problems = problems  # [{"field", "problem"}] where a request had several bad fields


class InvalidRequest(ServiceError):
    """A field of the request is malformed or not allowed (names the field and what is allowed)."""

    status = 422


class NotFound(ServiceError):
    """No such job, job item, calibration, camera or file."""

    status = 404


class Conflict(ServiceError):
    """The job's or the cell's state does not allow this now."""

    status = 409


class LockHeld(ServiceError):
    """Another client holds the operator lock."""

    status = 423


class Unavailable(ServiceError):
    """This service cannot do that at all here (e.g. jobs without a daemon), or cannot be reached."""

    status = 503


class InsufficientStorage(ServiceError):
    """The store's filesystem has too little free space for this (cellctl/stores/disk_space.py)."""

    status = 507


class Unreachable(ServiceError):
    """The daemon could not be reached (or its event stream broke): the cell's side, not the request's."""

    status = 503
