"""A hostile client against a real server, on SQLite and on PostgreSQL: every route that takes
a pose, a camera or an image size answers absurd numbers with a 4xx naming the field, never a
5xx, nothing is stored, and the client's keep-alive connection keeps working afterwards.

Property-based (hypothesis, derandomised, a bounded number of examples): finite but absurd
numbers (1e308, -1e308, 1e-308, 0, integers of 30 and 5000 digits), scaled, sheared and
mirrored matrices, cameras far away, focal lengths and principal points out of range, image
sizes beyond the limits. Every generated case is invalid by construction (no oracle that
copies the rules), except in the test of valid extremes, which must render.
"""

from __future__ import annotations

import base64
import io
import itertools
import tarfile
from collections.abc import Iterator
from dataclasses import dataclass

import cv2
import httpx
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from csa_core.data.camera import (
    FOCAL_RATIO_RANGE,
    MAX_SIZE_PX,
    MAX_TRANSLATION_M,
    PRINCIPAL_POINT_MARGIN,
)
from server import capabilities
from tests.server.conftest import (
    API_KEY,
    LiveServer,
    both_backends,
    database_url,
    start_server,
    test_settings,
)

pytestmark = both_backends

EXAMPLES = settings(
    max_examples=20,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=list(HealthCheck),
)
W, H = 40, 30  # the synthetic scene's size
K = {"fx": 30.0, "fy": 30.0, "cx": 19.5, "cy": 14.5, "width": W, "height": H}
TINY_NERF = {"steps": 30, "rays_per_step": 128, "occupancy_resolution": 16, "log2_table_size": 10}

# Finite JSON numbers that no pose, camera or size may hold; "9"*5000 is past Python's limit for
# integer parsing (the server must still answer 4xx).
HUGE = [
    "1e308",
    "-1e308",
    "1.7976931348623157e308",
    "1e300",
    "123456789012345678901234567890",
    "-99999999999999999999",
    "9" * 5000,
]
TINY = ["1e-308", "-1e-308", "5e-324", "0", "-0.0"]
_names = itertools.count()


def png(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return buf.tobytes()


def local_port(r: httpx.Response) -> int | None:
    """The client side port of the connection that carried ``r``; None once it is closed."""
    try:
        return r.extensions["network_stream"].get_extra_info("client_addr")[1]
    except OSError:
        return None


def matrix_text(cells: list[list[str]]) -> str:
    return "\n".join(" ".join(row) for row in cells) + "\n"


def json_matrix(cells: list[list[str]]) -> str:
    return "[" + ",".join("[" + ",".join(row) + "]" for row in cells) + "]"


def lit(x: float) -> str:
    return repr(float(x))


@dataclass
class Hostile:
    live: LiveServer
    http: httpx.Client
    scene: str  # 8 frames of 40x30 and, when the build has it, a NeRF
    bare: str  # no frames yet: the first frame's intrinsics are checked on their own
    has_nerf: bool
    has_model: bool

    def still_connected(self, before: httpx.Response) -> None:
        """The connection that carried ``before`` serves the next request."""
        assert before.headers.get("connection", "").lower() != "close"
        port = local_port(before)
        after = self.http.get(f"/api/v1/scenes/{self.bare}")
        assert after.status_code == 200
        assert port is not None and local_port(after) == port, (
            "the server dropped the keep-alive connection"
        )

    def refused(self, r: httpx.Response, field: str | None = None) -> dict:
        assert 400 <= r.status_code < 500, f"{r.status_code}: {r.text[:300]}"
        body = r.json()["error"]
        if field is not None:
            assert body["field"] == field, body
        self.still_connected(r)
        return body

    def frames(self, scene: str) -> int:
        return len(self.http.get(f"/api/v1/scenes/{scene}/frames").json())


@pytest.fixture(scope="module")
def hostile(request, tmp_path_factory, db_backend: str, synth_scene) -> Iterator[Hostile]:
    settings_ = test_settings(
        tmp_path_factory.mktemp("hostile"),
        database_url=database_url(request, db_backend),
        max_image_pixels=2_000_000,
    )
    live = start_server(settings_)
    with (
        live.client() as c,
        httpx.Client(base_url=live.url, headers={"X-API-Key": API_KEY}, timeout=60) as http,
    ):
        scene, _ = c.upload_scene_folder(synth_scene)
        bare = c.create_scene(f"bare-{db_backend}").name
        has_model = has_nerf = False
        if capabilities.available("seg"):
            c.wait_job(
                c.pretrain([scene.name], epochs=1, batch_size=4, name="hostile-base").id,
                timeout=300,
            )
            has_model = True
        if capabilities.available("nerf"):
            c.wait_job(
                c.create_job("fit_nerf", scene=scene.name, labels="ground_truth", **TINY_NERF).id,
                timeout=300,
            )
            has_nerf = True
        yield Hostile(live, http, scene.name, bare, has_nerf, has_model)
    live.stop()


# --- strategies: every case is invalid by construction ---------------------------------------

angles = st.tuples(*[st.floats(-np.pi, np.pi)] * 3)


def rotation(a: float, b: float, c: float) -> np.ndarray:
    rx = cv2.Rodrigues(np.array([a, 0.0, 0.0]))[0]
    ry = cv2.Rodrigues(np.array([0.0, b, 0.0]))[0]
    rz = cv2.Rodrigues(np.array([0.0, 0.0, c]))[0]
    return rz @ ry @ rx


@st.composite
def bad_poses(draw) -> list[list[str]]:
    """A 4x4 camera-to-world matrix as number literals that is not a bounded rigid transform."""
    pose = np.eye(4)
    pose[:3, :3] = rotation(*draw(angles))
    pose[:3, 3] = draw(st.tuples(*[st.floats(-5, 5)] * 3))
    kind = draw(
        st.sampled_from(
            ["scale", "shear", "reflection", "far", "last_row", "huge_entry", "degenerate"]
        )
    )
    if kind == "scale":
        pose[:3, :3] *= draw(st.sampled_from([5.0, 0.2, 1.01, 0.99, 1e154]))
    elif kind == "shear":
        i, j = draw(st.sampled_from([(0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1)]))
        shear = np.eye(3)
        shear[i, j] = draw(st.sampled_from([0.01, -0.5, 3.0, 1e100]))
        pose[:3, :3] = pose[:3, :3] @ shear
    elif kind == "reflection":
        pose[:3, draw(st.integers(0, 2))] *= -1
    elif kind == "far":
        direction = pose[:3, 0]  # any unit vector
        pose[:3, 3] = direction * draw(
            st.sampled_from([MAX_TRANSLATION_M * 1.001, 1e6, 1e154, 1e308])
        )
    elif kind == "last_row":
        pose[3, draw(st.integers(0, 3))] = draw(st.sampled_from([0.5, 2.0, -1.0, 1e308]))
    elif kind == "degenerate":
        pose[:3, :3] *= draw(st.sampled_from([0.0, 1e-308, 5e-324]))
    cells = [[lit(v) for v in row] for row in pose]
    if kind == "huge_entry":
        for k in draw(st.lists(st.integers(0, 15), min_size=1, max_size=4, unique=True)):
            cells[k // 4][k % 4] = draw(st.sampled_from(HUGE))
    return cells


@st.composite
def bad_cameras(draw) -> dict[str, str]:
    """Intrinsics (number literals) of a 40x30 image with one absurd value."""
    lo, hi = FOCAL_RATIO_RANGE
    m = PRINCIPAL_POINT_MARGIN
    camera = {k: lit(v) if isinstance(v, float) else str(v) for k, v in K.items()}
    key = draw(st.sampled_from(["fx", "fy", "cx", "cy", "width", "height"]))
    side = W if key in ("fx", "cx", "width") else H
    choices = {
        "fx": [*TINY, "-1", lit(lo * side * 0.99), lit(hi * side * 1.01), *HUGE],
        "cx": [lit(-m * side - 1), lit((1 + m) * side + 1), *HUGE],
        "width": [
            "0",
            "-1",
            str(MAX_SIZE_PX + 1),
            str(2**31),
            str(2**63),
            "1e308",
            "40.5",
            *HUGE[4:],
        ],
    }
    group = {"fy": "fx", "cy": "cx", "height": "width"}.get(key, key)
    camera[key] = draw(st.sampled_from(choices[group]))
    return camera


def camera_json(camera: dict[str, str]) -> str:
    return "{" + ",".join(f'"{k}":{v}' for k, v in camera.items()) + "}"


def camera_text(camera: dict[str, str]) -> str:
    return matrix_text(
        [[camera["fx"], "0", camera["cx"]], ["0", camera["fy"], camera["cy"]], ["0", "0", "1"]]
    )


bad_sizes = st.sampled_from([(0, 30), (40, 0), (7, 30), (MAX_SIZE_PX + 1, 8), (9999, 9999)])
images_too_large = st.sampled_from([(MAX_SIZE_PX + 1, 1), (1, MAX_SIZE_PX + 1), (20_000, 2)])


def frame_files(
    pose: str, color_size=(W, H), depth_size=(W, H), intrinsics: str | None = None
) -> dict:
    files = {
        "color": (
            "c.png",
            png(np.full((color_size[1], color_size[0], 3), 128, np.uint8)),
            "image/png",
        ),
        "depth": (
            "d.png",
            png(np.full((depth_size[1], depth_size[0]), 1500, np.uint16)),
            "image/png",
        ),
        "pose": ("p.txt", pose.encode(), "text/plain"),
    }
    if intrinsics is not None:
        files["intrinsics"] = ("k.txt", intrinsics.encode(), "text/plain")
    return files


def archive_with(pose: str, intrinsics: str) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tf:
        for name, data in {
            "color/0.png": png(np.full((H, W, 3), 99, np.uint8)),
            "depth/0.png": png(np.full((H, W), 1200, np.uint16)),
            "pose/0.txt": pose.encode(),
            "intrinsic/intrinsic_color.txt": intrinsics.encode(),
        }.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
    return buf.getvalue()


IDENTITY = [[lit(v) for v in row] for row in np.eye(4)]
GOOD_K = camera_text({k: lit(v) if isinstance(v, float) else str(v) for k, v in K.items()})


# --- the reported cases ----------------------------------------------------------------------


def test_a_pose_with_scale_five_is_refused_and_nothing_is_stored(hostile: Hostile) -> None:
    scaled = matrix_text([[lit(v) for v in row] for row in np.diag([5.0, 5.0, 5.0, 1.0])])
    before = hostile.frames(hostile.scene)
    r = hostile.http.post(
        f"/api/v1/scenes/{hostile.scene}/frames", files=frame_files(scaled), data={"name": "scaled"}
    )
    body = hostile.refused(r, field="pose")
    assert (
        r.status_code == 422 and "not orthonormal" in body["message"] and "rigid" in body["message"]
    )
    archive = archive_with(scaled, GOOD_K)
    r = hostile.http.post(
        f"/api/v1/scenes/{hostile.bare}/archive",
        files={"archive": ("s.tar", archive, "application/x-tar")},
    )
    assert hostile.refused(r, field="archive:pose/0.txt")["message"].startswith(
        "archive:pose/0.txt: rotation part is not orthonormal"
    )
    assert hostile.frames(hostile.scene) == before and hostile.frames(hostile.bare) == 0


def test_a_render_pose_holding_1e308_is_422_and_the_connection_survives(hostile: Hostile) -> None:
    pose = [row[:] for row in IDENTITY]
    pose[0][3] = "1e308"
    r = hostile.http.post(
        f"/api/v1/scenes/{hostile.scene}/render",
        content=f'{{"pose": {json_matrix(pose)}}}',
        headers={"content-type": "application/json"},
    )
    body = hostile.refused(r, field="pose")
    assert r.status_code == 422 and "translation is 1e+308 m from the origin" in body["message"]
    if hostile.has_nerf:  # the next real request on the same connection renders
        ok = hostile.http.post(
            f"/api/v1/scenes/{hostile.scene}/render",
            json={"pose": np.eye(4).tolist(), "channels": ["depth"]},
        )
        assert ok.status_code == 200 and local_port(ok) == local_port(r) is not None


def test_an_unexpected_error_answers_500_and_keeps_the_connection(
    hostile: Hostile, monkeypatch
) -> None:
    """A bug in a route (simulated) is a JSON 500, and the connection stays usable."""
    from server.services import scenes

    def broken(*_args, **_kw):
        raise RuntimeError("simulated bug")

    monkeypatch.setattr(scenes, "scene_out", broken)
    r = hostile.http.get(f"/api/v1/scenes/{hostile.scene}")
    assert r.status_code == 500 and r.json()["error"] == {
        "code": "internal",
        "message": "internal error: RuntimeError",
        "field": None,
    }
    monkeypatch.undo()
    hostile.still_connected(r)


@pytest.mark.parametrize(
    ("method", "path", "body", "status"),
    [
        ("GET", "/api/v1/jobs/99999999999", None, 422),
        ("GET", "/api/v1/jobs/2147483648", None, 422),
        ("GET", "/api/v1/scenes/99999999999", None, 404),
        ("GET", "/api/v1/scenes/%C2%B2", None, 404),  # "²" is a digit to str.isdigit, not to int()
        ("GET", "/api/v1/models/99999999999999999999", None, 404),
        ("GET", "/api/v1/scenes/a%00b", None, None),
        ("GET", "/api/v1/jobs?kind=a%00b", None, 422),
        ("GET", "/api/v1/models?lineage=a%00b", None, 422),
        ("POST", "/api/v1/scenes", {"name": "nul-description", "description": "a\u0000b"}, 422),
        ("POST", "/api/v1/jobs", {"kind": "evaluate", "params": {"scenes": [99999999999]}}, 422),
        ("POST", "/api/v1/jobs", {"kind": "fit_nerf", "params": {"scene": 2147483647}}, 404),
    ],
)
def test_ids_and_strings_the_database_cannot_hold_answer_4xx(
    hostile: Hostile, method: str, path: str, body, status: int | None
) -> None:
    r = hostile.http.request(method, path, json=body)
    assert r.status_code == status if status is not None else 400 <= r.status_code < 500, r.text[
        :300
    ]
    hostile.still_connected(r)


def test_a_frame_name_beyond_the_order_key_range_is_refused(hostile: Hostile) -> None:
    r = hostile.http.post(
        f"/api/v1/scenes/{hostile.bare}/frames",
        files=frame_files(matrix_text(IDENTITY), intrinsics=GOOD_K),
        data={"name": "99999999999"},
    )
    assert "larger than 2147483647" in hostile.refused(r, field="name")["message"]


# --- properties ------------------------------------------------------------------------------


@EXAMPLES
@given(pose=bad_poses())
def test_render_refuses_every_non_rigid_or_unbounded_pose(hostile: Hostile, pose) -> None:
    r = hostile.http.post(
        f"/api/v1/scenes/{hostile.scene}/render",
        content=f'{{"pose": {json_matrix(pose)}}}',
        headers={"content-type": "application/json"},
    )
    hostile.refused(r)
    if r.status_code == 422 and r.json()["error"]["field"] is not None:
        assert r.json()["error"]["field"].startswith("pose")


@EXAMPLES
@given(camera=bad_cameras())
def test_render_refuses_every_absurd_camera(hostile: Hostile, camera) -> None:
    body = f'{{"pose": {json_matrix(IDENTITY)}, "intrinsics": {camera_json(camera)}}}'
    r = hostile.http.post(
        f"/api/v1/scenes/{hostile.scene}/render",
        content=body,
        headers={"content-type": "application/json"},
    )
    error = hostile.refused(r)
    if r.status_code == 422 and error["field"] is not None:
        assert error["field"].startswith("intrinsics")


@EXAMPLES
@given(pose=bad_poses(), camera=bad_cameras(), which=st.sampled_from(["pose", "intrinsics"]))
def test_frame_uploads_refuse_absurd_poses_and_cameras(
    hostile: Hostile, pose, camera, which: str
) -> None:
    if which == "pose":
        files = frame_files(matrix_text(pose), intrinsics=GOOD_K)
    else:
        if camera["width"] != str(W) or camera["height"] != str(H):
            return  # the file holds no size: the image gives it (sizes have their own test)
        files = frame_files(matrix_text(IDENTITY), intrinsics=camera_text(camera))
    r = hostile.http.post(
        f"/api/v1/scenes/{hostile.bare}/frames", files=files, data={"name": f"f{next(_names)}"}
    )
    hostile.refused(r, field=which)
    assert hostile.frames(hostile.bare) == 0


@EXAMPLES
@given(pose=bad_poses(), camera=bad_cameras(), which=st.sampled_from(["pose", "intrinsics"]))
def test_archives_refuse_absurd_poses_and_cameras(
    hostile: Hostile, pose, camera, which: str
) -> None:
    if which == "intrinsics" and (camera["width"] != str(W) or camera["height"] != str(H)):
        return
    archive = (
        archive_with(matrix_text(pose), GOOD_K)
        if which == "pose"
        else archive_with(matrix_text(IDENTITY), camera_text(camera))
    )
    r = hostile.http.post(
        f"/api/v1/scenes/{hostile.bare}/archive",
        files={"archive": ("s.tar", archive, "application/x-tar")},
    )
    hostile.refused(r)
    assert hostile.frames(hostile.bare) == 0


@EXAMPLES
@given(
    size=bad_sizes,
    steps=st.sampled_from(
        ["0", "-1", "200001", str(2**63), "1e308", "123456789012345678901234567890"]
    ),
    which=st.sampled_from(["fit_nerf.size", "fit_nerf.steps", "pretrain.size"]),
)
def test_jobs_refuse_absurd_sizes_and_counts(
    hostile: Hostile, size, steps: str, which: str
) -> None:
    kind, key = which.split(".")
    value = f'"{size[0]}x{size[1]}"' if key == "size" else steps
    target = (
        f'"scenes": ["{hostile.scene}"]' if kind == "pretrain" else f'"scene": "{hostile.scene}"'
    )
    before = len(hostile.http.get("/api/v1/jobs").json())
    r = hostile.http.post(
        "/api/v1/jobs",
        content=f'{{"kind": "{kind}", "params": {{{target}, "{key}": {value}}}}}',
        headers={"content-type": "application/json"},
    )
    assert hostile.refused(r, field=f"{kind}.params.{key}") and r.status_code == 422
    assert len(hostile.http.get("/api/v1/jobs").json()) == before


@EXAMPLES
@given(size=images_too_large, part=st.sampled_from(["color", "depth"]))
def test_frame_uploads_refuse_images_beyond_the_size_limits(
    hostile: Hostile, size, part: str
) -> None:
    w, h = size
    intr = (
        camera_text({"fx": lit(w), "fy": lit(h), "cx": lit(w / 2), "cy": lit(h / 2)})
        if part == "color"
        else GOOD_K
    )
    files = frame_files(
        matrix_text(IDENTITY),
        color_size=size if part == "color" else (W, H),
        depth_size=size if part == "depth" else (W, H),
        intrinsics=intr,
    )
    r = hostile.http.post(
        f"/api/v1/scenes/{hostile.bare}/frames", files=files, data={"name": f"f{next(_names)}"}
    )
    hostile.refused(r)
    assert hostile.frames(hostile.bare) == 0


@settings(
    max_examples=6,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=list(HealthCheck),
)
@given(size=st.sampled_from([(1, 1), (1, 700), (700, 1), (MAX_SIZE_PX + 1, 1), (2000, 1001)]))
def test_predict_never_fails_on_odd_image_sizes(hostile: Hostile, size) -> None:
    """Tiny and thin images are labelled (200) or refused (4xx: too many pixels), never a 5xx."""
    if not hostile.has_model:
        pytest.skip("csa_core.seg is not available in this build")
    w, h = size
    r = hostile.http.post(
        "/api/v1/predict",
        files={"image": ("i.png", png(np.full((h, w, 3), 77, np.uint8)), "image/png")},
    )
    if w * h > 2_000_000:
        hostile.refused(r, field="image")
    else:
        assert r.status_code == 200, r.text[:300]
        labels = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_UNCHANGED)
        assert labels.shape == (h, w)
        hostile.still_connected(r)


@settings(
    max_examples=12,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=list(HealthCheck),
)
@given(
    rot=angles,
    distance=st.sampled_from([0.0, 1.0, 100.0, MAX_TRANSLATION_M * 0.999]),
    fx_ratio=st.sampled_from([FOCAL_RATIO_RANGE[0], 1.0, FOCAL_RATIO_RANGE[1]]),
    cx_at=st.sampled_from([-PRINCIPAL_POINT_MARGIN, 0.5, 1 + PRINCIPAL_POINT_MARGIN]),
    size=st.sampled_from([(1, 1), (5, 3), (16, 12)]),
)
def test_render_at_the_limits_of_what_is_valid_answers_200(
    hostile: Hostile, rot, distance, fx_ratio, cx_at, size
) -> None:
    """The other side of the rules: a far camera with an extreme lens still renders, with no
    NaN reaching the images (the depth PNG holds 0 where nothing was hit)."""
    if not hostile.has_nerf:
        pytest.skip("csa_core.nerf is not available in this build")
    w, h = size
    pose = np.eye(4)
    pose[:3, :3] = rotation(*rot)
    pose[:3, 3] = pose[:3, 2] * -distance + np.array([0.0, 0.0, 1.0])
    camera = {
        "fx": fx_ratio * w,
        "fy": fx_ratio * h,
        "cx": cx_at * w,
        "cy": cx_at * h,
        "width": w,
        "height": h,
    }
    r = hostile.http.post(
        f"/api/v1/scenes/{hostile.scene}/render",
        json={"pose": pose.tolist(), "intrinsics": camera, "channels": ["color", "depth"]},
    )
    assert r.status_code == 200, r.text[:300]
    out = r.json()
    assert (out["width"], out["height"]) == (w, h)
    depth = cv2.imdecode(
        np.frombuffer(base64.b64decode(out["images"]["depth"]), np.uint8), cv2.IMREAD_UNCHANGED
    )
    assert depth.shape == (h, w) and depth.dtype == np.uint16
    hostile.still_connected(r)
