"""`/health`: answers 200 once the database is reachable, 503 otherwise."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse
from sqlalchemy import text

from app import __version__
from app.api.errors import errors

router = APIRouter(tags=["health"])


@router.get("/health", responses=errors(503))
def health(request: Request) -> JSONResponse:
    """200 with the version once the database answers; 503 naming the problem otherwise."""
    engine = request.app.state.engine
    try:
        with engine.connect() as conn:
            conn.execute(text("SELECT 1"))
    except Exception as exc:  # the probe reports, it does not crash
        return JSONResponse({"status": "unavailable", "detail": str(exc)}, status_code=503)
    return JSONResponse({"status": "ok", "version": __version__})
