"""Application factory: settings -> database (migrated) -> routers -> error handlers."""

from __future__ import annotations

from contextlib import asynccontextmanager

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse

from app import __version__
from app.api.routes import health
from app.api.sample import load_sample_on_first_start
from app.core.errors import MmscleanError
from app.core.settings import Settings, get_settings
from app.store.db import init_db, make_engine


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or get_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        engine = make_engine(settings.database_url)
        init_db(engine)
        load_sample_on_first_start(engine, settings.sample_dir)
        app.state.engine = engine
        yield
        engine.dispose()

    app = FastAPI(title="mmsclean", version=__version__, lifespan=lifespan)
    app.state.settings = settings

    @app.exception_handler(MmscleanError)
    async def user_error(_: Request, exc: MmscleanError) -> JSONResponse:
        return JSONResponse({"detail": exc.message}, status_code=exc.http_status)

    app.include_router(health.router)
    return app
