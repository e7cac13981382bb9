"""The store's routes of the HTTP API.

    POST /store/backup     back the store up now (cellctl/stores/backup.py), where the cell file says

The route is the service's `backup_store` verb, which `cellctl store backup --url URL` calls too: a client
that cannot read the store's files itself (the daemon's service user owns them) still gets a backup. It is a
command (the bearer token, audited) but not behind the operator lock: it moves nothing. Where the backup goes
is the cell file's, never the request's: a client cannot make the daemon write elsewhere. A restore has no
route: it needs a store that no daemon serves (`cellctl store restore`, on the cell PC).
"""

from __future__ import annotations

from fastapi import APIRouter, Request

from cellctl.http.contract import LOCK as Lock
from cellctl.http.contract import client_of, errors
from cellctl.service import Caller


def store_router(daemon) -> APIRouter:
    router = APIRouter()
    service = daemon.service

    @router.post("/store/backup", summary="back the store up now: its databases (SQLite's online backup, "
                 "consistent while a job runs) and run folders, into the cell file's store.backup.to",
                 responses=errors(507))
    def backup_store(request: Request, lock: str | None = Lock):
        request.state.audited = True  # the service audits it
        return service.backup_store(Caller(client_of(request), lock, f"{request.method} {request.url.path}"))

    return router
