"""``csa backup`` and ``csa restore``: a service's data round-trips on SQLite (frames, a model
version, the generated API key) through the commands' own code; a backup taken while the
service runs is consistent; restore refuses a corrupt backup and a non-empty target unless
``--force``."""

from __future__ import annotations

import argparse
import hashlib
import os
from pathlib import Path

import pytest

from csa_core.cli.main import build_parser
from server import capabilities
from server.backup import MANIFEST, BackupError, check_backup
from tests.server.conftest import start_server, test_settings
from tests.server.test_crash_consistency import frame_parts, look


def csa(args: list[str], capsys) -> tuple[int, str, str]:
    """A ``csa`` command run through its parser in this process (no CSA_* settings apply:
    the data folder is given)."""
    ns: argparse.Namespace = build_parser().parse_args(args)
    code = ns.func(ns)
    out = capsys.readouterr()
    return code, out.out, out.err


def stored_files(data: Path) -> dict[str, bytes]:
    blobs = data / "artifacts" / "blobs"
    return {p.name: p.read_bytes() for d in blobs.iterdir() for p in d.iterdir()}


def test_backup_then_restore_round_trips_a_services_data(
    synth_scene: Path, tmp_path: Path, capsys, monkeypatch
) -> None:
    for key in [k for k in os.environ if k.startswith("CSA_")]:
        monkeypatch.delenv(key)
    monkeypatch.chdir(tmp_path)  # no .env of the checkout
    source = tmp_path / "source"
    live = start_server(
        test_settings(source, embedded_worker=False, api_keys=[])
    )  # a generated key
    try:
        with live.client(api_key=(source / "api_key").read_text().strip()) as c:
            c.upload_scene_folder(synth_scene, scene="room")
            extra = c.upload_frame(
                "room",
                name="extra",
                **{
                    **frame_parts(synth_scene, "0"),
                    "pose": [[1, 0, 0, 0.5], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
                },
            )
            model_sha = None
            if capabilities.available("seg"):
                from csa_core.seg.checkpoint import save_checkpoint
                from csa_core.seg.models import build_model

                save_checkpoint(tmp_path / "m.safetensors", build_model())
                model_sha = c.register_model(tmp_path / "m.safetensors", name="m").sha256
            before = {f.name: (f.id, f.pose) for f in c.frames("room")}
            # Taken while the service runs, as an operator would.
            code, out, err = csa(
                ["backup", str(tmp_path / "bk"), "--data-dir", str(source)], capsys
            )
            assert code == 0, err
            assert out.startswith("backed up the sqlite database and ")
    finally:
        live.stop()

    manifest = check_backup(tmp_path / "bk")
    assert manifest["database"] == "sqlite" and manifest["api_key_file"] is True
    assert set(manifest["artifacts"]) == set(stored_files(source))
    assert len(before) == 9 and extra.created

    # A backup goes into a new or empty folder only.
    code, _, err = csa(["backup", str(tmp_path / "bk"), "--data-dir", str(source)], capsys)
    assert code == 1 and "not an empty folder" in err

    target = tmp_path / "target"
    code, out, err = csa(["restore", str(tmp_path / "bk"), "--data-dir", str(target)], capsys)
    assert code == 0, err
    assert stored_files(target) == stored_files(source)
    assert (target / "api_key").read_text() == (source / "api_key").read_text()

    restored = start_server(test_settings(target, embedded_worker=False, api_keys=[]))
    try:
        with restored.client(api_key=(target / "api_key").read_text().strip()) as c:
            assert {f.name: (f.id, f.pose) for f in c.frames("room")} == before
            if model_sha is not None:
                got = c.download_model("m", tmp_path / "m-restored.safetensors").read_bytes()
                assert hashlib.sha256(got).hexdigest() == model_sha
        report = look(restored.settings)
        assert report.problems == 0, report.lines()
    finally:
        restored.stop()

    # A target with data is refused, naming it, unless --force; --force replaces it whole.
    code, _, err = csa(["restore", str(tmp_path / "bk"), "--data-dir", str(target)], capsys)
    assert code == 1 and "holds a database and artifact files" in err and "--force" in err
    stray = target / "artifacts" / "blobs" / "00" / ("0" * 64)
    stray.parent.mkdir(parents=True, exist_ok=True)
    stray.write_bytes(b"not in the backup")
    code, _, err = csa(
        ["restore", str(tmp_path / "bk"), "--data-dir", str(target), "--force"], capsys
    )
    assert code == 0, err
    assert not stray.exists() and stored_files(target) == stored_files(source)


def test_restore_refuses_a_corrupt_or_unfinished_backup_before_touching_the_target(
    tmp_path: Path, capsys
) -> None:
    source = tmp_path / "source"
    live = start_server(test_settings(source, embedded_worker=False))
    try:
        with live.client() as c:
            c.create_scene("empty-room")
    finally:
        live.stop()
    code, _, err = csa(["backup", str(tmp_path / "bk"), "--data-dir", str(source)], capsys)
    assert code == 0, err
    db_copy = tmp_path / "bk" / "csa.db"
    db_copy.write_bytes(db_copy.read_bytes() + b"\0")
    target = tmp_path / "target"
    code, _, err = csa(["restore", str(tmp_path / "bk"), "--data-dir", str(target)], capsys)
    assert code == 1 and "csa.db: missing or not the file the manifest records" in err
    assert not (target / "csa.db").exists()
    (tmp_path / "bk" / MANIFEST).unlink()
    with pytest.raises(BackupError, match="manifest.json: missing"):
        check_backup(tmp_path / "bk")


def test_backup_then_restore_on_postgresql(
    request, synth_scene: Path, tmp_path: Path, capsys
) -> None:
    """pg_dump in the snapshot the artifact list is read in, pg_restore into an empty database
    (and with --force over one that holds data); where the tests have a PostgreSQL server."""
    import shutil

    from tests.server.conftest import database_url

    if shutil.which("pg_dump") is None or shutil.which("pg_restore") is None:
        pytest.skip("PostgreSQL's client programs pg_dump and pg_restore are not installed")
    source_db, target_db = database_url(request, "postgresql"), database_url(request, "postgresql")
    source = tmp_path / "source"
    live = start_server(test_settings(source, database_url=source_db, embedded_worker=False))
    try:
        with live.client() as c:
            c.upload_scene_folder(synth_scene, scene="room")
            before = {f.name: (f.id, f.pose) for f in c.frames("room")}
            code, out, err = csa(
                [
                    "backup",
                    str(tmp_path / "bk"),
                    "--data-dir",
                    str(source),
                    "--database-url",
                    source_db,
                ],
                capsys,
            )
            assert code == 0, err
            assert out.startswith("backed up the postgresql database and ")
    finally:
        live.stop()
    assert check_backup(tmp_path / "bk")["database"] == "postgresql"

    target = tmp_path / "target"
    code, _, err = csa(
        ["restore", str(tmp_path / "bk"), "--data-dir", str(target), "--database-url", target_db],
        capsys,
    )
    assert code == 0, err
    assert stored_files(target) == stored_files(source)
    restored = start_server(test_settings(target, database_url=target_db, embedded_worker=False))
    try:
        with restored.client() as c:
            assert {f.name: (f.id, f.pose) for f in c.frames("room")} == before
            c.create_scene("after-restore")
        assert look(restored.settings).problems == 0
    finally:
        restored.stop()
    # The target holds data now: refused without --force, replaced whole with it.
    code, _, err = csa(
        ["restore", str(tmp_path / "bk"), "--data-dir", str(target), "--database-url", target_db],
        capsys,
    )
    assert code == 1 and "holds a database and artifact files" in err
    code, _, err = csa(
        [
            "restore",
            str(tmp_path / "bk"),
            "--data-dir",
            str(target),
            "--database-url",
            target_db,
            "--force",
        ],
        capsys,
    )
    assert code == 0, err
    restored = start_server(test_settings(target, database_url=target_db, embedded_worker=False))
    try:
        with restored.client() as c:
            assert [s.name for s in c.scenes()] == ["room"]
    finally:
        restored.stop()
