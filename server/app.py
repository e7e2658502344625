"""The FastAPI application factory.

``create_app()`` reads :class:`Settings` from the environment; tests and ``csa serve`` pass
their own. The app opens the database (migrating it), the artifact store and, unless
``CSA_EMBEDDED_WORKER=false``, the executor that runs queued jobs (``CSA_EXECUTOR``: in this
process, or on a Ray cluster; ``server/executors``).
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import Depends, FastAPI

from csa_core import __version__
from server import ui
from server.artifacts import OrphanSweeper
from server.audit import AuditMiddleware
from server.auth import require_api_key, resolve_api_keys
from server.errors import install_error_handlers
from server.executors import make_executor
from server.model_cache import ModelCache
from server.nerf_cache import NerfCache
from server.quotas import QUOTA_RESPONSES, RequestRate, RequestRateQuota
from server.request_metrics import RequestMetricsMiddleware, RequestStats, RouteTemplates
from server.routers import (
    admin,
    continual,
    frames,
    health,
    inference,
    jobs,
    memory,
    models,
    prometheus,
    rendering,
    scenes,
)
from server.services import open_services
from server.settings import Settings
from server.ui.session import require_ui_session
from server.upload_limits import BodyLimitMiddleware

API_PREFIX = "/api/v1"
UI_API_PREFIX = "/ui" + API_PREFIX

DESCRIPTION = """
Continual semantic adaptation as a service: upload posed RGB-D frames of the scenes a robot
visits, fit a Semantic-NeRF per scene (the memory bank), adapt the segmentation network
without labels, and serve inference and rendering.

Every route but `/health` needs an API key: `X-API-Key: KEY` or `Authorization: Bearer KEY`.
Keys carry a scope: `device` (its own scenes, their frames, predictions), `operator` (every
scene, jobs, models, the memory bank, renders, metrics) or `admin` (everything, keys and the
audit log); a key below a route's scope is answered 403 naming the scope needed.
Errors are `{"error": {"code", "message", "field"}}`.
"""


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()
    stats = RequestStats()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        services = open_services(settings)
        services.set_settings_keys(resolve_api_keys(settings), generated=not settings.api_keys)
        app.state.services = services
        device = None if settings.device == "auto" else settings.device
        app.state.model_cache = ModelCache(services.store, settings.model_cache_size, device)
        app.state.nerf_cache = NerfCache(
            services.store,
            settings.model_cache_size,
            device,
            concurrency=settings.resolved_render_concurrency,
            queue_seconds=settings.render_queue_seconds,
            threads=settings.render_threads,
        )
        worker = None
        if settings.embedded_worker:
            worker = make_executor(services)
            worker.start()
        app.state.worker = worker
        sweeper = OrphanSweeper(
            services.store,
            services.sessions,
            settings.orphan_blob_grace_seconds,
            settings.orphan_sweep_interval_seconds,
        )
        sweeper.start()
        app.state.orphan_sweeper = sweeper
        try:
            yield
        finally:
            if worker is not None:
                worker.stop(timeout=60)
            sweeper.stop()
            app.state.nerf_cache.close()
            services.close()

    app = FastAPI(
        title="CSA: continual semantic adaptation",
        version=__version__,
        description=DESCRIPTION,
        lifespan=lifespan,
        docs_url="/docs" if settings.public_docs else None,
        redoc_url=None,
        openapi_url="/openapi.json" if settings.public_docs else None,
    )
    app.state.request_stats = stats
    install_error_handlers(app)
    app.add_middleware(AuditMiddleware)
    app.add_middleware(BodyLimitMiddleware, settings=settings)
    templates = RouteTemplates(lambda: [*app.openapi()["paths"], "/docs", "/openapi.json"])
    app.add_middleware(RequestMetricsMiddleware, stats=stats, templates=templates)

    app.include_router(health.router)
    app.state.request_rate = RequestRate.from_settings(settings)  # per key (server/quotas.py)
    secured = [Depends(require_api_key), RequestRateQuota]
    app.include_router(prometheus.router, dependencies=secured, responses=QUOTA_RESPONSES)
    rest = (scenes, frames, jobs, models, memory, continual, inference, rendering, admin)
    for module in rest:
        app.include_router(
            module.router, prefix=API_PREFIX, dependencies=secured, responses=QUOTA_RESPONSES
        )
    # The same REST API for the dashboard's scripts, with its session cookie and CSRF checks
    # instead of a key header (server/ui/session.py), hidden from the OpenAPI document.
    for module in rest:
        app.include_router(
            module.router,
            prefix=UI_API_PREFIX,
            dependencies=[Depends(require_ui_session)],
            include_in_schema=False,
        )
    app.include_router(ui.router)  # the dashboard at /ui: its own session auth (server/ui)
    # FastAPI makes the routes' validation models (parameters, bodies, answers) on first use,
    # and each under a process-wide warnings filter that hides pydantic's warning about the
    # aliases FastAPI gives parameters (``after``, ``limit``, ...). At the first request that
    # would be in a server thread, where another thread restoring its own warnings filters
    # meanwhile undoes that one and lets the warning out. Writing the OpenAPI document now
    # makes every route's models, in the thread that makes the app, before it serves anything.
    app.openapi()
    return app
