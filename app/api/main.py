"""Application factory: settings -> private data dir -> database (migrated) -> first admin ->
sample survey -> routers -> error handlers; secrets redacted from the logs."""

from __future__ import annotations

import logging
from contextlib import asynccontextmanager

from fastapi import Depends, FastAPI
from sqlmodel import Session

from app import __version__
from app.api.disk_space import DiskSpace, refuse_writes_on_full_disk
from app.api.errors import document_disk_full, install_error_handlers
from app.api.orphans import remove_orphans
from app.api.routes import (
    areas,
    auth,
    clutter,
    dashboard,
    exports,
    guardrails,
    health,
    jobs,
    models,
    pillars,
    surveys,
    users,
    viewer,
    vocabulary,
)
from app.api.sample import load_sample_on_first_start
from app.core.logging import install_redaction
from app.core.security import TokenSigner
from app.core.settings import Settings, get_settings
from app.jobs.pool import WorkerPool
from app.jobs.retraining import RetrainingTrigger
from app.store.db import init_db, make_engine, secure_dir
from app.store.users import ensure_first_admin
from app.viewer.server import ViewerServer

log = logging.getLogger(__name__)


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or get_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        install_redaction()  # again: the server configured its loggers since create_app
        secure_dir(settings.data_dir)  # password hashes, the token key, surveys: owner only
        engine = make_engine(settings.database_url)
        init_db(engine)
        remove_orphans(engine, settings)  # before anything of this server writes files
        with Session(engine) as session:
            if ensure_first_admin(session, settings.admin_password) is not None:
                log.info("created the user 'admin' from MMSCLEAN_ADMIN_PASSWORD")
        load_sample_on_first_start(engine, settings.sample_dir)
        app.state.engine = engine
        app.state.token_signer = TokenSigner.for_data_dir(settings.data_dir)
        app.state.worker_pool = WorkerPool(settings, engine).start()  # after init_db
        app.state.retraining_trigger = RetrainingTrigger(engine, settings)
        app.state.viewer = ViewerServer(settings, engine).start()  # viser on 127.0.0.1 only
        yield
        app.state.viewer.stop()
        app.state.worker_pool.stop()
        engine.dispose()

    app = FastAPI(
        title="mmsclean",
        version=__version__,
        lifespan=lifespan,
        description="Cleaning mobile-mapping point clouds: jobs, labels, review and export.",
        dependencies=[Depends(refuse_writes_on_full_disk)],
    )
    app.state.settings = settings
    install_redaction()
    app.state.disk_space = DiskSpace(settings.data_dir, settings.min_free_mb)
    install_error_handlers(app)
    for module in (health, auth, users, surveys, jobs, pillars, clutter, guardrails, models):
        app.include_router(module.router)
    app.include_router(areas.router)
    app.include_router(vocabulary.router)
    app.include_router(exports.router)
    app.include_router(viewer.router)
    app.include_router(dashboard.router)
    document_disk_full(app)
    return app
