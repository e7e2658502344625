"""Frame uploads over real HTTP: validation errors name the field, re-uploads are idempotent,
failed uploads change nothing, and authentication and 404s behave."""

from __future__ import annotations

import itertools

import cv2
import httpx
import numpy as np
import pytest

from client import AuthError, Conflict, CSAClient, InvalidInput, NotFound, TooLarge
from tests.server.conftest import API_KEY

W, H = 32, 24
K = "30 0 15.5\n0 31 11.5\n0 0 1\n"
POSE = np.eye(4)
_names = itertools.count()


def png(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return buf.tobytes()


def color_png(seed: int = 0, w: int = W, h: int = H) -> bytes:
    return png(np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8))


def depth_png(w: int = W, h: int = H) -> bytes:
    return png(np.full((h, w), 1500, np.uint16))


@pytest.fixture
def scene(client: CSAClient) -> str:
    name = f"upload-{next(_names)}"
    client.create_scene(name)
    return name


def upload_first(client: CSAClient, scene: str, **kw):
    args = {
        "color": color_png(),
        "depth": depth_png(),
        "pose": POSE,
        "intrinsics": K.encode(),
        "name": "0",
    }
    args.update(kw)
    return client.upload_frame(scene, **args)


def test_upload_is_idempotent_and_conflicts_are_refused(client: CSAClient, scene: str) -> None:
    first = upload_first(client, scene)
    assert first.created and first.name == "0"
    again = upload_first(client, scene)
    assert not again.created and again.id == first.id
    assert len(client.frames(scene)) == 1
    with pytest.raises(Conflict) as e:
        upload_first(client, scene, color=color_png(seed=1))
    assert e.value.field == "name"
    replaced = upload_first(client, scene, color=color_png(seed=1), replace=True)
    assert replaced.replaced and replaced.id == first.id
    assert len(client.frames(scene)) == 1
    # Without a name, identical content finds the stored frame; new content gets the next number.
    assert client.upload_frame(scene, color_png(seed=1), depth_png(), POSE).name == "0"
    assert client.upload_frame(scene, color_png(seed=2), depth_png(), POSE).name == "1"


@pytest.mark.parametrize(
    ("field", "kwargs", "message"),
    [
        ("color", {"color": b"definitely not an image"}, "color: not a PNG or JPEG file"),
        ("color", {"color": b"\x89PNG\r\n\x1a\n" + b"\x00" * 40}, "color: unreadable PNG header"),
        ("depth", {"depth": depth_png(20, 20)}, "size mismatch"),
        ("depth", {"depth": png(np.full((H, W), 9, np.uint8))}, "uint16"),
        ("depth", {"depth": png(np.zeros((H, W, 3), np.uint16))}, "single-channel"),
        (
            "pose",
            {"pose": [[1, 0, 0, 0], [0, 1, 0, float("nan")], [0, 0, 1, 0], [0, 0, 0, 1]]},
            "not finite",
        ),
        ("pose", {"pose": b"1 0 0\n0 1 0\n0 0 1\n"}, "4x4"),
        ("pose", {"pose": b"1 0 0 0\n0 1 0 0\n0 0 1 0\n1 1 1 1\n"}, "0 0 0 1"),
        ("pose", {"pose": b"a b c d\n"}, "numeric"),
        ("intrinsics", {"intrinsics": b"0 0 1\n0 0 1\n0 0 1\n"}, "positive"),
        ("labels", {"labels": png(np.full((H, W), 77, np.uint8))}, "out of range"),
        ("labels", {"labels": png(np.ones((10, 30), np.uint8))}, "size mismatch"),
        ("name", {"name": "../x"}, "frame name"),
    ],
)
def test_bad_frames_are_refused_naming_the_field(
    client: CSAClient, scene: str, field: str, kwargs: dict, message: str
) -> None:
    with pytest.raises(InvalidInput) as e:
        upload_first(client, scene, **kwargs)
    assert e.value.status == 422 and e.value.field == field
    assert message in str(e.value)
    assert client.frames(scene) == []


def test_first_frame_needs_intrinsics_and_later_frames_must_match(
    client: CSAClient, scene: str
) -> None:
    with pytest.raises(InvalidInput) as e:
        client.upload_frame(scene, color_png(), depth_png(), POSE, name="0")
    assert e.value.field == "intrinsics"
    upload_first(client, scene)
    with pytest.raises(InvalidInput) as e:
        client.upload_frame(scene, color_png(3, 64, 48), depth_png(64, 48), POSE, name="1")
    assert e.value.field == "color" and "size mismatch" in str(e.value)
    with pytest.raises(InvalidInput) as e:
        client.upload_frame(
            scene,
            color_png(3),
            depth_png(),
            POSE,
            intrinsics=b"40 0 15.5\n0 31 11.5\n0 0 1\n",
            name="1",
        )
    assert e.value.field == "intrinsics"


def test_failed_upload_keeps_what_was_stored(api_server, client: CSAClient, scene: str) -> None:
    stored = upload_first(client, scene)
    with pytest.raises(InvalidInput):
        upload_first(client, scene, color=color_png(seed=9), depth=b"junk", replace=True)
    (frame,) = client.frames(scene)
    assert (
        frame.id == stored.id
        and frame.model_dump()["color_sha256"] == stored.model_dump()["color_sha256"]
    )
    services = api_server.services
    with services.sessions() as s:
        assert services.store.verify(s).ok


def test_oversize_upload_is_refused_before_it_is_stored(client: CSAClient, scene: str) -> None:
    big = color_png() + b"\x00" * 250_000  # over the 200 kB test limit per part
    with pytest.raises(TooLarge) as e:
        upload_first(client, scene, color=big)
    assert e.value.status == 413
    huge_body = b"x" * (7 * 200_000 + 2 * 1024 * 1024)
    with pytest.raises(TooLarge):
        upload_first(client, scene, labels=huge_body)
    assert client.frames(scene) == []


def test_api_key_is_required_everywhere_but_health(api_server) -> None:
    with httpx.Client(base_url=api_server.url, timeout=10) as http:
        assert http.get("/health").status_code == 200
        for path in (
            "/api/v1/scenes",
            "/api/v1/jobs",
            "/api/v1/models",
            "/api/v1/memory",
            "/metrics",
        ):
            r = http.get(path)
            assert r.status_code == 401 and r.json()["error"]["code"] == "unauthorized", path
        assert http.get("/api/v1/scenes", headers={"X-API-Key": "wrong"}).status_code == 401
        assert (
            http.get("/api/v1/scenes", headers={"Authorization": f"Bearer {API_KEY}"}).status_code
            == 200
        )
    with api_server.client(api_key="") as anonymous, pytest.raises(AuthError):
        anonymous.scenes()


def test_unknown_ids_are_404(client: CSAClient, scene: str) -> None:
    calls = [
        lambda: client.scene("no-such-scene"),
        lambda: client.scene(987654),
        lambda: client.job(987654),
        lambda: client.model(987654),
        lambda: client.model("no-such-model"),
        lambda: client.scene_nerf(scene),
        lambda: client.frames("no-such-scene"),
        lambda: client.cancel_job(987654),
        lambda: client.job_log(987654),
    ]
    for call in calls:
        with pytest.raises(NotFound) as e:
            call()
        assert e.value.status == 404
    with httpx.Client(base_url=client.base_url, headers={"X-API-Key": API_KEY}, timeout=10) as http:
        r = http.get(f"/api/v1/scenes/{scene}/frames/999/color")
        assert r.status_code == 404 and r.json()["error"]["code"] == "not_found"


def test_scene_names_are_validated_and_unique(client: CSAClient, scene: str) -> None:
    with pytest.raises(Conflict):
        client.create_scene(scene)
    for bad in ("", "12345", "../etc", "a" * 200, "has space"):
        with pytest.raises(InvalidInput) as e:
            client.create_scene(bad)
        assert e.value.field == "name"


def test_frame_files_download_with_their_checksum(client: CSAClient, scene: str) -> None:
    data = color_png(seed=5)
    upload_first(client, scene, color=data)
    with httpx.Client(base_url=client.base_url, headers={"X-API-Key": API_KEY}, timeout=10) as http:
        r = http.get(f"/api/v1/scenes/{scene}/frames/0/color")
        assert (
            r.status_code == 200 and r.content == data and r.headers["content-type"] == "image/png"
        )


def test_deleting_a_scene_removes_its_files_and_keeps_the_others(
    api_server, client: CSAClient
) -> None:
    keep, drop = f"keep-{next(_names)}", f"drop-{next(_names)}"
    client.create_scene(keep)
    client.create_scene(drop)
    upload_first(client, keep, color=color_png(seed=20))
    gone = upload_first(client, drop, color=color_png(seed=21))
    shared = upload_first(client, drop, color=color_png(seed=20), name="1")  # same bytes as `keep`
    store = api_server.services.store
    client.delete_scene(drop)
    with pytest.raises(NotFound):
        client.scene(drop)
    assert not store.path_of(gone.model_dump()["color_sha256"]).exists()
    assert store.path_of(shared.model_dump()["color_sha256"]).exists()  # still used by `keep`
    with api_server.services.sessions() as s:
        assert store.verify(s).ok
    assert len(client.frames(keep)) == 1
