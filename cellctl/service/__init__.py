"""The verbs of a cell, once: the interface (`interface`), in-process (`local`), over HTTP (`remote`).

Front ends (cellctl/cli, cellctl/http/api.py, later OPC UA) call a `CellService` and
translate its values and `cellctl.errors.ServiceError`s; they hold no logic of their own.
"""

from cellctl.service.interface import Blob, Caller, CellService, Export

__all__ = ["Blob", "Caller", "CellService", "Export"]
