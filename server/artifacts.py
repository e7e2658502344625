"""The artifact store: content-addressed files on disk, checksums in the database.

A file is stored under ``blobs/<sha[:2]>/<sha>``; it is written to a temporary name, fsynced
and renamed into place, so a crash never leaves a half-written blob under a checksum name.
Storing the same bytes twice is a no-op. The ``artifacts`` table records each blob's sha256,
size and kind; :meth:`ArtifactStore.verify` re-hashes the files against it.

A blob is written before the transaction that records it commits; when that transaction fails
(a concurrent upload, a deleted scene, a dead process) the file stays unrecorded.
:meth:`ArtifactStore.sweep_unrecorded` deletes such files (and stale ``tmp/*.part`` files) once
they are older than a grace period (the server runs it in the background, :class:`OrphanSweeper`,
never inside a request); storing bytes that already exist refreshes the file's
modification time, so a blob an open transaction is about to record is never swept.
"""

from __future__ import annotations

import hashlib
import logging
import os
import shutil
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import Session

from server import faults
from server.db.models import Artifact, Frame, ModelVersion, NerfCheckpoint

log = logging.getLogger(__name__)

_CHUNK = 1 << 20


class ArtifactMissing(LookupError):
    """A checksum the database refers to has no (intact) file in the store."""


@dataclass(frozen=True)
class StoredFile:
    sha256: str
    size_bytes: int


@dataclass(frozen=True)
class VerifyReport:
    checked: int
    missing: list[str]
    corrupt: list[str]

    @property
    def ok(self) -> bool:
        return not self.missing and not self.corrupt


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


class ArtifactStore:
    def __init__(self, root: Path):
        self.root = Path(root)
        (self.root / "blobs").mkdir(parents=True, exist_ok=True)
        (self.root / "tmp").mkdir(parents=True, exist_ok=True)

    def path_of(self, sha256: str) -> Path:
        if len(sha256) != 64 or any(c not in "0123456789abcdef" for c in sha256):
            raise ValueError(f"not a sha256 hex digest: {sha256!r}")
        return self.root / "blobs" / sha256[:2] / sha256

    # -- writing -------------------------------------------------------------------------

    def _commit_tmp(self, tmp: Path, sha: str) -> None:
        dest = self.path_of(sha)
        if dest.is_file() and dest.stat().st_size == tmp.stat().st_size:
            tmp.unlink(missing_ok=True)
            os.utime(dest)  # put again: not an orphan for another grace period
            return
        dest.parent.mkdir(parents=True, exist_ok=True)
        os.replace(tmp, dest)

    def put_bytes(
        self, session: Session, data: bytes, kind: str, media_type: str = "application/octet-stream"
    ) -> StoredFile:
        """Store ``data`` (atomically, once) and record it in the session's transaction."""
        sha = hashlib.sha256(data).hexdigest()
        fd, name = tempfile.mkstemp(dir=self.root / "tmp", suffix=".part")
        tmp = Path(name)
        try:
            with os.fdopen(fd, "wb") as f:
                faults.point("artifact.write")
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
            faults.point("artifact.tmp_written")
            self._commit_tmp(tmp, sha)
        finally:
            tmp.unlink(missing_ok=True)
        return self._record(session, sha, len(data), kind, media_type)

    def put_file(
        self, session: Session, path: Path, kind: str, media_type: str = "application/octet-stream"
    ) -> StoredFile:
        """Copy a file into the store (atomically, once) and record it."""
        h = hashlib.sha256()
        size = 0
        fd, name = tempfile.mkstemp(dir=self.root / "tmp", suffix=".part")
        tmp = Path(name)
        try:
            with open(path, "rb") as src, os.fdopen(fd, "wb") as dst:
                faults.point("artifact.write")
                while chunk := src.read(_CHUNK):
                    h.update(chunk)
                    size += len(chunk)
                    dst.write(chunk)
                dst.flush()
                os.fsync(dst.fileno())
            faults.point("artifact.tmp_written")
            sha = h.hexdigest()
            self._commit_tmp(tmp, sha)
        finally:
            tmp.unlink(missing_ok=True)
        faults.point("artifact.file_stored")
        return self._record(session, sha, size, kind, media_type)

    def _record(
        self, session: Session, sha: str, size: int, kind: str, media_type: str
    ) -> StoredFile:
        if session.get(Artifact, sha) is None:
            session.add(Artifact(sha256=sha, size_bytes=size, kind=kind, media_type=media_type))
            session.flush()
        return StoredFile(sha, size)

    # -- reading -------------------------------------------------------------------------

    def open_verified(self, sha256: str) -> Path:
        """Path of an existing blob (size checked); raises :class:`ArtifactMissing`."""
        p = self.path_of(sha256)
        if not p.is_file():
            raise ArtifactMissing(f"artifact {sha256[:12]} is missing from the store")
        return p

    def read_bytes(self, sha256: str) -> bytes:
        return self.open_verified(sha256).read_bytes()

    def materialize(self, sha256: str, dest: Path) -> Path:
        """Make ``dest`` a copy of a blob (a hard link when possible: blobs are never modified)."""
        src = self.open_verified(sha256)
        dest.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(src, dest)
        except OSError:
            shutil.copyfile(src, dest)
        return dest

    # -- integrity -----------------------------------------------------------------------

    def verify(self, session: Session, shas: Iterable[str] | None = None) -> VerifyReport:
        """Re-hash blobs (all recorded ones by default) and compare with the database."""
        rows: Iterator[Artifact]
        if shas is None:
            rows = iter(session.scalars(select(Artifact)).all())
        else:
            rows = (a for a in (session.get(Artifact, s) for s in shas) if a is not None)
        missing, corrupt, n = [], [], 0
        for art in rows:
            n += 1
            p = self.path_of(art.sha256)
            if not p.is_file():
                missing.append(art.sha256)
            elif p.stat().st_size != art.size_bytes or sha256_file(p) != art.sha256:
                corrupt.append(art.sha256)
        return VerifyReport(n, missing, corrupt)

    def collect_garbage(self, session: Session) -> list[str]:
        """Delete the rows of artifacts that no frame, model version or NeRF checkpoint refers
        to; returns their checksums for :meth:`remove_unrecorded` once the transaction commits."""
        used: set[str] = set()
        for c, d, lab in session.execute(
            select(Frame.color_sha256, Frame.depth_sha256, Frame.labels_sha256)
        ):
            used.update(s for s in (c, d, lab) if s)
        for (files,) in session.execute(select(ModelVersion.files)):
            used.update(files.values())
        for (files,) in session.execute(select(NerfCheckpoint.files)):
            used.update(files.values())
        removed = []
        for art in session.scalars(select(Artifact)).all():
            if art.sha256 not in used:
                session.delete(art)
                removed.append(art.sha256)
        session.flush()
        return removed

    def sweep_unrecorded(
        self, session: Session, older_than_s: float, dry_run: bool = False
    ) -> list[str]:
        """Delete blob files that no artifact row records and ``tmp/`` files, when last written
        more than ``older_than_s`` seconds ago (a younger one may belong to a transaction still
        open); returns the deleted files' names (with ``dry_run``: those it would delete, and
        deletes nothing). These are the leftovers of transactions that failed after writing
        their blobs."""
        cutoff = time.time() - older_than_s
        recorded = set(session.scalars(select(Artifact.sha256)))
        removed: list[str] = []
        candidates = [
            p
            for d in (self.root / "blobs").iterdir()
            if d.is_dir()
            for p in d.iterdir()
            if p.name not in recorded
        ]
        candidates += list((self.root / "tmp").iterdir())
        for path in candidates:
            try:
                if path.is_file() and path.stat().st_mtime < cutoff:
                    if not dry_run:
                        path.unlink()
                    removed.append(path.name)
            except FileNotFoundError:  # another process swept it first
                continue
        return removed

    def remove_unrecorded(self, session: Session, shas: Iterable[str]) -> None:
        """Delete blob files whose rows are gone (call after the deleting transaction commits;
        a blob that an upload recorded again in the meantime is kept)."""
        for sha in shas:
            if session.get(Artifact, sha) is None:
                self.path_of(sha).unlink(missing_ok=True)


class OrphanSweeper:
    """Runs :meth:`ArtifactStore.sweep_unrecorded` in a daemon thread: once at start, then every
    ``interval_s`` seconds (0: only the first), so a store of millions of files is listed in the
    background instead of inside a request or before the server answers. A failed sweep is
    logged and retried at the next interval."""

    def __init__(
        self,
        store: ArtifactStore,
        sessions: Callable[[], AbstractContextManager[Session]],
        older_than_s: float,
        interval_s: float,
    ):
        if interval_s < 0:
            raise ValueError(f"orphan_sweep_interval_seconds must be >= 0, got {interval_s}")
        self.store, self.sessions = store, sessions
        self.older_than_s, self.interval_s = older_than_s, interval_s
        self.sweeps = 0  # finished sweeps (for tests and the log)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="csa-orphan-sweeper", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout: float = 10.0) -> None:
        self._stop.set()
        self._thread.join(timeout)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                with self.sessions() as session:
                    swept = self.store.sweep_unrecorded(session, self.older_than_s)
                if swept:
                    log.info(
                        "deleted %d unrecorded artifact files older than %.0f s",
                        len(swept),
                        self.older_than_s,
                    )
            except Exception:  # a sweep must never take the server down: try again later
                log.exception("sweeping unrecorded artifact files failed")
            self.sweeps += 1
            if self.interval_s == 0 or self._stop.wait(self.interval_s):
                return
