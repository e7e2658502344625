"""Hostile clients over real HTTP, beyond the absurd numbers of test_hardening.py: archives whose
entries do not map to one file each, corrupt compressed streams, intrinsic matrices that are not
pinhole matrices, a second depth camera sneaked into a scene, forged model cards (non-finite
metrics too), uploads racing a scene's deletion, job parameters that would make a job read a
scene twice or at sizes no frame has, uploads that would hold the event loop, invented HTTP
methods, non-ASCII CSRF tokens, bodies without a length, labels sent as JPEG, progressive JPEGs
of thousands of scans and model cards holding numbers or text no database or answer can hold.
Every answer is a 4xx whose ``field`` names the culprit, nothing is stored, and no error message
shows a path of the server.

SQLite only, no worker (queued jobs never run): the rules live in the request path.
"""

from __future__ import annotations

import functools
import io
import itertools
import json
import random
import shutil
import tarfile
import zipfile
from collections.abc import Iterator
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest

from csa_core.errors import CSAInputError
from server.image_headers import MAX_JPEG_SCANS
from tests.server.conftest import API_KEY, LiveServer
from tests.server.test_image_headers import with_extra_scans

W, H = 32, 24
K = "30 0 15.5\n0 31 11.5\n0 0 1\n"
POSE = "1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n"
_names = itertools.count()


def png(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return buf.tobytes()


def jpg(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".jpg", img)
    assert ok
    return buf.tobytes()


def color(seed: int = 0, w: int = W, h: int = H) -> bytes:
    return png(np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8))


def depth(w: int = W, h: int = H) -> bytes:
    return png(np.full((h, w), 1500, np.uint16))


def labels(value: int = 3) -> bytes:
    return png(np.full((H, W), value, np.uint8))


SCENE = {
    "color/0.png": color(),
    "depth/0.png": depth(),
    "pose/0.txt": POSE.encode(),
    "intrinsic/intrinsic_color.txt": K.encode(),
}


@pytest.fixture
def http(api_server: LiveServer) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=api_server.url, headers={"X-API-Key": API_KEY}, timeout=30) as c:
        yield c


def new_scene(http: httpx.Client) -> str:
    name = f"hostile-{next(_names)}"
    assert http.post("/api/v1/scenes", json={"name": name}).status_code == 201
    return name


def frame_count(http: httpx.Client, scene: str) -> int:
    r = http.get(f"/api/v1/scenes/{scene}/frames")
    assert r.status_code == 200
    return len(r.json())


def refused(r: httpx.Response, status: int, field: str, *words: str) -> str:
    """The answer is ``status`` with ``field`` named; returns the message (which has ``words``)."""
    assert r.status_code == status, f"{r.status_code}: {r.text[:400]}"
    error = r.json()["error"]
    assert error["field"] == field, error
    for word in words:
        assert word in error["message"], error
    return error["message"]


def tar_of(entries: list[tuple[str, bytes | None]], mode: str = "w") -> bytes:
    """A tar of files (bytes) and folders (None), in this order, duplicates kept."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode=mode) as tf:
        for name, data in entries:
            info = tarfile.TarInfo(name)
            if data is None:
                info.type = tarfile.DIRTYPE
                tf.addfile(info)
            else:
                info.size = len(data)
                tf.addfile(info, io.BytesIO(data))
    return buf.getvalue()


def zip_of(entries: list[tuple[str, bytes]], compression: int = zipfile.ZIP_STORED) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression) as zf:
        for i, (name, data) in enumerate(entries):
            if any(n == name for n, _ in entries[:i]):
                with pytest.warns(UserWarning, match="Duplicate name"):
                    zf.writestr(name, data)
            else:
                zf.writestr(name, data)
    return buf.getvalue()


def upload_archive(http: httpx.Client, scene: str, data: bytes) -> httpx.Response:
    return http.post(
        f"/api/v1/scenes/{scene}/archive",
        files={"archive": ("scene.bin", data, "application/octet-stream")},
    )


def upload_frame(
    http: httpx.Client, scene: str, name: str, **parts: bytes | None
) -> httpx.Response:
    files = {"color": color(), "depth": depth(), "pose": POSE.encode(), "intrinsics": K.encode()}
    files.update(parts)
    return http.post(
        f"/api/v1/scenes/{scene}/frames",
        files={k: (k, v, "application/octet-stream") for k, v in files.items() if v is not None},
        data={"name": name},
    )


# --- archives ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("extra", "field", "problem"),
    [
        (
            [("color/1.png", None), ("depth/1.png", depth()), ("pose/1.txt", POSE.encode())],
            "archive:color/1.png",
            "is a folder",
        ),
        (
            [("color/0.jpg", jpg(np.zeros((H, W, 3), np.uint8)))],
            "archive:color/0.png",
            "two colour images (0.jpg and 0.png)",
        ),
        ([("pose/0.txt", None)], "archive:pose/0.txt", "is a folder"),
        (
            [("intrinsic/intrinsic_depth.txt", None)],
            "archive:intrinsic/intrinsic_depth.txt",
            "is a folder",
        ),
        ([("label-nyu40/0.png", None)], "archive:label-nyu40/0.png", "is a folder"),
    ],
    ids=[
        "colour-folder",
        "two-colour-images",
        "pose-folder",
        "depth-intrinsics-folder",
        "labels-folder",
    ],
)
def test_archive_entries_that_are_not_one_file_per_part_are_refused(
    http: httpx.Client, extra, field: str, problem: str
) -> None:
    """A colour folder named like an image used to end in a 500 (StopIteration); two images for
    one frame or a part that is a folder were picked or skipped without a word."""
    entries = [(n, d) for n, d in SCENE.items() if not any(n == e for e, _ in extra)] + extra
    scene = new_scene(http)
    refused(upload_archive(http, scene, tar_of(entries)), 422, field, problem)
    assert frame_count(http, scene) == 0


def test_archive_colour_suffixes_in_any_case_are_read(http: httpx.Client) -> None:
    """``0.Png`` counts as a frame (as the scene reader counts it) and is stored, not a 500."""
    entries = [
        ("color/0.Png", SCENE["color/0.png"]),
        *[(n, d) for n, d in SCENE.items() if not n.startswith("color/")],
    ]
    scene = new_scene(http)
    r = upload_archive(http, scene, tar_of(entries))
    assert r.status_code == 200 and r.json()["added"] == ["0"], r.text[:300]


@pytest.mark.parametrize(
    ("archive", "problem"),
    [
        (
            lambda: zip_of([*SCENE.items(), ("color/0.png", color(seed=7))]),
            "'color/0.png': the archive holds this path twice",
        ),
        (
            lambda: tar_of([*SCENE.items(), ("color/0.png", color(seed=7))]),
            "'color/0.png': the archive holds this path twice",
        ),
        (
            lambda: tar_of([*SCENE.items(), ("pose/0.txt/x", b"1")]),
            "'pose/0.txt' is a file in this archive, not a folder",
        ),
        (
            lambda: tar_of([("color", None), *SCENE.items(), ("color", b"junk")]),
            "'color': the archive holds this path as a folder and as a file",
        ),
    ],
    ids=[
        "zip-same-name-twice",
        "tar-same-name-twice",
        "tar-file-then-folder",
        "tar-folder-then-file",
    ],
)
def test_archives_naming_one_path_twice_are_refused(
    http: httpx.Client, archive, problem: str
) -> None:
    """Which of two same-named entries wins differs between tools: the upload is refused
    instead of silently keeping the last one (or failing on the server's own file system)."""
    scene = new_scene(http)
    message = refused(upload_archive(http, scene, archive()), 422, "archive", problem)
    assert "/tmp" not in message and "csa-archive" not in message
    assert frame_count(http, scene) == 0


def corrupt(data: bytes, start: int, count: int, seed: int = 0) -> bytes:
    b = bytearray(data)
    rng = random.Random(seed)
    for k in range(start, start + count):
        b[k] = rng.randrange(256)
    return bytes(b)


def deflated_zip_with_bad_stream() -> bytes:
    """A zip whose first member's deflate stream is garbage (zlib raises, not zipfile)."""
    data = zip_of(
        [("color/0.png", random.Random(1).randbytes(3000) + b"a" * 3000), *list(SCENE.items())[1:]],
        zipfile.ZIP_DEFLATED,
    )
    start = 30 + len("color/0.png") + 3  # local header, name, a few bytes into the stream
    return corrupt(data, start, 30)


def xz_tar_with_bad_stream() -> bytes:
    entries = [(f"junk/{i}", random.Random(i).randbytes(20000)) for i in range(3)]
    data = tar_of([*SCENE.items(), *entries], "w:xz")
    return corrupt(data, len(data) // 2, 50)


@pytest.mark.parametrize(
    "archive", [deflated_zip_with_bad_stream, xz_tar_with_bad_stream], ids=["zip-deflate", "tar-xz"]
)
def test_corrupt_compressed_archives_are_422_not_500(http: httpx.Client, archive) -> None:
    scene = new_scene(http)
    refused(upload_archive(http, scene, archive()), 422, "archive", "not a readable")
    assert frame_count(http, scene) == 0


def test_archive_errors_never_show_the_servers_paths(
    http: httpx.Client, api_server: LiveServer
) -> None:
    """A member name longer than the file system allows used to answer with the full path of
    the server's extraction folder."""
    scene = new_scene(http)
    r = upload_archive(http, scene, tar_of([*SCENE.items(), ("color/" + "a" * 300 + ".txt", b"x")]))
    message = refused(r, 422, "archive", "File name too long")
    assert (
        str(api_server.settings.resolved_work_dir) not in message and "csa-archive" not in message
    )


def gnu_tar_of(entries: list[tuple[str, bytes]]) -> bytes:
    """A GNU-format tar whose names are raw bytes (surrogate escapes), as tar writes them."""
    buf = io.BytesIO()
    with tarfile.open(
        fileobj=buf, mode="w", format=tarfile.GNU_FORMAT, encoding="utf-8", errors="surrogateescape"
    ) as tf:
        for name, data in entries:
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
    return buf.getvalue()


@pytest.mark.parametrize(
    ("member", "field"),
    [
        ("color/\u00b2.png", "archive:color/\u00b2.png"),
        ("color/\udcff.png", "archive:color/\\udcff.png"),
    ],
    ids=["superscript-two", "not-utf8"],
)
def test_archive_colour_images_with_names_that_are_not_frame_names_are_422(
    http: httpx.Client, member: str, field: str
) -> None:
    """``'\u00b2'.isdigit()`` is true but ``int('\u00b2')`` fails: sorting the frame names
    answered 500 before the names were checked. A name in bytes that are not UTF-8 made the
    error answer itself unencodable (500); it is answered with the bytes escaped."""
    scene = new_scene(http)
    r = upload_archive(http, scene, gnu_tar_of([*SCENE.items(), (member, color(seed=5))]))
    refused(r, 422, field, "must be 1-64 letters")
    assert frame_count(http, scene) == 0


def test_archive_depth_intrinsics_have_the_text_limit(http: httpx.Client) -> None:
    scene = new_scene(http)
    r = upload_archive(
        http, scene, tar_of([*SCENE.items(), ("intrinsic/intrinsic_depth.txt", b"1 " * 40_000)])
    )
    refused(r, 413, "archive:intrinsic/intrinsic_depth.txt", "65536 bytes")
    assert frame_count(http, scene) == 0


def tar_header(name: str, kind: bytes, size: int) -> bytes:
    """One 512-byte tar header block of type ``kind`` declaring ``size`` bytes of data."""
    info = tarfile.TarInfo(name)
    info.type, info.size = kind, size
    return info.tobuf(format=tarfile.GNU_FORMAT)[:512]


def gzipped(*blocks: bytes) -> bytes:
    import gzip

    return gzip.compress(b"".join(blocks), compresslevel=1)


@pytest.mark.parametrize(
    "kind",
    [tarfile.GNUTYPE_LONGNAME, tarfile.GNUTYPE_LONGLINK, tarfile.XHDTYPE, tarfile.XGLTYPE],
    ids=["gnu-long-name", "gnu-long-link", "pax", "pax-global"],
)
def test_tar_extended_headers_declaring_gigabytes_are_refused_unread(
    http: httpx.Client, kind: bytes
) -> None:
    """Python's tarfile reads a pax or GNU long-name header into memory whole, before the
    member it describes reaches any limit of ours: in a gzipped tar a few kilobytes decompress
    to gigabytes of header. Such a header is refused from its declared size."""
    scene = new_scene(http)
    declared = 8 * 1024**3 - 1  # the largest size an octal header field holds
    data = gzipped(
        tar_header("././@LongLink", kind, declared), b"a" * 4096, tar_of(list(SCENE.items()))
    )
    message = refused(
        upload_archive(http, scene, data), 422, "archive", f"extended header of {declared} bytes"
    )
    assert "csa-archive" not in message
    assert frame_count(http, scene) == 0


def pax_record(key: str, value: str) -> bytes:
    body = f" {key}={value}\n"
    n = len(body) + 1
    while len(str(n)) + len(body) != n:
        n += 1
    return f"{n}{body}".encode()


def pax_header(records: bytes, name: str = "pax") -> bytes:
    return tar_header(name, tarfile.XHDTYPE, len(records)) + records.ljust(
        -(-len(records) // 512) * 512, b"\0"
    )


@pytest.mark.parametrize(
    ("archive", "problem"),
    [
        (
            lambda: gzipped(
                tar_header("color/1.png", tarfile.GNUTYPE_SPARSE, 10), tar_of(list(SCENE.items()))
            ),
            "sparse files are not allowed",
        ),
        (
            lambda: gzipped(
                pax_header(
                    pax_record("GNU.sparse.major", "1") + pax_record("GNU.sparse.minor", "0")
                ),
                tar_header("color/1.png", tarfile.REGTYPE, 512),
                b"x\n".ljust(512, b"\0"),
                tar_of(list(SCENE.items())),
            ),
            "sparse files are not allowed",
        ),
        (
            lambda: gzipped(
                pax_header(
                    pax_record("GNU.sparse.map", "a,b") + pax_record("GNU.sparse.size", "9")
                ),
                tar_header("color/1.png", tarfile.REGTYPE, 0),
                tar_of(list(SCENE.items())),
            ),
            "not a readable tar archive",
        ),
        (
            lambda: gzipped(
                pax_header(pax_record("comment", "x")) * 2000, tar_of(list(SCENE.items()))
            ),
            "not a readable tar archive",
        ),
        (
            lambda: tar_of([(".", b"x" * 100), *SCENE.items()]),
            "a file cannot be the archive folder itself",
        ),
    ],
    ids=[
        "gnu-sparse",
        "pax-sparse-1.0",
        "pax-sparse-map-garbage",
        "chain-of-2000-pax-headers",
        "file-named-dot",
    ],
)
def test_tar_members_that_tarfile_cannot_read_safely_are_refused(
    http: httpx.Client, archive, problem: str
) -> None:
    """Sparse maps grow with the data that follows them (unbounded memory) and malformed ones
    raised ValueError; a chain of extended headers raised RecursionError; a file named ``.``
    had its data skipped without being counted: all answered 500 or ran unbounded."""
    scene = new_scene(http)
    refused(upload_archive(http, scene, archive()), 422, "archive", problem)
    assert frame_count(http, scene) == 0


# --- cameras -------------------------------------------------------------------------------

NOT_PINHOLE = [
    ("30 0 15.5\n0 31 11.5\n7 7 7\n", "third row must be 0 0 1"),
    ("30 0 15.5\n0 31 11.5\n0 0 2\n", "third row must be 0 0 1"),
    ("30 9 15.5\n0 31 11.5\n0 0 1\n", "skew 9 is not supported"),
    ("30 0 15.5\n4 31 11.5\n0 0 1\n", "the cell below fx must be 0"),
    ("30 0 15.5 0\n0 31 11.5 0\n0 0 1 0\n5 5 5 5\n", "fourth row and column"),
    ("30 0 15.5 3\n0 31 11.5 0\n0 0 1 0\n0 0 0 1\n", "fourth row and column"),
]


@pytest.mark.parametrize(("matrix", "problem"), NOT_PINHOLE)
def test_intrinsic_matrices_that_are_not_pinhole_matrices_are_refused(
    http: httpx.Client, matrix: str, problem: str
) -> None:
    """Those cells used to be ignored: a camera with skew or a homogeneous scale was stored as
    another camera than the one the client described."""
    scene = new_scene(http)
    refused(upload_frame(http, scene, "0", intrinsics=matrix.encode()), 422, "intrinsics", problem)
    r = upload_archive(
        http,
        scene,
        tar_of(list({**SCENE, "intrinsic/intrinsic_color.txt": matrix.encode()}.items())),
    )
    refused(r, 422, "archive:intrinsic/intrinsic_color.txt", problem)
    assert frame_count(http, scene) == 0


def test_the_scene_reader_applies_the_same_rule(synth_scene: Path, tmp_path: Path) -> None:
    """The command line reads scene folders with the same check (one rule, in csa_core)."""
    from csa_core.data import read_scene

    folder = shutil.copytree(synth_scene, tmp_path / "skewed")
    K4 = np.loadtxt(folder / "intrinsic" / "intrinsic_color.txt")
    K4[0, 1] = 5.0
    np.savetxt(folder / "intrinsic" / "intrinsic_color.txt", K4)
    with pytest.raises(CSAInputError, match="skew 5 is not supported"):
        read_scene(folder)


def test_a_scene_keeps_the_depth_camera_of_its_first_frame(http: httpx.Client) -> None:
    """A later frame could bring depth intrinsics to a scene whose first frame had none and
    change the depth camera of every frame stored before it; and a scene with its own depth
    camera refused later frames that (rightly) did not repeat the depth intrinsics."""
    plain = new_scene(http)
    assert upload_frame(http, plain, "0").status_code == 201
    r = upload_frame(
        http,
        plain,
        "1",
        color=color(seed=1),
        intrinsics=None,
        depth_intrinsics=b"99 0 15.5\n0 99 11.5\n0 0 1\n",
    )
    refused(r, 422, "depth_intrinsics", "one depth camera")
    assert frame_count(http, plain) == 1
    assert http.get(f"/api/v1/scenes/{plain}").json()["depth_size"] == [W, H]

    own = new_scene(http)  # depth of another aspect ratio, with its own camera
    d_k = b"15 0 8\n0 15 4.5\n0 0 1\n"
    assert upload_frame(http, own, "0", depth=depth(16, 9), depth_intrinsics=d_k).status_code == 201
    r = upload_frame(http, own, "1", color=color(seed=2), depth=depth(16, 9), intrinsics=None)
    assert r.status_code == 201, r.text[:300]
    refused(
        upload_frame(
            http,
            own,
            "2",
            color=color(seed=3),
            depth=depth(16, 9),
            depth_intrinsics=b"16 0 8\n0 15 4.5\n0 0 1\n",
        ),
        422,
        "depth_intrinsics",
        "differ",
    )
    assert frame_count(http, own) == 2


# --- model checkpoints ---------------------------------------------------------------------

BASE_CARD = {"arch": "lraspp_mobilenet_v3_large", "format": "csa-seg-checkpoint/1"}


def checkpoint(card: dict | list) -> bytes:
    import torch
    from safetensors.torch import save

    return save({"x": torch.zeros(1)}, metadata={"csa": json.dumps(card)})


@pytest.mark.parametrize(
    ("card", "problem"),
    [
        ({**BASE_CARD, "std": ["a", "b", "c"]}, "std must be a list of 3 finite numbers"),
        ({**BASE_CARD, "std": "abc"}, "std must be a list of 3 finite numbers"),
        ({**BASE_CARD, "mean": 5}, "mean must be a list of 3 finite numbers"),
        ({**BASE_CARD, "num_classes": 10**9}, "num_classes must be an integer within 1..40"),
        ({**BASE_CARD, "num_classes": "x"}, "num_classes must be an integer within 1..40"),
        ({**BASE_CARD, "class_names": 3}, "class_names must be a list of 40 names"),
        ({**BASE_CARD, "metrics": [1, 2]}, "metrics must be a JSON object"),
        ({**BASE_CARD, "input_size": [8192, 8192]}, "more than the limit"),
        (BASE_CARD, "weights do not match lraspp_mobilenet_v3_large"),
    ],
    ids=[
        "std-strings",
        "std-string",
        "mean-number",
        "num-classes-huge",
        "num-classes-text",
        "class-names",
        "metrics-list",
        "input-size-huge",
        "weights",
    ],
)
def test_forged_model_cards_are_refused_at_upload(
    http: httpx.Client, card: dict, problem: str
) -> None:
    """Cards with wrong types answered 500; a card with absurd classes or weights that do not
    fit its network was registered and made every later prediction with it fail."""
    before = http.get("/api/v1/models").json()
    r = http.post(
        "/api/v1/models",
        files={"checkpoint": ("m.safetensors", checkpoint(card), "application/octet-stream")},
        data={"name": f"forged-{next(_names)}"},
    )
    message = refused(r, 422, "checkpoint", problem)
    assert "/tmp" not in message
    assert http.get("/api/v1/models").json() == before


@functools.cache
def network_weights() -> dict:
    """The tensors of the base card's network (untrained), as a checkpoint holds them."""
    from csa_core.seg.models import build_model

    return {k: v.contiguous() for k, v in build_model(BASE_CARD["arch"]).state_dict().items()}


def upload_checkpoint(http: httpx.Client, data: bytes) -> httpx.Response:
    files = {"checkpoint": ("m.safetensors", data, "application/octet-stream")}
    return http.post("/api/v1/models", files=files, data={"name": f"upload-{next(_names)}"})


@pytest.mark.parametrize("spoil", ["extra-tensor", "shape", "dtype"])
def test_checkpoints_that_do_not_fit_the_network_are_refused_from_the_header(
    http: httpx.Client, monkeypatch, spoil: str
) -> None:
    """Every tensor of an uploaded checkpoint was read, twice (for the card, then for the
    network), before its names, shapes and dtypes were compared with the card's network: a
    file whose header alone shows it cannot fit cost memory in proportion to the upload limit.
    It is refused from the header; no tensor is read."""
    import torch
    from safetensors.torch import save

    from csa_core.seg import checkpoint

    tensors = dict(network_weights())
    k = next(k for k, v in tensors.items() if v.dtype == torch.float32 and v.ndim == 4)
    if spoil == "extra-tensor":
        tensors["extra"], problem = (
            torch.zeros(1),
            "weights do not match lraspp_mobilenet_v3_large: unexpected ['extra']",
        )
    elif spoil == "shape":
        tensors[k] = torch.zeros(tensors[k].shape[0] + 1, *tensors[k].shape[1:])
        problem = f"tensor {k} is F32 ({tensors[k].shape[0]}, "
    else:
        tensors[k], problem = (
            tensors[k].double(),
            f"tensor {k} is F64 {tuple(tensors[k].shape)}, lraspp_mobilenet_v3_large needs F32",
        )
    data = save(tensors, metadata={"csa": json.dumps(BASE_CARD)})
    reads: list[str] = []
    real = checkpoint.read_safetensors
    monkeypatch.setattr(
        checkpoint, "read_safetensors", lambda path: reads.append(str(path)) or real(path)
    )
    refused(upload_checkpoint(http, data), 422, "checkpoint", problem)
    assert reads == []


def raw_safetensors(header: bytes, data: bytes = b"", declared: int | None = None) -> bytes:
    """A safetensors file as bytes: the header's length (or ``declared``), header, data."""
    import struct

    return struct.pack("<Q", len(header) if declared is None else declared) + header + data


@pytest.mark.parametrize(
    "data",
    [
        raw_safetensors(b"{}", declared=10**6),
        raw_safetensors(b'{"__metadata__": {"csa": "\xff\xfe"}}'),
        raw_safetensors(
            json.dumps({"x": {"dtype": "F32", "shape": [2**40], "data_offsets": [0, 4]}}).encode(),
            b"\0" * 4,
        ),
        raw_safetensors(
            json.dumps(
                {"x": {"dtype": "F32", "shape": [2**62, 2**62], "data_offsets": [0, 4]}}
            ).encode(),
            b"\0" * 4,
        ),
        raw_safetensors(
            json.dumps({"x": {"dtype": "F99", "shape": [1], "data_offsets": [0, 4]}}).encode(),
            b"\0" * 4,
        ),
    ],
    ids=[
        "header-longer-than-file",
        "metadata-not-utf8",
        "tensor-of-4-tib",
        "shape-overflows",
        "unknown-dtype",
    ],
)
def test_malformed_safetensors_headers_are_refused_unread(
    http: httpx.Client, monkeypatch, data: bytes
) -> None:
    from csa_core.seg import checkpoint

    reads: list[str] = []
    real = checkpoint.read_safetensors
    monkeypatch.setattr(
        checkpoint, "read_safetensors", lambda path: reads.append(str(path)) or real(path)
    )
    message = refused(
        upload_checkpoint(http, data), 422, "checkpoint", "not a readable safetensors file"
    )
    assert reads == [] and "/tmp" not in message


def nested_card(depth: int) -> str:
    """A card whose metrics nest ``depth`` objects deep, as text (json.dumps would recurse)."""
    return json.dumps(BASE_CARD)[:-1] + ', "metrics": ' + '{"m": ' * depth + "1" + "}" * depth + "}"


@pytest.mark.parametrize("depth", [33, 700, 100_000])
def test_model_cards_nested_deeper_than_a_card_are_refused(http: httpx.Client, depth: int) -> None:
    """A card nested 100000 levels deep answered 500: parsing it raises RecursionError, which
    is not a ValueError. One nested 700 levels deep parsed and was registered, and from then
    on every listing of the models answered 500 (too deep to serialise). Cards nest a few
    levels; more than 32 is refused, naming the rule, and nothing is registered."""
    from safetensors.torch import save

    data = save(network_weights(), metadata={"csa": nested_card(depth)})
    before = http.get("/api/v1/models").json()
    refused(
        upload_checkpoint(http, data),
        422,
        "checkpoint",
        "model card is not valid",
        "nest more than 32 levels deep",
    )
    after = http.get("/api/v1/models")
    assert after.status_code == 200 and after.json() == before


def test_model_cards_over_the_size_cap_are_refused(http: httpx.Client) -> None:
    """A card's metrics are stored with the version and sent in every listing of the models:
    a card of more than a megabyte is refused, naming the cap, and nothing is registered."""
    from safetensors.torch import save

    from csa_core.seg.checkpoint import MAX_CARD_BYTES

    card = json.dumps({**BASE_CARD, "metrics": {"padding": "x" * MAX_CARD_BYTES}})
    before = http.get("/api/v1/models").json()
    refused(
        upload_checkpoint(http, save(network_weights(), metadata={"csa": card})),
        422,
        "checkpoint",
        "model card is not valid",
        f"more than the {MAX_CARD_BYTES} a card may hold",
    )
    assert http.get("/api/v1/models").json() == before


# --- a scene deleted while a frame is being stored -----------------------------------------


@pytest.mark.parametrize("first", [True, False], ids=["first-frame", "later-frame"])
def test_an_upload_racing_the_deletion_of_its_scene_is_404(
    http: httpx.Client, api_server: LiveServer, monkeypatch, first: bool
) -> None:
    """The scene disappears between validation and the frame's row (another client deleted
    it): the upload answers 404 instead of a 500 from the database."""
    from server.db.models import Scene
    from server.services import frames

    scene = new_scene(http)
    if not first:
        assert upload_frame(http, scene, "0").status_code == 201
    real = frames.store_frame

    def delete_first(db, store, row, *args, **kwargs):
        with api_server.services.sessions() as other:
            other.delete(other.get(Scene, row.id))
            other.commit()
        return real(db, store, row, *args, **kwargs)

    monkeypatch.setattr(frames, "store_frame", delete_first)
    r = upload_frame(http, scene, "1", color=color(seed=4))
    assert r.status_code == 404 and r.json()["error"]["code"] == "not_found", r.text[:300]
    monkeypatch.undo()
    assert http.get(f"/api/v1/scenes/{scene}").status_code == 404


def test_a_frame_without_a_name_that_loses_the_race_for_its_number_takes_the_next(
    http: httpx.Client, api_server: LiveServer, monkeypatch
) -> None:
    """Another API process stores a frame under the number this upload was about to take: the
    upload answered 409 telling the client, who sent no name, to overwrite that frame with
    replace=true. It takes the next number instead, and both frames are kept."""
    import dataclasses

    from server.db.models import Scene
    from server.services import frames

    scene = new_scene(http)
    assert upload_frame(http, scene, "0").status_code == 201
    real = frames.store_frame
    raced: list[str] = []

    def another_process_first(db, store, row, name, valid, *args, **kwargs):
        if not raced:
            raced.append(name)
            with api_server.services.sessions() as other:
                moved = valid.pose.copy()
                moved[0, 3] += 1.0
                real(
                    other,
                    store,
                    other.get(Scene, row.id),
                    name,
                    dataclasses.replace(valid, pose=moved),
                )
                other.commit()
        return real(db, store, row, name, valid, *args, **kwargs)

    monkeypatch.setattr(frames, "store_frame", another_process_first)
    r = http.post(
        f"/api/v1/scenes/{scene}/frames",
        files={
            k: (k, v, "application/octet-stream")
            for k, v in {"color": color(seed=9), "depth": depth(), "pose": POSE.encode()}.items()
        },
    )
    monkeypatch.undo()
    assert raced == ["1"]
    assert r.status_code == 201 and r.json()["name"] == "2", r.text[:300]
    assert [f["name"] for f in http.get(f"/api/v1/scenes/{scene}/frames").json()] == ["0", "1", "2"]


# --- job parameters ------------------------------------------------------------------------


@pytest.fixture
def scenes(http: httpx.Client) -> tuple[str, str, int]:
    """A labelled scene (by name and id) and an unlabelled one, one frame each."""
    labelled, unlabelled = new_scene(http), new_scene(http)
    assert upload_frame(http, labelled, "0", labels=labels()).status_code == 201
    assert upload_frame(http, unlabelled, "0").status_code == 201
    return labelled, unlabelled, http.get(f"/api/v1/scenes/{labelled}").json()["id"]


def test_jobs_refuse_scene_lists_that_name_a_scene_twice(http: httpx.Client, scenes) -> None:
    """``scenes: [s] * 1000`` made a job read one scene a thousand times; a scene named once by
    name and once by id is the same scene."""
    labelled, _, ident = scenes
    before = len(http.get("/api/v1/jobs").json())
    for body, field in [
        ({"kind": "pretrain", "params": {"scenes": [labelled] * 1000}}, "params.scenes"),
        ({"kind": "pretrain", "params": {"scenes": [labelled, ident]}}, "params.scenes"),
        (
            {"kind": "pretrain", "params": {"scenes": [labelled], "val_scenes": [labelled]}},
            "params.val_scenes",
        ),
    ]:
        refused(http.post("/api/v1/jobs", json=body), 422, field, labelled)
    assert len(http.get("/api/v1/jobs").json()) == before


def test_jobs_needing_ground_truth_refuse_unlabelled_scenes_when_queued(
    http: httpx.Client, scenes
) -> None:
    """They used to be queued and fail when they ran (a fit_nerf on ground truth still does: the
    dashboard's test of a failed job relies on it)."""
    labelled, unlabelled, _ = scenes
    before = len(http.get("/api/v1/jobs").json())
    r = http.post(
        "/api/v1/jobs", json={"kind": "pretrain", "params": {"scenes": [labelled, unlabelled]}}
    )
    refused(
        r, 422, "params.scenes", unlabelled, "1 of 1 frames have no ground-truth labels (e.g. 0)"
    )
    r = http.post(
        "/api/v1/jobs",
        json={"kind": "pretrain", "params": {"scenes": [labelled], "val_scenes": [unlabelled]}},
    )
    refused(r, 422, "params.val_scenes", unlabelled)
    assert len(http.get("/api/v1/jobs").json()) == before


@pytest.mark.parametrize(
    ("body", "field"),
    [
        (
            lambda s: {
                "kind": "fit_nerf",
                "params": {"scene": s, "labels": "none", "size": "8192x8192"},
            },
            "params.size",
        ),
        (
            lambda s: {
                "kind": "fit_nerf",
                "params": {"scene": s, "labels": "none", "size": "64x16"},
            },
            "params.size",
        ),
        (
            lambda s: {
                "kind": "pretrain",
                "params": {"scenes": [s], "size": "4096x4096", "batch_size": 1024},
            },
            "params.size",
        ),
    ],
    ids=["fit-8192", "fit-wider", "pretrain-4096"],
)
def test_jobs_refuse_working_sizes_beyond_the_scenes_frames(
    http: httpx.Client, scenes, body, field: str
) -> None:
    """A 32x24 scene read at 8192x8192 holds gigabytes per frame; frames are bounded by the
    upload limits, so a job's size is bounded by its frames."""
    labelled, _, _ = scenes
    before = len(http.get("/api/v1/jobs").json())
    refused(
        http.post("/api/v1/jobs", json=body(labelled)),
        422,
        field,
        f"larger than the scene's frames ({W}x{H})",
    )
    assert len(http.get("/api/v1/jobs").json()) == before


def test_jobs_at_the_frames_size_or_smaller_are_queued(http: httpx.Client, scenes) -> None:
    """The other side of the rules above."""
    labelled, _, _ = scenes
    for body in (
        {
            "kind": "fit_nerf",
            "params": {
                "scene": labelled,
                "labels": "ground_truth",
                "size": f"{W}x{H}",
                "steps": 10,
            },
        },
        {
            "kind": "pretrain",
            "params": {
                "scenes": [labelled],
                "size": "16x12",
                "epochs": 1,
                "name": f"ok-{next(_names)}",
            },
        },
    ):
        r = http.post("/api/v1/jobs", json=body)
        assert r.status_code == 202, r.text[:300]
        assert http.post(f"/api/v1/jobs/{r.json()['id']}/cancel").json()["status"] == "cancelled"


def test_a_name_or_lineage_a_queued_pretrain_will_register_is_taken(
    http: httpx.Client, scenes
) -> None:
    """Only the registry was asked whether a name or lineage was free: a second pre-training
    (or an uploaded checkpoint) with the lineage of a queued one was accepted, and registered
    a second root of that lineage (versions the continual chain never reaches); one with its
    name trained for hours and then failed on the name. Both are 409 naming the field, and
    free again once the first job has ended."""
    labelled, _, _ = scenes
    tag = f"claimed-{next(_names)}"
    pretrain = lambda **p: http.post(  # noqa: E731
        "/api/v1/jobs",
        json={"kind": "pretrain", "params": {"scenes": [labelled], "epochs": 1, **p}},
    )
    first = pretrain(name=tag)  # lineage: the name
    assert first.status_code == 202, first.text[:300]
    jobs_before, models_before = (
        len(http.get("/api/v1/jobs").json()),
        http.get("/api/v1/models").json(),
    )
    job = first.json()["id"]
    refused(pretrain(name=f"{tag}-b", lineage=tag), 409, "params.lineage", tag, f"job {job}")
    refused(pretrain(name=tag, lineage=f"{tag}-other"), 409, "params.name", tag, f"job {job}")
    for data, field in (
        ({"name": f"{tag}-c", "lineage": tag}, "lineage"),
        ({"name": tag, "lineage": f"{tag}-other"}, "name"),
    ):
        r = http.post(
            "/api/v1/models",
            files={"checkpoint": ("m.safetensors", b"never read", "application/octet-stream")},
            data=data,
        )
        refused(r, 409, field, tag, f"job {job}")
    assert (
        len(http.get("/api/v1/jobs").json()) == jobs_before
        and http.get("/api/v1/models").json() == models_before
    )
    assert http.post(f"/api/v1/jobs/{job}/cancel").json()["status"] == "cancelled"
    again = pretrain(name=f"{tag}-b", lineage=tag)
    assert again.status_code == 202, again.text[:300]
    http.post(f"/api/v1/jobs/{again.json()['id']}/cancel")


def test_adaptation_steps_name_their_version_with_a_free_name_that_fits(tmp_path: Path) -> None:
    """A step registered its version as ``<lineage>-step<n>`` at the very end of the job: a
    client who had uploaded a model of that name (any lineage) made every step of the lineage
    fail there, after all its work, since the next try computes the same name; and a lineage
    named with 128 characters (a valid name) made a name longer than the column holds."""
    from sqlalchemy import create_engine
    from sqlalchemy.orm import Session

    from server.db.models import Base, ModelVersion
    from server.jobs.adapt import step_name

    engine = create_engine(f"sqlite:///{tmp_path / 'db.sqlite'}")
    Base.metadata.create_all(engine)
    with Session(engine) as s:
        for name in ("base-step1", "base-step1.2"):  # squatters, in lineages of their own
            s.add(ModelVersion(name=name, lineage=name, files={}, arch="x"))
        s.commit()
        assert step_name(s, "base", 1) == "base-step1.3"
        assert step_name(s, "base", 2) == "base-step2"
        long = "L" * 128
        assert step_name(s, long, 12) == "L" * 121 + "-step12"
        s.add(ModelVersion(name="L" * 121 + "-step12", lineage=long, files={}, arch="x"))
        s.commit()
        assert step_name(s, long, 12) == "L" * 119 + "-step12.2"
    engine.dispose()


# --- form parts a route does not read ----------------------------------------------------


@pytest.mark.parametrize(
    ("route", "files", "data", "field"),
    [
        ("frames", {"label": labels()}, {}, "label"),
        ("frames", {}, {"nmae": "7"}, "nmae"),
        ("archive", {"archive": b"not read"}, {"overwrite": "true"}, "overwrite"),
        ("models", {"checkpoint": b"not read"}, {"name": "m", "current": "true"}, "current"),
        ("predict", {"image": color()}, {"modle": "x"}, "modle"),
    ],
    ids=["misspelt-labels", "misspelt-name", "archive-extra", "model-extra", "predict-extra"],
)
def test_form_parts_a_route_does_not_read_are_refused(
    http: httpx.Client, route: str, files: dict, data: dict, field: str
) -> None:
    """FastAPI drops an unknown part silently: a frame uploaded with ``label`` (for
    ``labels``) would be stored without its labels. Every multipart route names the part."""
    scene = new_scene(http)
    if route == "frames":
        files = {
            "color": color(),
            "depth": depth(),
            "pose": POSE.encode(),
            "intrinsics": K.encode(),
        } | files
        url = f"/api/v1/scenes/{scene}/frames"
    else:
        url = {
            "archive": f"/api/v1/scenes/{scene}/archive",
            "models": "/api/v1/models",
            "predict": "/api/v1/predict",
        }[route]
    r = http.post(
        url, files={k: (k, v, "application/octet-stream") for k, v in files.items()}, data=data
    )
    refused(r, 422, field, "unknown form part")
    assert frame_count(http, scene) == 0


@pytest.mark.parametrize(
    ("route", "parts", "field"),
    [
        ("frames", [("color", color(seed=21)), ("color", color(seed=22))], "color"),
        ("frames", [("labels", labels(3)), ("labels", labels(5))], "labels"),
        ("frames", [], "name"),  # two text fields: name=a&name=b
        ("archive", [("archive", tar_of(list(SCENE.items()))), ("archive", b"junk")], "archive"),
    ],
    ids=["two-colours", "two-labels", "two-names", "two-archives"],
)
def test_form_parts_sent_twice_are_refused(
    http: httpx.Client, route: str, parts: list, field: str
) -> None:
    """FastAPI keeps the last of two same-named parts and drops the other silently: a frame
    could be stored with the labels the client did not mean. Every multipart route names the
    part."""
    scene = new_scene(http)
    base = (
        [
            ("color", color()),
            ("depth", depth()),
            ("pose", POSE.encode()),
            ("intrinsics", K.encode()),
        ]
        if route == "frames"
        else []
    )
    sent = [p for p in base if p[0] not in {name for name, _ in parts}] + parts
    files = [(name, (name, data, "application/octet-stream")) for name, data in sent]
    data = {"name": ["a", "b"]} if field == "name" else {}
    refused(
        http.post(f"/api/v1/scenes/{scene}/{route}", files=files, data=data),
        422,
        field,
        "sent more than once",
    )
    assert frame_count(http, scene) == 0


def test_known_form_parts_still_store_the_frame(http: httpx.Client) -> None:
    """The other side: every part the frame route documents is accepted together."""
    scene = new_scene(http)
    r = http.post(
        f"/api/v1/scenes/{scene}/frames",
        files={
            k: (k, v, "application/octet-stream")
            for k, v in {
                "color": color(),
                "depth": depth(),
                "pose": POSE.encode(),
                "intrinsics": K.encode(),
                "depth_intrinsics": K.encode(),
                "labels": labels(),
            }.items()
        },
        data={"name": "0", "replace": "false"},
    )
    assert r.status_code == 201, r.text[:300]
    assert http.get(f"/api/v1/scenes/{scene}/frames/0/labels").status_code == 200


# --- labels as JPEG ------------------------------------------------------------------------


def test_labels_sent_as_jpeg_are_refused(http: httpx.Client) -> None:
    """Labels sent as a JPEG decoded to NYU40 ids and were stored, then served as
    ``image/png`` under a ``.png`` name with JPEG bytes inside (and linked as
    ``label-nyu40/<name>.png`` for jobs), where lossy compression had changed the ids at the
    edges of every region. They are refused naming the part, by frame and in an archive, and
    nothing is stored."""
    region = np.full((H, W), 3, np.uint8)
    region[:, W // 2 :] = 5
    scene = new_scene(http)
    r = upload_frame(http, scene, "0", labels=jpg(region))
    refused(r, 422, "labels", "must be a PNG file, not a JPEG")
    r = upload_archive(http, scene, tar_of([*SCENE.items(), ("label-nyu40/0.png", jpg(region))]))
    refused(r, 422, "archive:label-nyu40/0.png", "must be a PNG file, not a JPEG")
    assert frame_count(http, scene) == 0
    assert upload_frame(http, scene, "0", labels=png(region)).status_code == 201


# --- progressive JPEGs of thousands of scans ------------------------------------------------


def progressive_jpg(seed: int = 0) -> bytes:
    img = np.random.default_rng(seed).integers(0, 256, (H, W, 3), dtype=np.uint8)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])
    assert ok
    return buf.tobytes()


def test_jpegs_of_too_many_scans_are_refused_before_decoding(
    http: httpx.Client, monkeypatch
) -> None:
    """A small progressive JPEG of thousands of scans makes the decoder go over the whole image
    once per scan. Its markers are counted first: more than 100 scans is a 422 naming the part
    (by frame and in an archive), the decoder never sees the file and nothing is stored; an
    ordinary progressive JPEG is still stored."""
    from csa_core.data import image_files

    decoded: list[str] = []
    real_imread = image_files._imread

    def imread(path: Path, flags: int):
        decoded.append(path.suffix)
        return real_imread(path, flags)

    monkeypatch.setattr(image_files, "_imread", imread)
    bomb = with_extra_scans(progressive_jpg(), 2000)
    scene = new_scene(http)
    r = upload_frame(http, scene, "0", color=bomb)
    refused(r, 422, "color", f"more than {MAX_JPEG_SCANS} scans")
    archive = tar_of(
        [("color/0.jpg", bomb), *[(k, v) for k, v in SCENE.items() if not k.startswith("color/")]]
    )
    r = upload_archive(http, scene, archive)
    refused(r, 422, "archive:color/0.jpg", f"more than {MAX_JPEG_SCANS} scans")
    assert frame_count(http, scene) == 0
    assert ".jpg" not in decoded
    assert upload_frame(http, scene, "0", color=progressive_jpg()).status_code == 201
    assert ".jpg" in decoded


def test_predictions_refuse_jpegs_of_too_many_scans(http: httpx.Client) -> None:
    from server import capabilities

    if not capabilities.available("seg"):
        pytest.skip("csa_core.seg is not available in this build")
    model = _registered_model(http)
    bomb = with_extra_scans(progressive_jpg(), 2000)
    r = http.post(
        "/api/v1/predict", files={"image": ("i.jpg", bomb, "image/jpeg")}, data={"model": model}
    )
    refused(r, 422, "image", f"more than {MAX_JPEG_SCANS} scans")
    r = http.post(
        "/api/v1/predict",
        files={"image": ("i.jpg", progressive_jpg(), "image/jpeg")},
        data={"model": model},
    )
    assert r.status_code == 200, r.text[:300]


# --- blobs left behind by a transaction that failed ----------------------------------------


def test_blobs_of_a_failed_transaction_are_swept_after_the_grace_period(
    http: httpx.Client, api_server: LiveServer, monkeypatch
) -> None:
    """The frame's files are written before its row commits; when the commit fails they stay
    on disk unrecorded. The sweep deletes them once older than the grace period and never
    touches a recorded blob or a young one (an open transaction may be about to record it)."""
    import os
    import time

    from sqlalchemy.orm import Session

    scene = new_scene(http)
    assert upload_frame(http, scene, "0").status_code == 201
    store = api_server.services.store
    blobs = lambda: {p.name for d in (store.root / "blobs").iterdir() for p in d.iterdir()}  # noqa: E731
    before = blobs()

    real_commit = Session.commit

    def fail(self, *args, **kwargs):
        # Only the commit after the frame's files are written, the one that records them (the
        # route's reads before it end their transaction with a commit too).
        if blobs() - before:
            raise RuntimeError("the database went away")
        return real_commit(self, *args, **kwargs)

    monkeypatch.setattr(Session, "commit", fail)
    r = upload_frame(http, scene, "1", color=color(seed=11))
    monkeypatch.undo()
    assert r.status_code == 500 and frame_count(http, scene) == 1
    orphans = blobs() - before
    assert len(orphans) == 1  # the new colour image (depth and pose equal frame 0's)
    with api_server.services.sessions() as session:
        assert store.sweep_unrecorded(session, older_than_s=3600) == []  # young: kept
        (orphan,) = orphans
        path = store.path_of(orphan)
        old = time.time() - 7200
        os.utime(path, (old, old))
        frame0 = http.get(f"/api/v1/scenes/{scene}/frames/0").json()
        for recorded in (frame0["color_sha256"], frame0["depth_sha256"]):  # kept however old
            os.utime(store.path_of(recorded), (old, old))
        assert store.sweep_unrecorded(session, older_than_s=3600) == [orphan]
    assert blobs() == before
    assert http.get(f"/api/v1/scenes/{scene}/frames/0/color").status_code == 200


def test_putting_existing_bytes_again_refreshes_the_grace_period(tmp_path: Path) -> None:
    """An upload whose bytes are already on disk (unrecorded, old) is about to record them:
    the put makes the file young again so a concurrent sweep keeps it."""
    import os
    import time

    from sqlalchemy import create_engine
    from sqlalchemy.orm import Session

    from server.artifacts import ArtifactStore
    from server.db.models import Base

    store = ArtifactStore(tmp_path / "store")
    engine = create_engine(f"sqlite:///{tmp_path / 'db.sqlite'}")
    Base.metadata.create_all(engine)
    with Session(engine) as session:
        stored = store.put_bytes(session, b"frame bytes", "color")
        session.rollback()  # the transaction failed: the blob is unrecorded
        old = time.time() - 7200
        os.utime(store.path_of(stored.sha256), (old, old))
        (store.root / "tmp" / "crashed.part").write_bytes(b"half")
        os.utime(store.root / "tmp" / "crashed.part", (old, old))
        store.put_bytes(session, b"frame bytes", "color")  # a second upload of the same bytes
        assert store.sweep_unrecorded(session, older_than_s=3600) == ["crashed.part"]
        session.commit()
        assert store.path_of(stored.sha256).is_file()
    engine.dispose()


def test_the_background_sweeper_deletes_old_orphans_and_stops(tmp_path: Path) -> None:
    """``OrphanSweeper`` sweeps once at start and then every interval in its own thread (no
    request lists the store); a failing sweep is logged and retried; stop ends the thread."""
    import os
    import time
    from contextlib import contextmanager

    from sqlalchemy import create_engine
    from sqlalchemy.orm import Session

    from server.artifacts import ArtifactStore, OrphanSweeper
    from server.db.models import Base

    store = ArtifactStore(tmp_path / "store")
    engine = create_engine(f"sqlite:///{tmp_path / 'db.sqlite'}")
    Base.metadata.create_all(engine)
    with Session(engine) as session:
        orphan = store.put_bytes(session, b"orphan bytes", "color")
        session.rollback()  # never recorded
        kept = store.put_bytes(session, b"recorded bytes", "color")
        session.commit()
    old = time.time() - 7200
    for sha in (orphan.sha256, kept.sha256):
        os.utime(store.path_of(sha), (old, old))
    calls = []

    @contextmanager
    def sessions():
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError("the database is not up yet")  # the first sweep fails
        with Session(engine) as s:
            yield s

    sweeper = OrphanSweeper(store, sessions, older_than_s=3600, interval_s=0.01)
    sweeper.start()
    deadline = time.monotonic() + 30
    while store.path_of(orphan.sha256).exists() and time.monotonic() < deadline:
        time.sleep(0.01)
    sweeper.stop()
    assert not store.path_of(orphan.sha256).exists()
    assert store.path_of(kept.sha256).is_file()
    assert sweeper.sweeps >= 2 and not sweeper._thread.is_alive()
    once = OrphanSweeper(store, sessions, older_than_s=3600, interval_s=0)
    once.start()
    once._thread.join(30)
    assert once.sweeps == 1 and not once._thread.is_alive()
    with pytest.raises(ValueError, match="orphan_sweep_interval_seconds"):
        OrphanSweeper(store, sessions, older_than_s=3600, interval_s=-1)
    engine.dispose()


# --- slow request work off the event loop ----------------------------------------------------


def _checkpoint_bytes() -> bytes:
    """A checkpoint the service registers: the base card's (untrained) network."""
    from safetensors.torch import save

    return save(network_weights(), metadata={"csa": json.dumps(BASE_CARD)})


def _registered_model(http: httpx.Client) -> str:
    name = f"loop-{next(_names)}"
    r = http.post(
        "/api/v1/models",
        files={"checkpoint": ("m.safetensors", _checkpoint_bytes(), "application/octet-stream")},
        data={"name": name, "make_current": "false"},
    )
    assert r.status_code == 201, r.text[:300]
    return name


@pytest.mark.parametrize("route", ["frame", "archive", "model", "predict"])
def test_uploads_are_processed_off_the_event_loop(
    http: httpx.Client, api_server: LiveServer, monkeypatch, route: str
) -> None:
    """An upload's work (decoding and validating images, extracting an archive, loading a
    checkpoint, hashing and fsyncing files, the network) ran on the server's event loop: while
    an archive of 60 frames of 640x480 (88 MB) was stored, every other request, ``/health``
    included, waited 1.2 s, and the limits allow archives of a gigabyte and 20000 members. That
    work runs in a worker thread: here it is held until ``/health`` has been answered, which
    never happens on a blocked loop."""
    import threading

    from csa_core.data import image_files
    from server import capabilities
    from server.services import frames, models

    if route in ("model", "predict") and not capabilities.available("seg"):
        pytest.skip("csa_core.seg is not available in this build")
    scene = new_scene(http)
    entered, release = threading.Event(), threading.Event()

    def held(real):
        def run(*args, **kwargs):
            entered.set()
            release.wait(20)
            return real(*args, **kwargs)

        return run

    model = _registered_model(http) if route == "predict" else None
    card_checkpoint = _checkpoint_bytes() if route == "model" else b""
    if route in ("frame", "archive"):
        monkeypatch.setattr(frames, "validate_frame", held(frames.validate_frame))
    elif route == "model":
        monkeypatch.setattr(models, "register_checkpoint", held(models.register_checkpoint))
    else:
        monkeypatch.setattr(image_files, "read_color", held(image_files.read_color))

    def send(c: httpx.Client) -> httpx.Response:
        if route == "frame":
            return upload_frame(c, scene, "0")
        if route == "archive":
            return upload_archive(c, scene, tar_of(list(SCENE.items())))
        if route == "model":
            return upload_checkpoint(c, card_checkpoint)
        return c.post(
            "/api/v1/predict",
            files={"image": ("i.png", color(), "image/png")},
            data={"model": model},
        )

    answers: list[httpx.Response] = []
    with httpx.Client(base_url=api_server.url, headers={"X-API-Key": API_KEY}, timeout=60) as other:
        upload = threading.Thread(target=lambda: answers.append(send(other)))
        upload.start()
        try:
            assert entered.wait(30), "the upload never reached the held step"
            health = httpx.get(
                f"{api_server.url}/health", timeout=5
            )  # ReadTimeout on a blocked loop
            assert health.status_code == 200
            assert not release.is_set() and upload.is_alive()
        finally:
            release.set()
            upload.join(60)
    assert len(answers) == 1 and answers[0].status_code in (200, 201), answers[0].text[:300]


# --- invented methods, non-ASCII tokens, bodies without a length -----------------------------


def test_invented_http_methods_add_no_metrics_series(http: httpx.Client) -> None:
    """HTTP lets a client send any token as its method, and the request counters run before
    authentication: every invented method added 15 series to ``/metrics`` for good, so anyone
    could grow the server's memory and the metrics without bound. They count as OTHER."""
    for i in range(25):
        assert http.request(f"INVENTED{i}", "/health").status_code == 405
    text = http.get("/metrics").text
    assert "INVENTED" not in text
    assert 'csa_http_requests_total{method="OTHER",route="/health",status="405"} 25' in text


def test_non_ascii_csrf_tokens_are_403_not_500(api_server: LiveServer) -> None:
    """hmac.compare_digest raises TypeError for str holding non-ASCII characters: a signed-in
    dashboard request whose CSRF token (header or form field) had one answered 500."""
    with httpx.Client(base_url=api_server.url, headers={"Origin": api_server.url}, timeout=30) as c:
        assert c.post("/ui/login", data={"api_key": API_KEY}).status_code == 303
        r = c.post(
            "/ui/api/v1/scenes",
            json={"name": f"csrf-{next(_names)}"},
            headers={"X-CSRF-Token": b"\xe9t\xe9"},
        )
        assert r.status_code == 403 and "CSRF token" in r.json()["error"]["message"], r.text[:300]
        r = c.post("/ui/logout", data={"csrf_token": "été"})
        assert r.status_code == 403 and "CSRF token" in r.json()["error"]["message"], r.text[:300]


@pytest.mark.parametrize(
    ("route", "head", "content_type", "what"),
    [
        ("/api/v1/scenes", b'{"name": "big", "description": "', "application/json", "request body"),
        (
            "/api/v1/jobs",
            b'{"kind": "evaluate", "params": {"model": "',
            "application/json",
            "request body",
        ),
        (
            "frames",
            b'--BB\r\nContent-Disposition: form-data; name="color"; filename="c.png"\r\n\r\n',
            "multipart/form-data; boundary=BB",
            "frame upload",
        ),
        (
            "archive",
            b'--BB\r\nContent-Disposition: form-data; name="archive"; filename="a.tar"\r\n\r\n',
            "multipart/form-data; boundary=BB",
            "archive",
        ),
    ],
    ids=["json-scene", "json-job", "frame", "archive"],
)
def test_bodies_without_a_length_over_the_limit_are_413(
    http: httpx.Client,
    api_server: LiveServer,
    route: str,
    head: bytes,
    content_type: str,
    what: str,
) -> None:
    """A body sent chunked (no Content-Length) was cut off at the limit, but FastAPI turned the
    middleware's error into its own 400 "There was an error parsing the body": the client
    could not tell that its upload was too large. It is a 413 naming the limit, as with a
    Content-Length over it."""
    from server.upload_limits import BodyLimitMiddleware

    scene = new_scene(http)
    path = f"/api/v1/scenes/{scene}/{route}" if not route.startswith("/") else route
    limit, _ = BodyLimitMiddleware(None, api_server.settings)._limit(path)

    def body() -> Iterator[bytes]:
        yield head
        for _ in range(limit // 65536 + 4):
            yield b"x" * 65536

    r = http.post(path, content=body(), headers={"content-type": content_type})
    refused(r, 413, what, f"{what} exceeds the limit of {limit} bytes")
    assert frame_count(http, scene) == 0


# --- model cards whose metrics no database or answer can hold --------------------------------


@pytest.mark.parametrize(
    ("metrics", "problem"),
    [
        ('{"miou": NaN}', "metrics.miou is not a finite number"),
        ('{"best": Infinity}', "metrics.best is not a finite number"),
        ('{"per_scene": {"a": [0.5, -1e999]}}', "metrics.per_scene.a[1] is not a finite number"),
        # json.dumps keeps a lone surrogate as its escape ("\ud800").
        (json.dumps({"note": "a\ud800"}), "metrics.note is not Unicode text"),
        (json.dumps({"per_scene": ["\udc80"]}), "metrics.per_scene[0] is not Unicode text"),
        (
            json.dumps({"per_scene": {"\ud800": 1.0}}),
            "metrics.per_scene has a key that is not Unicode",
        ),
    ],
    ids=["nan", "infinity", "nested-overflow", "surrogate", "nested-surrogate", "surrogate-key"],
)
def test_model_cards_with_unstorable_metrics_are_refused(
    http: httpx.Client, metrics: str, problem: str
) -> None:
    """Python's json reads NaN, Infinity and 1e999: a card's metrics holding one were stored
    with the version, as text that is not JSON on SQLite, and on PostgreSQL the database
    refused the row (a 422 that named no field). JSON escapes also spell lone surrogates, which
    no answer can encode: a card holding one was registered, and from then on every listing of
    the models answered 500. Both are refused naming where they sit, and nothing is
    registered."""
    from safetensors.torch import save

    card = json.dumps(BASE_CARD)[:-1] + f', "metrics": {metrics}}}'
    before = http.get("/api/v1/models").json()
    refused(
        upload_checkpoint(http, save(network_weights(), metadata={"csa": card})),
        422,
        "checkpoint",
        f"model card {problem}",
    )
    after = http.get("/api/v1/models")
    assert after.status_code == 200 and after.json() == before
