"""Quotas per API key (docs/operations.md "Quotas"): a request rate, stored bytes, queued jobs.

- **Request rate.** A token bucket per key name in each API process (memory only: a restart
  or a second replica starts full). A request takes a token; an empty bucket is answered 429
  with ``Retry-After`` (whole seconds until the next token) and a message naming the quota and
  the key. Checked right after authentication (``check_request_rate``, hooked in
  ``server/app.py``), so it covers every ``/api/v1`` route and ``/metrics``.
- **Stored bytes.** Counted from the database on every upload, so a restart keeps the count:
  the stored files of the frames of the scenes a key owns (``scenes.owner_key_id``: frame and
  archive uploads to a scene count against the key that made it, the only key of device scope
  that can upload to it), plus the checkpoints the key registered (``model_versions.meta``'s
  ``uploaded_by_key_id``). An upload that would go over is answered 413 naming the quota and
  the key before anything is written to the store. The check is not one transaction with the
  write: concurrent uploads of one key may overshoot by their own sizes.
- **Queued jobs.** A key of scope operator may queue a job while fewer than
  ``quota_queued_jobs_operator`` jobs wait in the queue (all keys' jobs: jobs do not record who
  queued them); 429 naming the limit otherwise. Device keys cannot queue jobs at all.

Admin keys, the settings' keys (``CSA_API_KEYS`` and the generated one) among them, have no
quotas: they are the operator's own and must stay able to revoke keys and cancel jobs while
other keys are held back. A quota set to 0 is off.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Request
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from server.auth import current_principal, require_api_key
from server.db.models import ApiKey, Artifact, Frame, Job, ModelVersion, Scene
from server.deps import DbDep
from server.errors import APIError
from server.jobs.queue import QUEUED
from server.keys import ADMIN, DEVICE, OPERATOR, Principal
from server.schemas.common import ErrorBody
from server.settings import Settings

QUOTA_EXCEEDED = "quota_exceeded"
UPLOADER_META = "uploaded_by_key_id"  # model_versions.meta: the key that registered a checkpoint
# The answer of a request over a key's rate, or of a job over the queued-jobs quota (OpenAPI).
QUOTA_RESPONSES: dict[int | str, dict] = {
    429: {"model": ErrorBody, "description": "over a quota of the key (`Retry-After` for the rate)"}
}


def exempt(principal: Principal) -> bool:
    """Admin keys (the settings' keys are admin keys) have no quotas."""
    return principal.allows(ADMIN)


# -- request rate ----------------------------------------------------------------------------


@dataclass
class _Bucket:
    tokens: float
    at: float  # clock time of ``tokens``


class RequestRate:
    """Token buckets per key name: ``burst`` tokens at most, refilled at ``per_second``.
    Thread-safe (sync routes' dependencies run in a thread pool); ``clock`` is for tests."""

    def __init__(self, per_second: float, burst: int, clock: Callable[[], float] = time.monotonic):
        self.per_second = per_second
        self.burst = max(1, burst)
        self.clock = clock
        self._buckets: dict[str, _Bucket] = {}
        self._lock = threading.Lock()

    @classmethod
    def from_settings(cls, settings: Settings) -> RequestRate:
        return cls(settings.quota_requests_per_second, settings.quota_request_burst)

    @property
    def enabled(self) -> bool:
        return self.per_second > 0

    def take(self, name: str) -> float:
        """Take a token of ``name``'s bucket: 0.0 when there was one, else the seconds until
        there is one (nothing is taken then)."""
        now = self.clock()
        with self._lock:
            bucket = self._buckets.get(name)
            if bucket is None:
                bucket = self._buckets[name] = _Bucket(float(self.burst), now)
            refill = max(0.0, now - bucket.at) * self.per_second
            bucket.tokens, bucket.at = min(float(self.burst), bucket.tokens + refill), now
            if bucket.tokens >= 1.0:
                bucket.tokens -= 1.0
                return 0.0
            return (1.0 - bucket.tokens) / self.per_second


def check_request_rate(
    request: Request, principal: Annotated[Principal, Depends(require_api_key)]
) -> None:
    """Dependency after authentication: 429 with ``Retry-After`` when the key's bucket is empty."""
    rate: RequestRate | None = getattr(request.app.state, "request_rate", None)
    if rate is None or not rate.enabled or exempt(principal):
        return
    wait = rate.take(principal.name)
    if wait <= 0:
        return
    retry_after = max(1, math.ceil(wait))
    raise APIError(
        429,
        QUOTA_EXCEEDED,
        f"request rate quota of key {principal.name!r} exceeded: {rate.per_second:g} requests "
        f"per second, bursts of {rate.burst} (CSA_QUOTA_REQUESTS_PER_SECOND, "
        f"CSA_QUOTA_REQUEST_BURST); retry in {retry_after} s",
        headers={"Retry-After": str(retry_after)},
    )


RequestRateQuota = Depends(check_request_rate)


# -- stored bytes ----------------------------------------------------------------------------


@dataclass(frozen=True)
class Account:
    """The key that an upload's bytes count against."""

    key_id: int
    name: str
    scope: str


def account_of_principal(principal: Principal) -> Account | None:
    """The requesting key (checkpoint uploads); None for keys without quotas."""
    if principal.key_id is None or exempt(principal):
        return None
    return Account(principal.key_id, principal.name, principal.scope)


def account_of_scene(db: Session, scene: Scene) -> Account | None:
    """The key a scene's frames count against: its owner; None for scenes of the settings'
    keys (no owner) and of admin keys."""
    if scene.owner_key_id is None:
        return None
    key = db.get(ApiKey, scene.owner_key_id)
    if key is None or key.scope == ADMIN:
        return None
    return Account(key.id, key.name, key.scope)


def stored_bytes(db: Session, key_id: int) -> int:
    """Bytes a key stores, from the database: its scenes' frame files and its checkpoints."""
    total = 0
    for column in (Frame.color_sha256, Frame.depth_sha256, Frame.labels_sha256):
        total += (
            db.scalar(
                select(func.coalesce(func.sum(Artifact.size_bytes), 0))
                .select_from(Frame)
                .join(Scene, Scene.id == Frame.scene_id)
                .join(Artifact, Artifact.sha256 == column)
                .where(Scene.owner_key_id == key_id)
            )
            or 0
        )
    # Uploaded checkpoints have no job; their uploader is in meta (JSON, read here, not in SQL,
    # so that one query serves SQLite and PostgreSQL; the registry holds few versions).
    for size, meta in db.execute(
        select(ModelVersion.size_bytes, ModelVersion.meta).where(ModelVersion.job_id.is_(None))
    ):
        if isinstance(meta, dict) and meta.get(UPLOADER_META) == key_id:
            total += int(size or 0)
    return int(total)


def stored_bytes_quota(settings: Settings, scope: str) -> int:
    return {
        DEVICE: settings.quota_stored_bytes_device,
        OPERATOR: settings.quota_stored_bytes_operator,
    }.get(scope, 0)


def check_stored_bytes(
    db: Session,
    settings: Settings,
    account: Account | None,
    adding: int,
    field: str,
    new_bytes: Callable[[], int] | None = None,
) -> None:
    """Refuse (413 naming the quota, the key and ``field``) an upload of ``adding`` bytes that
    would take ``account`` over its stored-bytes quota. Call before writing to the store.
    ``new_bytes`` recomputes, only when over, the bytes the upload really adds (content the
    store already holds for it, as an identical re-upload, adds none)."""
    if account is None:
        return
    quota = stored_bytes_quota(settings, account.scope)
    if quota <= 0:
        return
    used = stored_bytes(db, account.key_id)
    if used + adding <= quota:
        return
    if new_bytes is not None:
        adding = new_bytes()
        if adding == 0 or used + adding <= quota:
            return
    setting = f"CSA_QUOTA_STORED_BYTES_{account.scope.upper()}"
    raise APIError(
        413,
        QUOTA_EXCEEDED,
        f"{field}: stored-bytes quota of key {account.name!r} exceeded: it stores {used} bytes, "
        f"this upload adds {adding}, the quota of scope {account.scope!r} is {quota} bytes "
        f"({setting}); delete scenes or ask for a higher quota",
        field=field,
    )


# -- queued jobs -----------------------------------------------------------------------------


def queued_jobs_quota(settings: Settings, scope: str) -> int:
    return settings.quota_queued_jobs_operator if scope == OPERATOR else 0


def check_queued_jobs(request: Request, db: DbDep) -> None:
    """Dependency of the routes that queue a job: 429 naming the limit when the queue already
    holds the scope's limit of queued jobs."""
    principal = current_principal(request)
    if exempt(principal):
        return
    services = request.app.state.services
    limit = queued_jobs_quota(services.settings, principal.scope)
    if limit <= 0:
        return
    queued = db.scalar(select(func.count(Job.id)).where(Job.status == QUEUED)) or 0
    if queued >= limit:
        raise APIError(
            429,
            QUOTA_EXCEEDED,
            f"queued-jobs quota of scope {principal.scope!r} reached: {queued} jobs wait in the "
            f"queue, keys of this scope (key {principal.name!r}) may queue while fewer than "
            f"{limit} wait (CSA_QUOTA_QUEUED_JOBS_{principal.scope.upper()}); retry once jobs "
            "have started",
        )


QueuedJobsQuota = Depends(check_queued_jobs)
