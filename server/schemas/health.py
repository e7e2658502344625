from __future__ import annotations

from pydantic import BaseModel


class HealthOut(BaseModel):
    status: str
    version: str
    database: str
    workers_alive: int
    capabilities: dict[str, str | None]  # name -> null when available, else why not
