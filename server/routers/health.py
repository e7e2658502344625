"""``/health``: liveness and readiness without an API key (``server/services/status.py``)."""

from __future__ import annotations

from fastapi import APIRouter

from csa_core import __version__
from server import capabilities
from server.deps import DbDep, ServicesDep
from server.schemas.health import HealthOut
from server.services import status

router = APIRouter(tags=["health"])


@router.get("/health", response_model=HealthOut, summary="service health (no API key needed)")
def health(db: DbDep, services: ServicesDep) -> HealthOut:
    try:
        status.check_database(db)
        database = "ok"
        alive = status.workers_alive(db, services.settings)
    except Exception as e:  # noqa: BLE001 - health reports, it does not fail
        database, alive = f"error: {type(e).__name__}", 0
    return HealthOut(
        status="ok" if database == "ok" else "degraded",
        version=__version__,
        database=database,
        workers_alive=int(alive),
        capabilities=capabilities.report(),
    )
