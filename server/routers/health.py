"""``/health``: liveness and readiness without an API key."""

from __future__ import annotations

import datetime as dt

from fastapi import APIRouter
from sqlalchemy import func, select, text

from csa_core import __version__
from server import capabilities
from server.db.models import Worker, utcnow
from server.deps import DbDep, ServicesDep
from server.schemas.health import HealthOut

router = APIRouter(tags=["health"])


@router.get("/health", response_model=HealthOut, summary="service health (no API key needed)")
def health(db: DbDep, services: ServicesDep) -> HealthOut:
    try:
        db.execute(text("SELECT 1"))
        database = "ok"
        horizon = utcnow() - dt.timedelta(seconds=3 * services.settings.heartbeat_seconds + services.settings.worker_poll_seconds + 5)
        alive = db.scalar(select(func.count(Worker.id)).where(Worker.stopped_at.is_(None), Worker.heartbeat_at >= horizon)) or 0
    except Exception as e:  # noqa: BLE001 - health reports, it does not fail
        database, alive = f"error: {type(e).__name__}", 0
    return HealthOut(
        status="ok" if database == "ok" else "degraded",
        version=__version__,
        database=database,
        workers_alive=int(alive),
        capabilities=capabilities.report(),
    )
