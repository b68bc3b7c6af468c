"""Error answers: one body shape for every 4xx, documented on every route.

Every error the API gives is `{"detail": "<one line naming the field or record and the
problem>"}`; validation errors add `errors` (FastAPI's list) and conflicts may add `current`
(the record as it is now, so the client can merge and retry).
"""

from __future__ import annotations

from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel

from app.core.errors import MmscleanError, StaleWriteError


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
    503: "a dependency (model weights, database) is missing",
}


def errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    """`responses=` for a route or router: the listed error codes with the ErrorBody schema."""
    return {code: {"model": ErrorBody, "description": WHAT[code]} for code in codes}


def field_name(loc: tuple | list) -> str:
    """('body', 'labels', 3, 'label') -> 'labels[3].label' (the part a user wrote)."""
    parts = [p for p in loc if p not in ("body", "query", "path", "header", "cookie")]
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
