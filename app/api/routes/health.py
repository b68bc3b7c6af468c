"""`/health`: 200 once the database is reachable, 503 otherwise. A data directory's disk with
less than `min_free_mb` free is `degraded`, still 200: reads and logins go on, writes answer
507 (a load balancer should keep the server, an operator should free space)."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse

from app import __version__
from app.api.errors import errors
from app.store.db import ping

router = APIRouter(tags=["health"])


@router.get("/health", responses=errors(503))
def health(request: Request) -> JSONResponse:
    """200 with the version and the disk's free space once the database answers (`status`
    `degraded` with a `detail` when the disk is below MMSCLEAN_MIN_FREE_MB); 503 naming the
    problem otherwise."""
    engine = request.app.state.engine
    try:
        ping(engine)
    except Exception as exc:  # the probe reports, it does not crash
        return JSONResponse({"status": "unavailable", "detail": str(exc)}, status_code=503)
    body = {"status": "ok", "version": __version__}
    disk = request.app.state.disk_space
    free = disk.free_mb()
    body["disk_free_mb"] = round(free, 1)
    if free < disk.min_free_mb:
        body["status"] = "degraded"
        body["detail"] = (
            f"the data directory's disk is full ({free:.0f} MB free, MMSCLEAN_MIN_FREE_MB is "
            f"{disk.min_free_mb:g}): writes answer 507, reads work"
        )
    return JSONResponse(body)
