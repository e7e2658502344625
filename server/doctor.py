"""``csa doctor``: what a crash (or a hand in the data folder) left inconsistent between the
database and the artifact store, and its repair (docs/operations.md "csa doctor").

It finds, with the store's and the queue's own code:

* blob files that no artifact row records, and half-written ``tmp/*.part`` files
  (:meth:`ArtifactStore.sweep_unrecorded`, the background sweep's own pass);
* artifact rows that no frame, model version or NeRF checkpoint refers to
  (:meth:`ArtifactStore.collect_garbage`, as deleting a scene does);
* rows whose blob is missing or does not hash to its checksum (:meth:`ArtifactStore.verify`),
  and checksums that a model version or NeRF checkpoint names without an artifact row;
* scratch folders of jobs no longer running and of killed uploads
  (:func:`server.executors.base.stale_scratch`);
* jobs left running by an owner that died (:func:`server.jobs.queue.stale_jobs`).

The repair removes the leftovers, records an artifact row for a referenced blob that has an
intact file but no row, and ends stuck jobs as the queue's recovery does (re-queued, or
failed after ``max_attempts``). It never deletes a blob that a row refers to; a missing or
corrupt blob cannot be repaired here (restore a backup: docs/operations.md "Backup and restore").
"""

from __future__ import annotations

import datetime as dt
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from server.artifacts import ArtifactStore, sha256_file
from server.db.models import Artifact, ModelVersion, NerfCheckpoint, Worker, utcnow
from server.db.session import session_scope
from server.executors.base import stale_scratch
from server.jobs import queue


@dataclass
class DoctorReport:
    orphan_blobs: list[str] = field(default_factory=list)  # blob files without an artifact row
    temp_files: list[str] = field(default_factory=list)  # tmp/*.part: writes that never finished
    unreferenced_rows: list[str] = field(default_factory=list)  # artifact rows nothing refers to
    unrecorded_refs: list[str] = field(
        default_factory=list
    )  # named by a model/NeRF, no artifact row
    missing_blobs: list[str] = field(default_factory=list)  # artifact rows whose file is gone
    corrupt_blobs: list[str] = field(default_factory=list)  # files that do not hash to their name
    stale_scratch: list[str] = field(default_factory=list)  # work folders of dead jobs / uploads
    stuck_jobs: list[tuple[int, str]] = field(
        default_factory=list
    )  # (job id, why its owner is gone)
    min_age_s: float = 0.0
    live_workers: list[str] = field(default_factory=list)
    repaired: bool = False

    @property
    def unrepairable(self) -> list[str]:
        """Problems a repair cannot fix: data whose bytes are gone."""
        return (
            self.missing_blobs
            + self.corrupt_blobs
            + [s for s in self.unrecorded_refs if s in self._unfixable_refs]
        )

    _unfixable_refs: set[str] = field(default_factory=set)

    @property
    def problems(self) -> int:
        return sum(
            len(x)
            for x in (
                self.orphan_blobs,
                self.temp_files,
                self.unreferenced_rows,
                self.unrecorded_refs,
                self.missing_blobs,
                self.corrupt_blobs,
                self.stale_scratch,
                self.stuck_jobs,
            )
        )

    def lines(self) -> list[str]:
        done = self.repaired
        out = [
            f"{len(self.live_workers)} live executor(s): {', '.join(self.live_workers) or 'none'}; "
            f"files younger than {self.min_age_s:g} s are left alone (they may belong to a request "
            "still running)"
        ]
        groups: list[tuple[str, list[str], str]] = [
            (
                "blob files without an artifact row",
                self.orphan_blobs,
                "removed" if done else "would remove",
            ),
            (
                "half-written temporary files",
                self.temp_files,
                "removed" if done else "would remove",
            ),
            (
                "artifact rows nothing refers to",
                self.unreferenced_rows,
                "removed with their files" if done else "would remove with their files",
            ),
            (
                "checksums named by a model or NeRF without an artifact row",
                self.unrecorded_refs,
                "recorded when the file is intact"
                if done
                else "would record when the file is intact",
            ),
            (
                "artifact rows whose file is missing",
                self.missing_blobs,
                "cannot repair: restore a backup",
            ),
            (
                "blobs that do not match their checksum",
                self.corrupt_blobs,
                "cannot repair: restore a backup",
            ),
            (
                "scratch folders of dead jobs and uploads",
                self.stale_scratch,
                "removed" if done else "would remove",
            ),
            (
                "jobs running with no live owner",
                [f"job {i}: {why}" for i, why in self.stuck_jobs],
                "ended as the queue's recovery does"
                if done
                else "would re-queue (or fail after max attempts)",
            ),
        ]
        for title, items, action in groups:
            out.append(f"{title}: {len(items)}" + (f" ({action})" if items else ""))
            out.extend(f"  {item}" for item in items)
        return out


def live_workers(s: Session, lease_seconds: float) -> list[str]:
    """Executors registered as running whose process is alive (this host) or whose heartbeat
    is younger than a lease (another host)."""
    recent = utcnow() - dt.timedelta(seconds=lease_seconds)
    alive = []
    for w in s.scalars(select(Worker).where(Worker.stopped_at.is_(None))):
        if queue._owner_gone(w, w.id) is not None:
            continue
        if w.heartbeat_at is not None and w.heartbeat_at >= recent:
            alive.append(w.id)
    return alive


def _referenced_by_files(s: Session) -> set[str]:
    used: set[str] = set()
    for (files,) in s.execute(select(ModelVersion.files)):
        used.update(files.values())
    for (files,) in s.execute(select(NerfCheckpoint.files)):
        used.update(files.values())
    return used


def examine(
    sessions: sessionmaker[Session],
    store: ArtifactStore,
    work_dir: Path,
    *,
    repair: bool,
    min_age_s: float | None,
    grace_s: float,
    lease_seconds: float,
    max_attempts: int,
    say: Callable[[str], None] = lambda _: None,
) -> DoctorReport:
    """Look for inconsistencies (and repair them when ``repair``). ``min_age_s=None``: 0 when no
    executor is alive, else ``grace_s`` (the background sweep's grace period)."""
    report = DoctorReport()
    with session_scope(sessions) as s:
        report.live_workers = live_workers(s, lease_seconds)
    report.min_age_s = (
        min_age_s if min_age_s is not None else (grace_s if report.live_workers else 0.0)
    )

    # Stuck jobs first: their scratch folders are stale only once they no longer run.
    with session_scope(sessions) as s:
        report.stuck_jobs = [(job.id, why) for job, why in queue.stale_jobs(s)]
    if repair and report.stuck_jobs:
        queue.recover_stale_jobs(sessions, max_attempts)

    # Rows nothing refers to: deleted in one transaction, their files after it commits.
    s = sessions()
    try:
        report.unreferenced_rows = store.collect_garbage(s)
        if repair:
            s.commit()
            store.remove_unrecorded(s, report.unreferenced_rows)
        else:
            s.rollback()
    finally:
        s.close()

    with session_scope(sessions) as s:
        recorded = set(s.scalars(select(Artifact.sha256)))
        for sha in sorted(_referenced_by_files(s) - recorded):
            report.unrecorded_refs.append(sha)
            path = store.path_of(sha)
            if not path.is_file() or sha256_file(path) != sha:
                report._unfixable_refs.add(sha)
            elif repair:  # the file is intact: record it, so that the sweep never deletes it
                s.add(Artifact(sha256=sha, size_bytes=path.stat().st_size, kind="recovered"))
    # After the references are recorded, so that the sweep keeps their files.
    with session_scope(sessions) as s:
        for name in store.sweep_unrecorded(s, report.min_age_s, dry_run=not repair):
            (
                report.temp_files
                if name.endswith(".part") or len(name) != 64
                else report.orphan_blobs
            ).append(name)
        verified = store.verify(s)
    report.missing_blobs, report.corrupt_blobs = sorted(verified.missing), sorted(verified.corrupt)

    with session_scope(sessions) as s:
        scratch = stale_scratch(s, work_dir, report.min_age_s)
    if not repair:  # the folders of the stuck jobs, which the repair ends first
        scratch += [
            p
            for job_id, _ in report.stuck_jobs
            for p in sorted(work_dir.glob(f"job-{job_id}-*"))
            if p.is_dir()
        ]
    report.stale_scratch = [p.name for p in scratch]
    if repair:
        for p in scratch:
            shutil.rmtree(p, ignore_errors=True)
    report.repaired = repair
    for line in report.lines():
        say(line)
    return report
