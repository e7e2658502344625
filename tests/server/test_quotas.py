"""Quotas per key (server/quotas.py, docs/operations.md "Quotas"): the request rate (429 with
Retry-After), stored bytes (413 before anything is stored, counted from the database so that a
restart keeps the count) and queued jobs (429 naming the limit); each key's quotas leave the
others' alone, and admin keys have none. One server without a worker per backend."""

from __future__ import annotations

import functools
import hashlib
import io
import json
import tarfile
from collections.abc import Iterator
from dataclasses import dataclass

import cv2
import httpx
import numpy as np
import pytest
from sqlalchemy import func, select

from server.db.models import Artifact, ModelVersion
from server.db.session import session_scope
from server.quotas import RequestRate, stored_bytes
from tests.server.conftest import (
    API_KEY,
    LiveServer,
    both_backends,
    database_url,
    start_server,
    test_settings,
)

W, H = 32, 24
K = "30 0 15.5\n0 31 11.5\n0 0 1\n"
POSE = "1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n"
SLOW_RATE = 0.01  # requests per second: one token per 100 s, so a test never sees a refill
BURST = 12  # requests per key at once: more than any key of the other tests sends
QUEUED_JOBS = 2
CARD = {"arch": "lraspp_mobilenet_v3_large", "format": "csa-seg-checkpoint/1"}


def png(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return buf.tobytes()


def frame_parts(seed: int) -> dict[str, bytes]:
    rng = np.random.default_rng(seed)
    return {
        "color": png(rng.integers(0, 256, (H, W, 3), dtype=np.uint8)),
        "depth": png(np.full((H, W), 1500, np.uint16)),
    }


def frame_files(seed: int) -> dict:
    parts = frame_parts(seed)
    return {
        "color": ("c.png", parts["color"]),
        "depth": ("d.png", parts["depth"]),
        "pose": ("p.txt", POSE.encode()),
        "intrinsics": ("k.txt", K.encode()),
    }


def frame_bytes(seed: int) -> int:
    return sum(len(b) for b in frame_parts(seed).values())


def archive_of(seed: int, name: str) -> bytes:
    """A tar of a scene folder holding one frame."""
    parts = frame_parts(seed)
    members = {
        f"color/{name}.png": parts["color"],
        f"depth/{name}.png": parts["depth"],
        f"pose/{name}.txt": POSE.encode(),
        "intrinsic/intrinsic_color.txt": K.encode(),
    }
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tf:
        for path, data in members.items():
            info = tarfile.TarInfo(path)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
    return buf.getvalue()


@functools.cache
def checkpoint_bytes() -> bytes:
    """A real checkpoint: the card's untrained network, as the registry accepts it."""
    from safetensors.torch import save

    from csa_core.seg.models import build_model

    weights = {k: v.contiguous() for k, v in build_model(CARD["arch"]).state_dict().items()}
    return save(weights, metadata={"csa": json.dumps(CARD)})


@dataclass
class Quotaed:
    live: LiveServer
    keys: dict[str, str]

    def http(self, who: str) -> httpx.Client:
        key = self.keys.get(who, who)
        return httpx.Client(base_url=self.live.url, headers={"X-API-Key": key}, timeout=60)

    def make_key(self, name: str, scope: str) -> str:
        with self.http(API_KEY) as admin:
            r = admin.post("/api/v1/keys", json={"name": name, "scope": scope})
        assert r.status_code == 201, r.text
        self.keys[name] = r.json()["key"]
        return self.keys[name]

    def key_id(self, name: str) -> int:
        with self.http(API_KEY) as admin:
            rows = admin.get("/api/v1/keys").json()
        return next(r["id"] for r in rows if r["name"] == name)


# The device quota holds the first frame of each device (seed 1, then seed 2) but not a second
# one; the operator quota holds one checkpoint but not two.
DEVICE_QUOTA = frame_bytes(1) + frame_bytes(2) // 2


def quota_settings(data_dir, url):
    return test_settings(
        data_dir,
        database_url=url,
        embedded_worker=False,  # queued jobs stay queued
        quota_requests_per_second=SLOW_RATE,
        quota_request_burst=BURST,
        quota_stored_bytes_device=DEVICE_QUOTA,
        quota_stored_bytes_operator=len(checkpoint_bytes()) * 3 // 2,
        quota_queued_jobs_operator=QUEUED_JOBS,
        max_frame_upload_bytes=200_000,
    )


@pytest.fixture(scope="module")
def quotaed(request, tmp_path_factory, db_backend: str) -> Iterator[Quotaed]:
    data_dir = tmp_path_factory.mktemp("quotas")
    settings = quota_settings(data_dir, database_url(request, db_backend))
    q = Quotaed(start_server(settings), {"admin-settings": API_KEY})
    yield q
    q.live.stop()


def refused(r: httpx.Response, status: int, *words: str) -> dict:
    assert r.status_code == status, f"{r.status_code}: {r.text[:400]}"
    error = r.json()["error"]
    assert error["code"] == "quota_exceeded", error
    for word in words:
        assert word in error["message"], error
    return error


def test_token_bucket_refills_at_its_rate() -> None:
    now = [100.0]
    rate = RequestRate(per_second=2.0, burst=3, clock=lambda: now[0])
    assert [rate.take("a") for _ in range(3)] == [0.0, 0.0, 0.0]
    assert rate.take("a") == pytest.approx(0.5)  # one token in half a second
    assert rate.take("b") == 0.0  # another key's bucket is full
    now[0] += 0.25
    assert rate.take("a") == pytest.approx(0.25)
    now[0] += 0.25
    assert rate.take("a") == 0.0
    now[0] += 100.0  # a long pause fills the bucket to its burst, no more
    assert [rate.take("a") for _ in range(4)][-1] == pytest.approx(0.5)


@both_backends
def test_request_rate_answers_429_with_retry_after_per_key(quotaed: Quotaed) -> None:
    quotaed.make_key("rate-a", "device")
    quotaed.make_key("rate-b", "operator")
    with quotaed.http("rate-a") as a, quotaed.http("rate-b") as b, quotaed.http(API_KEY) as admin:
        for _ in range(BURST):
            assert a.get("/api/v1/scenes").status_code == 200
        r = a.get("/api/v1/scenes")
        error = refused(r, 429, "request rate quota", "'rate-a'", "CSA_QUOTA_REQUESTS_PER_SECOND")
        retry_after = int(r.headers["Retry-After"])
        # One token takes 1 / SLOW_RATE = 100 s; the requests before took well under 10 s.
        assert 90 <= retry_after <= 100, retry_after
        assert f"retry in {retry_after} s" in error["message"]
        # A refused request takes no token: still refused, and so are writes.
        refused(a.post("/api/v1/scenes", json={"name": "rate-a-scene"}), 429, "'rate-a'")
        # Another key's bucket is untouched, and admin keys have no rate quota.
        for _ in range(BURST):
            assert b.get("/api/v1/jobs").status_code == 200
        assert b.get("/api/v1/jobs").status_code == 429
        for _ in range(3 * BURST):
            assert admin.get("/api/v1/scenes").status_code == 200
        # /health needs no key and is never limited.
        assert a.get("/health").status_code == 200


def _artifact_count(live: LiveServer) -> int:
    with session_scope(live.services.sessions) as db:
        return db.scalar(select(func.count()).select_from(Artifact)) or 0


def _has_artifact(live: LiveServer, data: bytes) -> bool:
    with session_scope(live.services.sessions) as db:
        return db.get(Artifact, hashlib.sha256(data).hexdigest()) is not None


@both_backends
def test_stored_bytes_quota_refuses_before_storing_and_survives_a_restart(quotaed: Quotaed) -> None:
    quotaed.make_key("bytes-a", "device")
    quotaed.make_key("bytes-b", "device")
    with quotaed.http("bytes-a") as a:
        assert a.post("/api/v1/scenes", json={"name": "bytes-a-scene"}).status_code == 201
        r = a.post("/api/v1/scenes/bytes-a-scene/frames", files=frame_files(1), data={"name": "0"})
        assert r.status_code == 201, r.text
        before = _artifact_count(quotaed.live)
        r = a.post("/api/v1/scenes/bytes-a-scene/frames", files=frame_files(2), data={"name": "1"})
        error = refused(
            r,
            413,
            "stored-bytes quota",
            "'bytes-a'",
            f"is {DEVICE_QUOTA} bytes",
            f"it stores {frame_bytes(1)} bytes",
            "CSA_QUOTA_STORED_BYTES_DEVICE",
        )
        assert error["field"] == "color"
        assert _artifact_count(quotaed.live) == before
        assert not _has_artifact(quotaed.live, frame_parts(2)["color"])
        # The same content again adds nothing: an idempotent re-upload is not refused.
        r = a.post("/api/v1/scenes/bytes-a-scene/frames", files=frame_files(1), data={"name": "0"})
        assert r.status_code == 200, r.text
        # An archive whose frame would go over is refused whole, naming the archive.
        files = {"archive": ("s.tar", archive_of(2, "5"), "application/x-tar")}
        r = a.post("/api/v1/scenes/bytes-a-scene/archive", files=files)
        assert refused(r, 413, "'bytes-a'")["field"] == "archive"
        assert _artifact_count(quotaed.live) == before
        assert a.get("/api/v1/scenes/bytes-a-scene").json()["num_frames"] == 1
    # Another device's quota is its own: it stores the frame that bytes-a could not.
    with quotaed.http("bytes-b") as b:
        assert b.post("/api/v1/scenes", json={"name": "bytes-b-scene"}).status_code == 201
        r = b.post("/api/v1/scenes/bytes-b-scene/frames", files=frame_files(2), data={"name": "0"})
        assert r.status_code == 201, r.text
    # An admin key has no quota, also on the device's scene.
    with quotaed.http(API_KEY) as admin:
        r = admin.post("/api/v1/scenes", json={"name": "bytes-admin-scene"})
        assert r.status_code == 201
        for i in range(3):
            path = "/api/v1/scenes/bytes-admin-scene/frames"
            assert admin.post(path, files=frame_files(10 + i)).status_code == 201

    with session_scope(quotaed.live.services.sessions) as db:
        assert stored_bytes(db, quotaed.key_id("bytes-a")) == frame_bytes(1)
        assert stored_bytes(db, quotaed.key_id("bytes-b")) == frame_bytes(2)

    # A restart (a new app on the same database and folder) keeps the count: still refused.
    settings = quotaed.live.settings
    quotaed.live.stop()
    quotaed.live = start_server(settings)
    with quotaed.http("bytes-a") as a:
        r = a.post("/api/v1/scenes/bytes-a-scene/frames", files=frame_files(2), data={"name": "1"})
        refused(r, 413, f"it stores {frame_bytes(1)} bytes", "'bytes-a'")


@both_backends
def test_checkpoints_count_against_the_key_that_registered_them(quotaed: Quotaed) -> None:
    quotaed.make_key("ckpt-op", "operator")
    data = checkpoint_bytes()
    files = {"checkpoint": ("m.safetensors", data, "application/octet-stream")}
    with quotaed.http("ckpt-op") as op:
        r = op.post("/api/v1/models", files=files, data={"name": "quota-first"})
        assert r.status_code == 201, r.text
        r = op.post("/api/v1/models", files=files, data={"name": "quota-second"})
        error = refused(
            r, 413, "'ckpt-op'", f"it stores {len(data)} bytes", "CSA_QUOTA_STORED_BYTES_OPERATOR"
        )
        assert error["field"] == "checkpoint"
    with session_scope(quotaed.live.services.sessions) as db:
        names = set(db.scalars(select(ModelVersion.name)))
        assert "quota-first" in names and "quota-second" not in names
        assert stored_bytes(db, quotaed.key_id("ckpt-op")) == len(data)


@both_backends
def test_queued_jobs_quota_per_scope(quotaed: Quotaed) -> None:
    quotaed.make_key("jobs-op", "operator")
    quotaed.make_key("jobs-other-op", "operator")
    quotaed.make_key("jobs-device", "device")
    with quotaed.http(API_KEY) as admin:
        assert admin.post("/api/v1/scenes", json={"name": "jobs-scene"}).status_code == 201
        r = admin.post("/api/v1/scenes/jobs-scene/frames", files=frame_files(7))
        assert r.status_code == 201, r.text
        queued = len(admin.get("/api/v1/jobs", params={"status": "queued"}).json())
    assert queued == 0
    body = {"kind": "fit_nerf", "params": {"scene": "jobs-scene", "labels": "ground_truth"}}
    with quotaed.http("jobs-op") as op, quotaed.http("jobs-other-op") as other:
        for _ in range(QUEUED_JOBS):
            r = op.post("/api/v1/jobs", json=body)
            assert r.status_code == 202, r.text
        r = other.post("/api/v1/jobs", json=body)  # the limit is the scope's, not one key's
        refused(
            r,
            429,
            "queued-jobs quota of scope 'operator'",
            f"fewer than {QUEUED_JOBS}",
            "'jobs-other-op'",
            "CSA_QUOTA_QUEUED_JOBS_OPERATOR",
        )
        assert "Retry-After" not in r.headers  # the queue drains at the pace of its jobs
    with quotaed.http("jobs-device") as device:  # device keys may not queue jobs at all
        assert device.post("/api/v1/jobs", json=body).status_code == 403
    with quotaed.http(API_KEY) as admin:  # admin keys have no queue quota
        assert admin.post("/api/v1/jobs", json=body).status_code == 202
        ids = [j["id"] for j in admin.get("/api/v1/jobs", params={"status": "queued"}).json()]
        assert len(ids) == QUEUED_JOBS + 1
        assert admin.post(f"/api/v1/jobs/{ids[0]}/cancel").status_code == 200
        assert admin.post(f"/api/v1/jobs/{ids[1]}/cancel").status_code == 200
    with quotaed.http("jobs-other-op") as other:  # room again once fewer wait
        assert other.post("/api/v1/jobs", json=body).status_code == 202


def test_quota_settings_refuse_negative_values(tmp_path) -> None:
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="quota_stored_bytes_device"):
        test_settings(tmp_path, quota_stored_bytes_device=-1)
