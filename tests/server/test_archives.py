"""Scene archives: safe extraction (traversal, links, bombs, counts) and bulk upload over HTTP."""

from __future__ import annotations

import io
import itertools
import tarfile
import zipfile
from pathlib import Path

import pytest

from client import CSAClient, InvalidInput
from server.archives import ArchiveLimits, UnsafeArchive, extract_archive

LIMITS = ArchiveLimits(
    max_members=50, max_member_bytes=1_000_000, max_total_bytes=3_000_000, max_ratio=100.0
)
_names = itertools.count()


def tar_with(
    path: Path, members: list[tuple[tarfile.TarInfo, bytes | None]], mode: str = "w"
) -> Path:
    with tarfile.open(path, mode) as tf:
        for info, data in members:
            if data is not None:
                info.size = len(data)
                tf.addfile(info, io.BytesIO(data))
            else:
                tf.addfile(info)
    return path


def file_info(name: str) -> tarfile.TarInfo:
    return tarfile.TarInfo(name)


def link_info(name: str, target: str, kind: bytes) -> tarfile.TarInfo:
    info = tarfile.TarInfo(name)
    info.type = kind
    info.linkname = target
    return info


@pytest.mark.parametrize(
    ("members", "problem"),
    [
        ([(file_info("../evil.txt"), b"x")], "leaves the archive"),
        ([(file_info("color/../../evil.txt"), b"x")], "leaves the archive"),
        ([(file_info("/etc/evil.txt"), b"x")], "absolute path"),
        (
            [(link_info("color/0.png", "/etc/passwd", tarfile.SYMTYPE), None)],
            "links are not allowed",
        ),
        (
            [(link_info("color/0.png", "pose/0.txt", tarfile.LNKTYPE), None)],
            "links are not allowed",
        ),
        ([(link_info("dev", "", tarfile.CHRTYPE), None)], "only regular files"),
        ([(file_info(f"f{i}"), b"") for i in range(60)], "more than 50 entries"),
        ([(file_info("big"), b"\0" * 1_100_000)], "larger than"),
        ([(file_info(f"f{i}"), b"\0" * 900_000) for i in range(4)], "unpacks to more than"),
    ],
)
def test_unsafe_tar_archives_are_refused(tmp_path: Path, members, problem: str) -> None:
    archive = tar_with(tmp_path / "a.tar.gz", members, "w:gz")
    dest = tmp_path / "out"
    with pytest.raises(UnsafeArchive, match=problem):
        extract_archive(archive, dest, LIMITS)
    assert list(dest.iterdir()) == []
    assert not (tmp_path / "evil.txt").exists()


def test_tar_member_that_lies_about_its_size_is_cut_off(tmp_path: Path) -> None:
    # A gzip stream of zeros claiming to be small is still counted while it is copied.
    archive = tar_with(
        tmp_path / "a.tar.gz", [(file_info(f"zeros{i}"), b"\0" * 999_999) for i in range(4)], "w:gz"
    )
    assert archive.stat().st_size < 20_000  # a compressed bomb: tiny on the wire
    with pytest.raises(UnsafeArchive, match="unpacks to more than"):
        extract_archive(archive, tmp_path / "out", LIMITS)


def zip_with(path: Path, entries: list[tuple[zipfile.ZipInfo | str, bytes]]) -> Path:
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for info, data in entries:
            zf.writestr(info, data)
    return path


def symlink_zip_info(name: str) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name)
    info.external_attr = 0o120777 << 16  # S_IFLNK
    return info


@pytest.mark.parametrize(
    ("entries", "problem"),
    [
        ([("../evil.txt", b"x")], "leaves the archive"),
        ([("/abs/evil.txt", b"x")], "absolute path"),
        ([("C:/evil.txt", b"x")], "absolute path"),
        ([(symlink_zip_info("color/0.png"), b"/etc/passwd")], "links are not allowed"),
        ([("bomb", b"\0" * 900_000)], "compression ratio"),
        ([(f"f{i}", b"") for i in range(60)], "more than 50 entries"),
    ],
)
def test_unsafe_zip_archives_are_refused(tmp_path: Path, entries, problem: str) -> None:
    archive = zip_with(tmp_path / "a.zip", entries)
    with pytest.raises(UnsafeArchive, match=problem):
        extract_archive(archive, tmp_path / "out", LIMITS)
    assert not (tmp_path / "evil.txt").exists()


def test_not_an_archive(tmp_path: Path) -> None:
    p = tmp_path / "x.bin"
    p.write_bytes(b"hello world" * 10)
    with pytest.raises(UnsafeArchive, match="not a tar or zip"):
        extract_archive(p, tmp_path / "out", LIMITS)


def pack_scene(folder: Path, dest: Path, fmt: str, extra: list[tuple[str, bytes]] = ()) -> Path:
    if fmt == "zip":
        with zipfile.ZipFile(dest, "w") as zf:
            for p in sorted(folder.rglob("*")):
                if p.is_file():
                    zf.write(p, arcname=f"{folder.name}/{p.relative_to(folder)}")
            for name, data in extra:
                zf.writestr(name, data)
    else:
        with tarfile.open(dest, "w:gz") as tf:
            tf.add(folder, arcname=folder.name)
            for name, data in extra:
                info = tarfile.TarInfo(name)
                info.size = len(data)
                tf.addfile(info, io.BytesIO(data))
    return dest


@pytest.mark.parametrize("fmt", ["zip", "tar.gz"])
def test_archive_upload_stores_all_frames_once(
    client: CSAClient, synth_scene: Path, tmp_path: Path, fmt: str
) -> None:
    name = f"arch-{next(_names)}"
    client.create_scene(name)
    archive = pack_scene(synth_scene, tmp_path / f"scene.{fmt}", fmt)
    result = client.upload_archive(name, archive)
    assert len(result.added) == 8 and result.unchanged == [] and result.skipped == []
    again = client.upload_archive(name, archive)
    assert again.added == [] and len(again.unchanged) == 8
    scene = client.scene(name)
    assert scene.num_frames == 8 and scene.num_labelled_frames == 8
    assert (scene.intrinsics.width, scene.intrinsics.height) == (40, 30)


def test_archive_with_traversal_stores_nothing(
    client: CSAClient, synth_scene: Path, tmp_path: Path
) -> None:
    name = f"arch-{next(_names)}"
    client.create_scene(name)
    archive = pack_scene(
        synth_scene, tmp_path / "evil.tar.gz", "tar.gz", extra=[("../../escape.txt", b"owned")]
    )
    with pytest.raises(InvalidInput) as e:
        client.upload_archive(name, archive)
    assert e.value.field == "archive" and "leaves the archive" in str(e.value)
    assert client.scene(name).num_frames == 0


def test_archive_with_one_bad_frame_stores_nothing(
    client: CSAClient, synth_scene: Path, tmp_path: Path
) -> None:
    name = f"arch-{next(_names)}"
    client.create_scene(name)
    bad = tmp_path / "bad"
    import shutil

    shutil.copytree(synth_scene, bad)
    (bad / "pose" / "5.txt").write_text("1 0 0\n0 1 0\n")
    with pytest.raises(InvalidInput) as e:
        client.upload_archive(name, pack_scene(bad, tmp_path / "bad.zip", "zip"))
    assert e.value.field == "archive:pose/5.txt"
    assert client.scene(name).num_frames == 0


def test_archive_frames_with_infinite_pose_are_skipped(
    client: CSAClient, synth_scene: Path, tmp_path: Path
) -> None:
    name = f"arch-{next(_names)}"
    client.create_scene(name)
    lost = tmp_path / "lost"
    import shutil

    shutil.copytree(synth_scene, lost)
    (lost / "pose" / "2.txt").write_text("\n".join(["-inf -inf -inf -inf"] * 4))
    result = client.upload_archive(name, pack_scene(lost, tmp_path / "lost.zip", "zip"))
    assert [s.name for s in result.skipped] == ["2"] and "not finite" in result.skipped[0].reason
    assert len(result.added) == 7


def test_oversize_archive_is_refused(client: CSAClient, tmp_path: Path) -> None:
    name = f"arch-{next(_names)}"
    client.create_scene(name)
    big = tmp_path / "big.tar"
    big.write_bytes(b"\0" * 2_500_000)  # over the 2 MB test limit
    with pytest.raises(Exception) as e:
        client.upload_archive(name, big)
    assert getattr(e.value, "status", None) == 413
