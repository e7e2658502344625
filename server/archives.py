"""Safe extraction of uploaded tar and zip archives (a scene folder sent in one request).

Only regular files and folders are extracted. Refused: absolute paths, ``..`` components,
symbolic and hard links, devices and FIFOs, more than ``max_members`` entries, a member larger
than ``max_member_bytes``, more than ``max_total_bytes`` in all, zip members whose
compression ratio exceeds ``max_ratio`` (archive bombs), tar extended headers (pax, GNU long
names) above ``MAX_TAR_HEADER_BYTES`` and sparse tar members (``tarfile`` reads those whole into
memory before any limit here sees them: a few kilobytes of gzip can declare gigabytes), one path
named twice or as both a file and a folder, and encrypted or corrupt members (errors never carry
the server's paths). Sizes are counted while copying, so a header that lies about a size gains
nothing.
"""

from __future__ import annotations

import lzma
import shutil
import stat
import tarfile
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import IO

from server.errors import storage_full

_CHUNK = 1 << 20
MAX_TAR_HEADER_BYTES = 64 * 1024  # a pax or GNU long-name header: a path of a few kilobytes at most
_EXTENDED_HEADERS = (
    tarfile.XHDTYPE,
    tarfile.XGLTYPE,
    tarfile.SOLARIS_XHDTYPE,
    tarfile.GNUTYPE_LONGNAME,
    tarfile.GNUTYPE_LONGLINK,
)


class UnsafeArchive(ValueError):
    """The archive is malformed, too large or tries to write outside its folder."""


@dataclass(frozen=True)
class ArchiveLimits:
    max_members: int
    max_member_bytes: int
    max_total_bytes: int
    max_ratio: float


def _safe_relpath(name: str) -> PurePosixPath | None:
    """The member's path relative to the extraction folder, or None for the folder itself."""
    name = name.replace("\\", "/")
    if name.startswith("/") or (len(name) > 1 and name[1] == ":"):
        raise UnsafeArchive(f"{name!r}: absolute path")
    parts = [p for p in PurePosixPath(name).parts if p not in ("", ".")]
    if any(p == ".." for p in parts):
        raise UnsafeArchive(f"{name!r}: path leaves the archive folder ('..')")
    if any("\x00" in p for p in parts):
        raise UnsafeArchive(f"{name!r}: bad character in path")
    return PurePosixPath(*parts) if parts else None


class _Budget:
    """Counts entries and bytes, and keeps the paths seen so far: an archive that names one
    path twice, or a file and a folder at one path, is ambiguous (tools disagree on which entry
    wins) and is refused rather than extracted over itself."""

    def __init__(self, limits: ArchiveLimits):
        self.limits = limits
        self.members = 0
        self.total = 0
        self.files: set[PurePosixPath] = set()
        self.folders: set[PurePosixPath] = set()

    def member(self, name: str) -> None:
        self.members += 1
        if self.members > self.limits.max_members:
            raise UnsafeArchive(f"more than {self.limits.max_members} entries")

    def claim(self, name: str, rel: PurePosixPath, is_dir: bool) -> None:
        """Record an entry's path; refuse a duplicate file or a file/folder clash."""
        for parent in rel.parents:
            if parent in self.files:
                raise UnsafeArchive(
                    f"{name!r}: {str(parent)!r} is a file in this archive, not a folder"
                )
        if rel in self.files:
            raise UnsafeArchive(f"{name!r}: the archive holds this path twice")
        if is_dir:
            self.folders.add(rel)
            return
        if rel in self.folders:
            raise UnsafeArchive(f"{name!r}: the archive holds this path as a folder and as a file")
        self.files.add(rel)
        self.folders.update(p for p in rel.parents if p != PurePosixPath("."))

    def copy(self, src: IO[bytes], dest: Path, name: str) -> None:
        written = 0
        with open(dest, "wb") as out:
            while chunk := src.read(_CHUNK):
                written += len(chunk)
                self.total += len(chunk)
                if written > self.limits.max_member_bytes:
                    raise UnsafeArchive(
                        f"{name!r}: larger than {self.limits.max_member_bytes} bytes"
                    )
                if self.total > self.limits.max_total_bytes:
                    raise UnsafeArchive(f"unpacks to more than {self.limits.max_total_bytes} bytes")
                out.write(chunk)


def _os_problem(e: OSError) -> str:
    """An OS error without the file names it carries (they are paths of the server)."""
    return e.strerror or type(e).__name__


def _target(root: Path, rel: PurePosixPath) -> Path:
    dest = (root / rel).resolve()
    if not dest.is_relative_to(root):
        raise UnsafeArchive(f"{str(rel)!r}: path leaves the archive folder")
    return dest


class _BoundedTarInfo(tarfile.TarInfo):
    """A tar header that ``tarfile`` parses only when reading it cannot take unbounded memory:
    extended headers (pax, GNU long names) are read whole before the member they describe, and
    sparse maps (GNU sparse members, pax sparse 1.0) grow with the data, so an extended header
    above ``MAX_TAR_HEADER_BYTES`` and sparse members are refused before they are read."""

    @classmethod
    def frombuf(cls, buf: bytes, encoding: str, errors: str) -> tarfile.TarInfo:
        info = super().frombuf(buf, encoding, errors)
        if info.type == tarfile.GNUTYPE_SPARSE:
            raise UnsafeArchive(f"{info.name!r}: sparse files are not allowed")
        if info.type in _EXTENDED_HEADERS and info.size > MAX_TAR_HEADER_BYTES:
            raise UnsafeArchive(
                f"{info.name!r}: extended header of {info.size} bytes (more than "
                f"{MAX_TAR_HEADER_BYTES})"
            )
        return info

    def _proc_gnusparse_10(self, member, pax_headers, archive):  # tarfile's hook for pax sparse 1.0
        raise UnsafeArchive(f"{member.name!r}: sparse files are not allowed")


def _extract_tar(path: Path, root: Path, limits: ArchiveLimits) -> None:
    budget = _Budget(limits)
    try:
        try:
            tf = tarfile.open(path, mode="r:*", tarinfo=_BoundedTarInfo)
        except tarfile.ReadError:  # no tar header, compressed or not (tarfile.is_tarfile's test)
            raise UnsafeArchive("not a tar or zip archive") from None
        with tf:
            while (m := tf.next()) is not None:
                budget.member(m.name)
                rel = _safe_relpath(m.name)
                if m.issym() or m.islnk():
                    raise UnsafeArchive(f"{m.name!r}: links are not allowed")
                if not (m.isfile() or m.isdir()):
                    raise UnsafeArchive(f"{m.name!r}: only regular files and folders are allowed")
                if m.sparse is not None:  # pax sparse 0.0 and 0.1 (bounded by the header size)
                    raise UnsafeArchive(f"{m.name!r}: sparse files are not allowed")
                if rel is None:
                    if m.isfile():  # its data would be skipped unread, uncounted
                        raise UnsafeArchive(
                            f"{m.name!r}: a file cannot be the archive folder itself"
                        )
                    continue
                budget.claim(m.name, rel, m.isdir())
                dest = _target(root, rel)
                if m.isdir():
                    dest.mkdir(parents=True, exist_ok=True)
                    continue
                if m.size > limits.max_member_bytes:
                    raise UnsafeArchive(f"{m.name!r}: larger than {limits.max_member_bytes} bytes")
                dest.parent.mkdir(parents=True, exist_ok=True)
                src = tf.extractfile(m)
                if src is None:
                    raise UnsafeArchive(f"{m.name!r}: cannot be read")
                with src:
                    budget.copy(src, dest, m.name)
    except UnsafeArchive:
        raise
    except (
        tarfile.TarError,
        EOFError,
        RecursionError,
        ValueError,
        zlib.error,
        lzma.LZMAError,
    ) as e:  # RecursionError: a chain of extended headers
        raise UnsafeArchive(f"not a readable tar archive ({e})") from None
    except OSError as e:  # the message, never the server's path
        if storage_full(e):  # the server's disk, not the archive: answered 507
            raise
        raise UnsafeArchive(f"not a readable tar archive ({_os_problem(e)})") from None


def _extract_zip(path: Path, root: Path, limits: ArchiveLimits) -> None:
    budget = _Budget(limits)
    try:
        with zipfile.ZipFile(path) as zf:
            infos = zf.infolist()
            if len(infos) > limits.max_members:
                raise UnsafeArchive(f"more than {limits.max_members} entries")
            declared = 0
            for info in infos:
                _safe_relpath(info.filename)
                file_type = stat.S_IFMT(
                    info.external_attr >> 16
                )  # 0: made on a system without types
                if file_type == stat.S_IFLNK:
                    raise UnsafeArchive(f"{info.filename!r}: links are not allowed")
                if file_type not in (0, stat.S_IFREG, stat.S_IFDIR):
                    raise UnsafeArchive(
                        f"{info.filename!r}: only regular files and folders are allowed"
                    )
                if info.file_size > limits.max_member_bytes:
                    raise UnsafeArchive(
                        f"{info.filename!r}: larger than {limits.max_member_bytes} bytes"
                    )
                if info.file_size > 1024 and info.file_size > limits.max_ratio * max(
                    info.compress_size, 1
                ):
                    raise UnsafeArchive(
                        f"{info.filename!r}: compression ratio above {limits.max_ratio:g} (archive "
                        "bomb?)"
                    )
                declared += info.file_size
            if declared > limits.max_total_bytes:
                raise UnsafeArchive(f"unpacks to more than {limits.max_total_bytes} bytes")
            for info in infos:
                budget.member(info.filename)
                rel = _safe_relpath(info.filename)
                if rel is None:
                    continue
                budget.claim(info.filename, rel, info.is_dir())
                dest = _target(root, rel)
                if info.is_dir():
                    dest.mkdir(parents=True, exist_ok=True)
                    continue
                dest.parent.mkdir(parents=True, exist_ok=True)
                with zf.open(info) as src:
                    budget.copy(src, dest, info.filename)
    except UnsafeArchive:
        raise
    except (
        zipfile.BadZipFile,
        zipfile.LargeZipFile,
        EOFError,
        NotImplementedError,
        RuntimeError,
        ValueError,
        zlib.error,
        lzma.LZMAError,
    ) as e:  # RuntimeError: encrypted
        raise UnsafeArchive(f"not a readable zip archive ({e})") from None
    except OSError as e:  # the message, never the server's path
        if storage_full(e):  # the server's disk, not the archive: answered 507
            raise
        raise UnsafeArchive(f"not a readable zip archive ({_os_problem(e)})") from None


def extract_archive(path: Path, dest: Path, limits: ArchiveLimits) -> Path:
    """Extract a tar (optionally gz/bz2/xz) or zip archive into the empty folder ``dest``.

    On any refusal ``dest`` is emptied and :class:`UnsafeArchive` says why.
    """
    dest.mkdir(parents=True, exist_ok=True)
    root = dest.resolve()
    try:
        if zipfile.is_zipfile(path):
            _extract_zip(path, root, limits)
        else:
            _extract_tar(path, root, limits)  # "not a tar or zip archive" when it is neither
    except BaseException:
        shutil.rmtree(root, ignore_errors=True)
        root.mkdir(parents=True, exist_ok=True)
        raise
    return root
