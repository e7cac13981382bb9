"""The fleet page: every cell of the plant database on one read-only web page (static files in page/).

`router(connect)` serves the page at `/` and its data as JSON (`/api/status`, `/api/trend`, `/api/jobs`: the
queries of plant.py). Each request opens its own connection with `connect()` and closes it, so a page left open
holds nothing while idle and a database that restarts is picked up by the next request. A database that cannot
be reached answers 503 with `{"detail": ...}`, which the page shows while keeping what it last had.

`cellctl fleet serve` runs `create_app` on loopback (`serve`); a daemon whose cell file has `fleet.postgres`
includes the router at /fleet/ (cellctl/http/api.py). Nothing here writes, so nothing needs a token.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import psycopg
from fastapi import APIRouter, FastAPI, Query
from fastapi.responses import FileResponse, JSONResponse
from pydantic import BaseModel

from cellctl.errors import Unreachable
from cellctl.fleet import plant

PAGE_DIR = Path(__file__).with_name("page")
STATIC = {"fleet.js": "text/javascript", "fleet.css": "text/css"}


class PlantUnreachable(BaseModel):
    detail: str


# declared on each JSON route, so a schema that includes the router (the daemon's) documents the 503
UNREACHABLE: dict[int | str, dict[str, Any]] = {
    503: {"model": PlantUnreachable, "description": "the plant database cannot be reached, or no cell has set it up yet"}}


def connector(dsn: str, timeout_s: int = 5) -> Callable[[], psycopg.Connection]:
    """`connect` for the router: a new connection to `dsn` (plant.connect)."""
    return lambda: plant.connect(dsn, timeout_s)


def _down(why: str) -> JSONResponse:
    return JSONResponse({"detail": why}, status_code=503, headers={"Retry-After": "5"})


def _read(connect: Callable[[], psycopg.Connection], query: Callable[[psycopg.Connection], dict]):
    """`query` on a connection of its own; 503 with the reason when the database is down or not set up."""
    try:
        conn = connect()
    except Unreachable as exc:
        return _down(str(exc))
    except (psycopg.Error, OSError) as exc:
        return _down("the plant database cannot be reached: " + " ".join(str(exc).split()))
    try:
        return query(conn)
    except psycopg.errors.UndefinedTable:  # a new plant database: tables come with the first cell's connection
        return _down("the plant database has no cellctl tables yet: no cell has connected to it")
    except (psycopg.OperationalError, psycopg.InterfaceError) as exc:  # lost in the middle of the query
        return _down("the plant database cannot be reached: " + " ".join(str(exc).split()))
    finally:
        conn.close()


def router(connect: Callable[[], psycopg.Connection]) -> APIRouter:
    """The page and its JSON; `connect()` returns a new psycopg connection (closed after each request)."""
    r = APIRouter()

    # the page's files, by name (never a path from the request); out of the API schema, like the console
    @r.get("/", include_in_schema=False)
    def page():
        return FileResponse(PAGE_DIR / "fleet.html", media_type="text/html", headers={"Cache-Control": "no-cache"})

    def static(name: str, media_type: str):
        # a closure, not default arguments: FastAPI would take those for query parameters
        return lambda: FileResponse(PAGE_DIR / name, media_type=media_type, headers={"Cache-Control": "no-cache"})

    for name, media_type in STATIC.items():
        r.add_api_route(f"/{name}", static(name, media_type), methods=["GET"], include_in_schema=False)

    @r.get("/api/status", summary="fleet: every cell's state, last word, live job and active calibrations "
           "(version, verification mean, health)", responses=UNREACHABLE)
    def status():
        return _read(connect, plant.status)

    @r.get("/api/trend", summary="fleet: per target and cell, each version's verification mean and each "
           "check's drift (µm) over time", responses=UNREACHABLE)
    def trend():
        return _read(connect, plant.trend)

    @r.get("/api/jobs", summary="fleet: the jobs of every cell, newest first", responses=UNREACHABLE)
    def jobs(limit: int = Query(100, ge=1, le=1000, description="at most this many")):
        return _read(connect, lambda conn: plant.jobs(conn, limit=limit))

    return r


def create_app(connect: Callable[[], psycopg.Connection]) -> FastAPI:
    """The fleet page on its own (`cellctl fleet serve`): the router at /, no interactive docs (they would load
    scripts from elsewhere)."""
    app = FastAPI(title="cellctl fleet page", version="1", docs_url=None, redoc_url=None,
                  description="Read-only: the plant database's cells, their calibrations and their health.")
    app.include_router(router(connect))
    return app


def serve(dsn: str, host: str = "127.0.0.1", port: int = 8480) -> int:
    """Serve the fleet page until interrupted; loopback by default (it shows the plant to whoever reaches it)."""
    import uvicorn

    uvicorn.run(create_app(connector(dsn)), host=host, port=port, log_level="info", access_log=False)
    return 0
