"""``/metrics``: Prometheus text exposition (requests, jobs, stored data, workers)."""

from __future__ import annotations

import datetime as dt
import time

from fastapi import APIRouter, Request
from fastapi.responses import PlainTextResponse
from sqlalchemy import func, select

from server.auth import OperatorScope
from server.db.models import (
    Artifact,
    Frame,
    Job,
    ModelVersion,
    NerfCheckpoint,
    Scene,
    Worker,
    utcnow,
)
from server.deps import DbDep, ServicesDep
from server.jobs.queue import STATUSES
from server.request_metrics import BUCKETS, RequestStats
from server.schemas.common import ERROR_RESPONSES

router = APIRouter(tags=["metrics"], responses={401: ERROR_RESPONSES[401], 403: ERROR_RESPONSES[403]}, dependencies=[OperatorScope])


def _esc(v: str) -> str:
    return v.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")


def _labels(**kv: str) -> str:
    return "{" + ",".join(f'{k}="{_esc(str(v))}"' for k, v in kv.items()) + "}"


@router.get("/metrics", response_class=PlainTextResponse, summary="Prometheus metrics (text format 0.0.4)")
def metrics(request: Request, db: DbDep, services: ServicesDep) -> PlainTextResponse:
    stats: RequestStats = request.app.state.request_stats
    counts, lsum, lcount, lbuckets = stats.snapshot()
    out: list[str] = []

    def head(name: str, kind: str, help_: str) -> None:
        out.append(f"# HELP {name} {help_}")
        out.append(f"# TYPE {name} {kind}")

    head("csa_http_requests_total", "counter", "HTTP requests by method, route and status.")
    for (method, route, status), n in sorted(counts.items()):
        out.append(f"csa_http_requests_total{_labels(method=method, route=route, status=status)} {n}")
    head("csa_http_request_duration_seconds", "histogram", "HTTP request latency.")
    for (method, route), buckets in sorted(lbuckets.items()):
        for bound, n in zip(BUCKETS, buckets, strict=True):
            out.append(f"csa_http_request_duration_seconds_bucket{_labels(method=method, route=route, le=str(bound))} {n}")
        out.append(f"csa_http_request_duration_seconds_bucket{_labels(method=method, route=route, le='+Inf')} {lcount[(method, route)]}")
        out.append(f"csa_http_request_duration_seconds_sum{_labels(method=method, route=route)} {lsum[(method, route)]:.6f}")
        out.append(f"csa_http_request_duration_seconds_count{_labels(method=method, route=route)} {lcount[(method, route)]}")

    head("csa_jobs", "gauge", "Jobs by kind and status.")
    by = {(k, s): n for k, s, n in db.execute(select(Job.kind, Job.status, func.count(Job.id)).group_by(Job.kind, Job.status))}
    kinds = sorted({k for k, _ in by}) or []
    for kind in kinds:
        for status in STATUSES:
            out.append(f"csa_jobs{_labels(kind=kind, status=status)} {by.get((kind, status), 0)}")

    def gauge(name: str, help_: str, value: float) -> None:
        head(name, "gauge", help_)
        out.append(f"{name} {value}")

    gauge("csa_scenes", "Stored scenes.", db.scalar(select(func.count(Scene.id))) or 0)
    gauge("csa_frames", "Stored frames.", db.scalar(select(func.count(Frame.id))) or 0)
    gauge("csa_model_versions", "Model versions in the registry.", db.scalar(select(func.count(ModelVersion.id))) or 0)
    gauge("csa_memory_bank_bytes", "Bytes of the active NeRF checkpoints.", db.scalar(select(func.coalesce(func.sum(NerfCheckpoint.size_bytes), 0)).where(NerfCheckpoint.active.is_(True))) or 0)
    gauge("csa_memory_bank_scenes", "Scenes with a NeRF in the memory bank.", db.scalar(select(func.count(func.distinct(NerfCheckpoint.scene_id))).where(NerfCheckpoint.active.is_(True))) or 0)
    gauge("csa_artifact_bytes", "Bytes in the artifact store.", db.scalar(select(func.coalesce(func.sum(Artifact.size_bytes), 0))) or 0)
    horizon = utcnow() - dt.timedelta(seconds=3 * services.settings.heartbeat_seconds + services.settings.worker_poll_seconds + 5)
    gauge("csa_workers_alive", "Workers with a recent heartbeat.", db.scalar(select(func.count(Worker.id)).where(Worker.stopped_at.is_(None), Worker.heartbeat_at >= horizon)) or 0)
    gauge("csa_uptime_seconds", "Seconds since the API started.", round(time.time() - stats.started, 3))
    return PlainTextResponse("\n".join(out) + "\n", media_type="text/plain; version=0.0.4; charset=utf-8")

