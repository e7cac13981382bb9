"""The HTTP API's contract as /openapi.json states it, and the answers only that contract can give.

Each route declares what is its own: the media type of its success body (`body(...)`, `PNG`) and the
errors of its own checks (`errors(404, 409)`). What holds for every route of a kind is added here,
once, from the rules that api.py's middleware and error handlers apply to all of them:
- a command (POST, DELETE) needs the bearer token (401 without it, 403 wrong), may be refused with 423
  while another client holds the operator lock, and gets 400 for a body that is not even text;
- a route with parameters may answer 422, always as ErrorBody (not FastAPI's own validation model).
`MethodGate` answers for the schema: OPTIONS with `Allow` (the methods documented for the path), and
405 with `Allow` for a method the path does not document.
"""

from __future__ import annotations

import re
from typing import Any

from fastapi import FastAPI, Header, Request
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, ConfigDict, Field

ERRORS = {400: "malformed request body (not UTF-8 text)", 401: "no token, or not sent as Bearer TOKEN (commands only)",
          403: "wrong token", 404: "no such job, job item, calibration, camera, request or file",
          409: "the job's (or cell's) state does not allow this", 422: "invalid field",
          423: "another client holds the operator lock",
          507: "the store's filesystem has less free space than the cell file's store.min_free_mb"}
COMMAND_METHODS = ("post", "delete")
BEARER = "bearer"


CLIENT_RE = re.compile(r"^[\w.@:+-]{1,64}$")
LOCK = Header(None, alias="X-Cellctl-Lock", max_length=128, description="the operator lock id, if you hold it")


class Body(BaseModel):
    """Every request body: unknown fields are errors, and no coercion (false is not a seed, "1" not a number)."""

    model_config = ConfigDict(extra="forbid", strict=True)


def client_of(request: Request) -> str:
    """Who sent the request, for the audit: its X-Cellctl-Client name (if well formed) at its address."""
    client = request.headers.get("x-cellctl-client", "anonymous")
    if not CLIENT_RE.match(client):
        client = "invalid-client-name"
    return f"{client}@{request.client.host if request.client else '?'}"


class Problem(BaseModel):
    field: str
    problem: str


class ErrorBody(BaseModel):
    detail: str = Field(..., description="what was wrong, naming the field and what is allowed")
    problems: list[Problem] | None = None
    lock: dict | None = Field(None, description="with 423: who holds the operator lock")
    broken: dict | None = Field(None, description="with 423 to a lock id someone broke: holder, by, reason, at")


def errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    """The `responses` of a route's own refusals, each with the error body."""
    return {code: {"model": ErrorBody, "description": ERRORS[code]} for code in codes}


def body(media_type: str, description: str, schema: dict | None = None) -> dict[int | str, dict[str, Any]]:
    """The `responses` entry of a success body that is not JSON (without a schema: not described further)."""
    return {200: {"description": description, "content": {media_type: {"schema": schema} if schema else {}}}}


PNG = body("image/png", "a PNG image", {"type": "string", "format": "binary"})


def complete(schema: dict) -> dict:
    """Add to FastAPI's schema what the middleware and handlers do for every route (in place)."""
    components = schema.setdefault("components", {})
    models = components.setdefault("schemas", {})
    error_schema = ErrorBody.model_json_schema(ref_template="#/components/schemas/{model}")
    models.update(error_schema.pop("$defs", {}), ErrorBody=error_schema)
    for unused in ("HTTPValidationError", "ValidationError"):  # ours is ErrorBody
        models.pop(unused, None)
    components.setdefault("securitySchemes", {})[BEARER] = {
        "type": "http", "scheme": "bearer", "description": "the daemon's token (`cellctl token` prints it)"}
    error = {"description": "", "content": {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorBody"}}}}
    for operations in schema.get("paths", {}).values():
        for method, operation in operations.items():
            responses = operation.setdefault("responses", {})
            codes = ["422"] if "422" in responses else []
            if method in COMMAND_METHODS:
                operation["security"] = [{BEARER: []}]
                codes += ["401", "403", "423"] + (["400"] if "requestBody" in operation else [])
            for code in codes:
                responses[code] = dict(error, description=ERRORS[int(code)])
    return schema


def install(app: FastAPI) -> None:
    """Serve the completed schema at /openapi.json (built once, on the first request)."""

    def openapi() -> dict:
        if app.openapi_schema is None:
            complete(FastAPI.openapi(app))  # FastAPI keeps what it built in app.openapi_schema
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]


class MethodGate:
    """The methods each path of the schema documents (read on first use, once every route is added)."""

    def __init__(self, app: FastAPI):
        self.app = app
        self._paths: list[tuple[re.Pattern, set[str]]] | None = None

    def allowed(self, path: str) -> list[str]:
        if self._paths is None:
            self._paths = [(re.compile("^" + re.sub(r"\\{\w+\\}", "[^/]+", re.escape(template)) + "$"),
                            {method.upper() for method in operations})
                           for template, operations in self.app.openapi()["paths"].items()]
        return sorted({m for pattern, methods in self._paths if pattern.match(path) for m in methods})

    def answer(self, request: Request) -> Response | None:
        """OPTIONS and an undocumented method of a documented path are answered here; None: route it."""
        path, method = request.scope["path"], request.method
        allowed = self.allowed(path)
        if not allowed or method in allowed:
            return None  # not ours (the console, a 404) or a route's
        allow = {"Allow": ", ".join(allowed)}
        if method == "OPTIONS":
            return Response(status_code=204, headers=allow)
        return JSONResponse({"detail": f"{path} has no method {method}; it has {', '.join(allowed)}"},
                            status_code=405, headers=allow)
