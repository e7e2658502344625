"""``/metrics``: Prometheus text exposition (requests, jobs, stored data, workers)."""

from __future__ import annotations

import time

from fastapi import APIRouter, Request
from fastapi.responses import PlainTextResponse

from server.auth import OperatorScope
from server.deps import DbDep, ServicesDep
from server.jobs.queue import STATUSES
from server.request_metrics import BUCKETS, RequestStats
from server.schemas.common import ERROR_RESPONSES
from server.services import status

router = APIRouter(
    tags=["metrics"],
    responses={401: ERROR_RESPONSES[401], 403: ERROR_RESPONSES[403]},
    dependencies=[OperatorScope],
)


def _esc(v: str) -> str:
    return v.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")


def _labels(**kv: str) -> str:
    return "{" + ",".join(f'{k}="{_esc(str(v))}"' for k, v in kv.items()) + "}"


@router.get(
    "/metrics", response_class=PlainTextResponse, summary="Prometheus metrics (text format 0.0.4)"
)
def metrics(request: Request, db: DbDep, services: ServicesDep) -> PlainTextResponse:
    stats: RequestStats = request.app.state.request_stats
    counts, lsum, lcount, lbuckets = stats.snapshot()
    out: list[str] = []

    def head(name: str, kind: str, help_: str) -> None:
        out.append(f"# HELP {name} {help_}")
        out.append(f"# TYPE {name} {kind}")

    head("csa_http_requests_total", "counter", "HTTP requests by method, route and status.")
    for (method, route, code), n in sorted(counts.items()):
        out.append(f"csa_http_requests_total{_labels(method=method, route=route, status=code)} {n}")
    head("csa_http_request_duration_seconds", "histogram", "HTTP request latency.")
    name = "csa_http_request_duration_seconds"
    for (method, route), buckets in sorted(lbuckets.items()):
        for bound, n in zip(BUCKETS, buckets, strict=True):
            out.append(f"{name}_bucket{_labels(method=method, route=route, le=str(bound))} {n}")
        count = lcount[(method, route)]
        out.append(f"{name}_bucket{_labels(method=method, route=route, le='+Inf')} {count}")
        out.append(f"{name}_sum{_labels(method=method, route=route)} {lsum[(method, route)]:.6f}")
        out.append(f"{name}_count{_labels(method=method, route=route)} {count}")

    head("csa_jobs", "gauge", "Jobs by kind and status.")
    by = status.job_counts(db)
    kinds = sorted({k for k, _ in by}) or []
    for kind in kinds:
        for job_status in STATUSES:
            n = by.get((kind, job_status), 0)
            out.append(f"csa_jobs{_labels(kind=kind, status=job_status)} {n}")

    def gauge(name: str, help_: str, value: float) -> None:
        head(name, "gauge", help_)
        out.append(f"{name} {value}")

    stored = status.stored(db)
    gauge("csa_scenes", "Stored scenes.", stored.scenes)
    gauge("csa_frames", "Stored frames.", stored.frames)
    gauge("csa_model_versions", "Model versions in the registry.", stored.model_versions)
    gauge(
        "csa_memory_bank_bytes", "Bytes of the active NeRF checkpoints.", stored.memory_bank_bytes
    )
    gauge(
        "csa_memory_bank_scenes",
        "Scenes with a NeRF in the memory bank.",
        stored.memory_bank_scenes,
    )
    gauge("csa_artifact_bytes", "Bytes in the artifact store.", stored.artifact_bytes)
    alive = status.workers_alive(db, services.settings)
    gauge("csa_workers_alive", "Workers with a recent heartbeat.", alive)
    uptime = round(time.time() - stats.started, 3)
    gauge("csa_uptime_seconds", "Seconds since the API started.", uptime)
    return PlainTextResponse(
        "\n".join(out) + "\n", media_type="text/plain; version=0.0.4; charset=utf-8"
    )
