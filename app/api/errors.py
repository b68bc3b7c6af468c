"""Error answers: one body shape for every 4xx, documented on every route.

Every error the API gives is `{"detail": "<one line naming the field or record and the
problem>"}`; validation errors add `errors` (FastAPI's list) and conflicts may add `current`
(the record as it is now, so the client can merge and retry).
"""

from __future__ import annotations

import errno
import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel

from app.api.disk_space import WORKS_ON_FULL_DISK, WRITE_METHODS, DiskSpace, is_disk_full
from app.core.errors import MmscleanError, StaleWriteError

log = logging.getLogger(__name__)


class ErrorBody(BaseModel):
    detail: str
    errors: list[dict[str, Any]] | None = None
    current: Any | None = None


WHAT = {
    400: "bad request (e.g. a path outside the data root)",
    401: "not logged in, or the token expired",
    403: "the user's role does not allow this",
    404: "no record with this id",
    409: "stale version or duplicate; `current` holds the record as it is now",
    413: "upload larger than the configured limit",
    422: "invalid payload or file; `detail` names the field or file",
    429: "too many failed logins; `Retry-After` says how many seconds to wait",
    503: "a dependency (model weights, database) is missing",
    507: "the data directory's disk is full; reads still work",
}


def errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    """`responses=` for a route or router: the listed error codes with the ErrorBody schema."""
    return {code: {"model": ErrorBody, "description": WHAT[code]} for code in codes}


def field_name(loc: tuple | list) -> str:
    """('body', 'labels', 3, 'label') -> 'labels[3].label' (the part a user wrote)."""
    where = ("body", "query", "path", "header", "cookie")
    parts = list(loc[1:]) if loc and loc[0] in where else list(loc)  # a field may be `path`
    name = ""
    for part in parts:
        name += f"[{part}]" if isinstance(part, int) else (f".{part}" if name else str(part))
    return name or ".".join(str(p) for p in loc)


def install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(MmscleanError)
    async def user_error(_: Request, exc: MmscleanError) -> JSONResponse:
        body: dict[str, Any] = {"detail": exc.message}
        if isinstance(exc, StaleWriteError):
            body["current"] = exc.current
        return JSONResponse(body, status_code=exc.http_status)

    @app.exception_handler(RequestValidationError)
    async def invalid_payload(_: Request, exc: RequestValidationError) -> JSONResponse:
        problems = exc.errors()
        first = problems[0] if problems else {"loc": (), "msg": "invalid request"}
        detail = f"{field_name(first.get('loc', ()))}: {first.get('msg')}"
        if len(problems) > 1:
            detail += f" (and {len(problems) - 1} more)"
        plain = [
            {"loc": list(p.get("loc", ())), "msg": p.get("msg"), "type": p.get("type")}
            for p in problems
        ]
        return JSONResponse({"detail": detail, "errors": plain}, status_code=422)

    app.add_middleware(UnhandledErrors)


def document_disk_full(app: FastAPI) -> None:
    """List the 507 answer on every operation the full-disk check guards (an app-wide
    dependency, so it is added to the generated schema rather than to each route)."""
    build = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema:
            return app.openapi_schema
        schema = build()
        body = {"$ref": "#/components/schemas/ErrorBody"}
        answer = {"description": WHAT[507], "content": {"application/json": {"schema": body}}}
        for path, item in schema["paths"].items():
            for method, operation in item.items():
                key = (method.upper(), path)
                if key[0] in WRITE_METHODS and key not in WORKS_ON_FULL_DISK:
                    operation["responses"].setdefault("507", answer)
        return schema

    app.openapi = openapi


def unhandled_answer(scope: dict, exc: Exception) -> tuple[int, dict[str, str]]:
    """The answer to an error no route handled: 507 for a full disk, 422 for a name the file
    system refuses, else a generic 500 (the traceback goes to the log, never to the client)."""
    if is_disk_full(exc):
        disk: DiskSpace | None = getattr(scope["app"].state, "disk_space", None)
        if disk is not None:
            return 507, {"detail": disk.error().message}
        return 507, {"detail": "the data directory's disk is full"}
    if isinstance(exc, OSError) and exc.errno == errno.ENAMETOOLONG:
        return 422, {"detail": "a name in the request is too long for the file system"}
    return 500, {"detail": "internal error: the server logged the details"}


class UnhandledErrors:
    """Outermost guard below Starlette's: any exception a route or a background task lets out
    is logged with its traceback and answered in the API's JSON shape, and the connection stays
    usable (Starlette's own handler re-raises, so the server drops the keep-alive connection)."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        state = {"started": False, "complete": False}

        async def tracked(message) -> None:
            if message["type"] == "http.response.start":
                state["started"] = True
            elif message["type"] == "http.response.body" and not message.get("more_body"):
                state["complete"] = True
            await send(message)

        try:
            await self.app(scope, receive, tracked)
        except Exception as exc:
            status, body = unhandled_answer(scope, exc)
            where = f"{scope.get('method')} {scope.get('path')}"
            if status == 500:
                log.exception("unhandled error in %s", where)
            else:
                cause = (str(exc).splitlines() or [""])[0][:200]  # SQL errors run to megabytes
                log.warning("%s: %s (%s: %s)", where, body["detail"], type(exc).__name__, cause)
            if state["complete"]:
                return  # a background task after the answer: logged, nothing left to send
            if state["started"]:
                raise  # half an answer went out: only closing the connection can end it
            await JSONResponse(body, status_code=status)(scope, receive, send)
