"""Every setting of the service, read once from the environment (prefix ``CSA_``) or a .env file."""

from __future__ import annotations

import os
from functools import cached_property
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

MiB = 1024 * 1024
GiB = 1024 * MiB


def available_cores() -> int:
    """The CPU cores this process may run on (its affinity where the platform tells)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


class Settings(BaseSettings):
    """Service configuration. ``CSA_DATA_DIR`` holds the SQLite database, the artifact store,
    job scratch space and the generated API key, unless the individual paths are given."""

    model_config = SettingsConfigDict(env_prefix="CSA_", env_file=".env", extra="ignore")

    data_dir: Path = Path("csa-data")
    database_url: str | None = None  # default: sqlite file in data_dir; any SQLAlchemy URL works
    artifact_dir: Path | None = None  # default: data_dir/artifacts
    work_dir: Path | None = None  # default: data_dir/work (job scratch, removed after each job)

    # Authentication: requests need one of these keys in X-API-Key or "Authorization: Bearer".
    # With none configured, a random key is generated once and kept in data_dir/api_key.
    api_keys: Annotated[list[str], NoDecode] = Field(default_factory=list)
    public_docs: bool = True  # serve /docs and /openapi.json without a key (they hold no data)

    # Upload limits (bytes and counts), checked before anything is stored.
    max_frame_upload_bytes: int = 64 * MiB
    max_archive_bytes: int = 1024 * MiB
    max_archive_members: int = 20_000
    max_archive_unpacked_bytes: int = 4096 * MiB
    max_archive_member_bytes: int = 256 * MiB
    max_archive_ratio: float = 200.0  # zip: uncompressed / compressed size per member
    max_image_pixels: int = 4096 * 4096
    max_model_upload_bytes: int = 1024 * MiB
    max_inference_upload_bytes: int = 32 * MiB
    orphan_blob_grace_seconds: float = (
        3600.0  # unrecorded blob files older than this are deleted by the background sweep
    )
    orphan_sweep_interval_seconds: float = (
        3600.0  # background sweep: at start, then this often (0: at start only)
    )

    # Quotas per key (docs/operations.md "Quotas"; server/quotas.py); 0 turns one off. Admin
    # keys, the settings' keys among them, have none.
    quota_requests_per_second: float = Field(20.0, ge=0)  # per key and API process, sustained
    quota_request_burst: int = Field(200, ge=1)  # requests a key may send at once after a pause
    quota_stored_bytes_device: int = Field(50 * GiB, ge=0)  # its scenes' frames
    quota_stored_bytes_operator: int = Field(500 * GiB, ge=0)  # its scenes' frames, checkpoints
    quota_queued_jobs_operator: int = Field(100, ge=0)  # queued jobs when an operator key queues

    # Jobs: where they run (docs/architecture.md, "Executors").
    executor: Literal["embedded", "ray"] = (
        "embedded"  # embedded: in this process; ray: on a Ray cluster
    )
    embedded_worker: bool = (
        True  # run jobs from this process (false: API only, jobs wait in the queue)
    )
    ray_address: str = (
        "local"  # a running cluster (host:port, "auto"), or "local": start one in this process
    )
    ray_num_cpus: int | None = None  # CPUs of the "local" cluster (default: all of this machine's)
    ray_cpus_per_job: float = 1.0  # CPUs each job's task asks for (and its torch threads)
    ray_max_running_jobs: int | None = (
        None  # jobs handed to the cluster at once (default: its GPUs, else CPUs / per job)
    )
    ray_cancel_grace_seconds: float = 30.0  # a cancelled task still running after this is killed
    worker_poll_seconds: float = 1.0
    lease_seconds: float = (
        30.0  # a running job whose lease is this old belongs to a dead API process
    )
    heartbeat_seconds: float = 5.0
    max_attempts: int = (
        2  # a job whose process (or Ray worker) died this many times fails instead of re-queueing
    )
    job_log_lines: int = 2000  # log lines kept per job

    # Server-sent events of job progress.
    sse_poll_seconds: float = 0.5
    sse_max_seconds: float = 3600.0  # a stream ends after this long; clients reconnect

    # Database connections per API process (docs/operations.md "Database connections"): the
    # pool holds db_pool_size, opens up to db_max_overflow more under load, and a request that
    # waits db_pool_timeout seconds for one is answered 503 database_busy. The default total
    # (40) matches the thread pool that runs the routes, so a connection is there for each.
    db_pool_size: int = Field(10, ge=1)
    db_max_overflow: int = Field(30, ge=0)
    db_pool_timeout: float = Field(10.0, gt=0)

    migrate_on_start: bool = True
    device: str = "auto"  # torch device for jobs and inference: auto (CUDA when present), cpu, cuda
    torch_threads: int | None = None  # torch.set_num_threads for jobs and inference
    model_cache_size: int = (
        2  # segmentation networks kept loaded for inference (and NeRFs for renders)
    )

    # Renders (POST /api/v1/scenes/{scene}/render, the dashboard's pseudo-label panels;
    # docs/operations.md "Rendering"; server/nerf_cache.py): this many at once per API process,
    # each on torch_threads (default: the cores) / this many threads.
    render_concurrency: int | None = Field(None, ge=1)  # default: half the cores, 1 to 4
    render_queue_seconds: float = Field(
        30.0, ge=0
    )  # a render that waits longer for its turn: 503 with Retry-After

    @field_validator("api_keys", mode="before")
    @classmethod
    def _split_keys(cls, v: object) -> object:
        if isinstance(v, str):
            return [k.strip() for k in v.split(",") if k.strip()]
        return v

    @cached_property
    def resolved_database_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'csa.db').resolve()}"

    @cached_property
    def resolved_artifact_dir(self) -> Path:
        return (self.artifact_dir or self.data_dir / "artifacts").resolve()

    @cached_property
    def resolved_work_dir(self) -> Path:
        return (self.work_dir or self.data_dir / "work").resolve()

    @property
    def resolved_render_concurrency(self) -> int:
        """Renders at once: by default half the cores (1 to 4), so that renders, which take
        seconds of CPU each, leave the other half to predictions, uploads and listings."""
        return self.render_concurrency or max(1, min(4, available_cores() // 2))

    @property
    def render_threads(self) -> int:
        """Torch threads of each render: the renders together use half of ``torch_threads``
        (default: the cores), each at least one."""
        threads = (self.torch_threads or available_cores()) // 2
        return max(1, threads // self.resolved_render_concurrency)
