"""Pages of the list routes: ``GET /api/v1/scenes``, ``/scenes/{scene}/frames`` and ``/models``
answer ``limit`` rows from ``offset``, or after the cursor of a full page's ``Link`` header, in
a stable order, with the size of the whole list in ``X-Total-Count``; the cursors neither skip
nor repeat rows when others are added or deleted meanwhile; out-of-range paging and a cursor
the server did not give out are a 422 naming the parameter, never a database error (an offset
past a 64-bit integer included); and ``CSAClient`` (with ``csa-client``) follows the cursors
through every page, so its users still get whole lists.

One server without a worker per backend; five scenes, five frames with names chosen so that
the frame order is neither upload order nor name order, and five model versions in two
lineages written straight into the registry's table (no checkpoint is read).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from dataclasses import dataclass

import cv2
import httpx
import numpy as np
import pytest
from rich.console import Console

from client import CSAClient, cli
from client.cli import main as cli_main
from server.db.models import MAX_ID, ModelVersion
from server.db.session import session_scope
from server.pagination import MAX_LIMIT, TOTAL_COUNT_HEADER, encode_cursor
from server.registry import CHECKPOINT_FILE
from tests.server.conftest import (
    API_KEY,
    LiveServer,
    both_backends,
    database_url,
    start_server,
    test_settings,
)

pytestmark = both_backends

W, H = 32, 24
K = "30 0 15.5\n0 31 11.5\n0 0 1\n"
POSE = "1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n"
SCENES = [f"paged-{i}" for i in range(5)]
# Uploaded in this order; order keys 5, 6 (the next after 5), 6, 1, 10: the list is by order
# key, then name ("6" before "b").
FRAME_UPLOADS = ["5", "b", "6", "1", "10"]
FRAME_ORDER = ["1", "5", "6", "b", "10"]
MODELS = [
    ("alpha-0", "alpha"),
    ("beta-0", "beta"),
    ("alpha-1", "alpha"),
    ("beta-1", "beta"),
    ("alpha-2", "alpha"),
]
ROUTES = {
    "scenes": "/api/v1/scenes",
    "frames": f"/api/v1/scenes/{SCENES[0]}/frames",
    "models": "/api/v1/models",
}


def png(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return buf.tobytes()


@dataclass
class Paged:
    live: LiveServer
    http: httpx.Client

    def whole(self, route: str, **params: object) -> list[dict]:
        r = self.http.get(ROUTES[route], params={"limit": MAX_LIMIT, **params})
        assert r.status_code == 200, r.text[:300]
        return r.json()


@pytest.fixture(scope="module")
def paged(request, tmp_path_factory, db_backend: str) -> Iterator[Paged]:
    settings = test_settings(
        tmp_path_factory.mktemp("paged"),
        database_url=database_url(request, db_backend),
        embedded_worker=False,
    )
    live = start_server(settings)
    with httpx.Client(base_url=live.url, headers={"X-API-Key": API_KEY}, timeout=30) as http:
        for name in SCENES:
            assert http.post("/api/v1/scenes", json={"name": name}).status_code == 201
        rng = np.random.default_rng(0)
        for name in FRAME_UPLOADS:
            files = {
                "color": ("c.png", png(rng.integers(0, 256, (H, W, 3), dtype=np.uint8))),
                "depth": ("d.png", png(np.full((H, W), 1500, np.uint16))),
                "pose": ("p.txt", POSE.encode()),
                "intrinsics": ("k.txt", K.encode()),
            }
            r = http.post(ROUTES["frames"], files=files, data={"name": name})
            assert r.status_code == 201, r.text[:300]
        with session_scope(live.services.sessions) as s:
            for i, (name, lineage) in enumerate(MODELS):
                s.add(
                    ModelVersion(
                        name=name, lineage=lineage, arch="x", files={CHECKPOINT_FILE: f"{i:064x}"}
                    )
                )
        yield Paged(live, http)
    live.stop()


def key(route: str, row: dict) -> object:
    return row["name"] if route == "frames" else row["id"]


@pytest.mark.parametrize("route", list(ROUTES))
def test_the_whole_list_is_one_page_in_a_stable_order(paged: Paged, route: str) -> None:
    r = paged.http.get(ROUTES[route])  # no parameters: the default limit holds every row here
    assert r.status_code == 200
    rows = r.json()
    assert r.headers[TOTAL_COUNT_HEADER] == "5" and len(rows) == 5
    if route == "frames":
        assert [f["name"] for f in rows] == FRAME_ORDER
    else:
        ids = [row["id"] for row in rows]
        assert ids == sorted(ids)
        assert [row["name"] for row in rows] == (
            SCENES if route == "scenes" else [m for m, _ in MODELS]
        )
    assert rows == paged.whole(route)


@pytest.mark.parametrize("limit", [1, 2, 3, 4, 5])
@pytest.mark.parametrize("route", list(ROUTES))
def test_pages_slice_the_list_without_overlap_or_gap(paged: Paged, route: str, limit: int) -> None:
    whole = paged.whole(route)
    for offset in range(0, 7):
        r = paged.http.get(ROUTES[route], params={"limit": limit, "offset": offset})
        assert r.status_code == 200
        assert r.headers[TOTAL_COUNT_HEADER] == str(len(whole))
        assert [key(route, x) for x in r.json()] == [
            key(route, x) for x in whole[offset : offset + limit]
        ]
    pages = [
        paged.http.get(ROUTES[route], params={"limit": limit, "offset": o}).json()
        for o in range(0, len(whole), limit)
    ]
    assert list(itertools.chain.from_iterable(pages)) == whole


def test_the_total_counts_the_filtered_list(paged: Paged) -> None:
    r = paged.http.get(ROUTES["models"], params={"lineage": "alpha", "limit": 2})
    assert r.headers[TOTAL_COUNT_HEADER] == "3"
    assert [m["name"] for m in r.json()] == ["alpha-0", "alpha-1"]
    r = paged.http.get(ROUTES["models"], params={"lineage": "alpha", "limit": 2, "offset": 2})
    assert r.headers[TOTAL_COUNT_HEADER] == "3" and [m["name"] for m in r.json()] == ["alpha-2"]
    r = paged.http.get(ROUTES["models"], params={"lineage": "gamma"})
    assert r.status_code == 200 and r.json() == [] and r.headers[TOTAL_COUNT_HEADER] == "0"
    r = paged.http.get(f"/api/v1/scenes/{SCENES[1]}/frames")
    assert r.json() == [] and r.headers[TOTAL_COUNT_HEADER] == "0"


@pytest.mark.parametrize("route", list(ROUTES))
def test_the_largest_offset_reaches_the_database_and_answers_an_empty_page(
    paged: Paged, route: str
) -> None:
    r = paged.http.get(ROUTES[route], params={"limit": MAX_LIMIT, "offset": MAX_ID})
    assert r.status_code == 200, r.text[:300]
    assert r.json() == [] and r.headers[TOTAL_COUNT_HEADER] == "5"


@pytest.mark.parametrize(
    ("param", "value"),
    [
        ("limit", 0),
        ("limit", -1),
        ("limit", MAX_LIMIT + 1),
        ("limit", 2**63),
        ("limit", "ten"),
        ("offset", -1),
        ("offset", MAX_ID + 1),
        ("offset", 2**63 - 1),
        ("offset", 2**63),
        ("offset", "9" * 5000),
        ("offset", "1.5"),
    ],
)
@pytest.mark.parametrize("route", list(ROUTES))
def test_paging_out_of_range_is_a_422_naming_the_parameter(
    paged: Paged, route: str, param: str, value: object
) -> None:
    r = paged.http.get(ROUTES[route], params={param: value})
    assert r.status_code == 422, r.text[:300]
    assert r.json()["error"]["field"] == param
    assert TOTAL_COUNT_HEADER not in r.headers


def test_frames_of_a_missing_scene_are_404_whatever_the_page(paged: Paged) -> None:
    r = paged.http.get("/api/v1/scenes/no-such-scene/frames", params={"limit": 2, "offset": 1})
    assert r.status_code == 404


def test_the_openapi_document_names_the_parameters_and_the_header(paged: Paged) -> None:
    spec = paged.http.get("/openapi.json").json()
    for path in ("/api/v1/scenes", "/api/v1/scenes/{scene_ref}/frames", "/api/v1/models"):
        op = spec["paths"][path]["get"]
        params = {p["name"]: p["schema"] for p in op["parameters"]}
        assert params["limit"] == {
            **params["limit"],
            "minimum": 1,
            "maximum": MAX_LIMIT,
            "default": MAX_LIMIT,
        }
        assert params["offset"] == {
            **params["offset"],
            "minimum": 0,
            "maximum": MAX_ID,
            "default": 0,
        }
        ok = op["responses"]["200"]
        assert ok["headers"][TOTAL_COUNT_HEADER]["schema"]["type"] == "integer"
        assert ok["content"]["application/json"]["schema"]["type"] == "array"


# --- the client reads every page -------------------------------------------------------------


class Recording(httpx.HTTPTransport):
    """A real transport that remembers the (path, "offset N" or "after") of every GET."""

    def __init__(self) -> None:
        super().__init__()
        self.gets: list[tuple[str, str | None]] = []

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        if request.method == "GET":
            params = request.url.params
            where = "after" if "after" in params else f"offset {params.get('offset')}"
            self.gets.append((request.url.path, where))
        return super().handle_request(request)


@pytest.fixture
def recorded(paged: Paged) -> Iterator[tuple[CSAClient, Recording]]:
    transport = Recording()
    with CSAClient(paged.live.url, api_key=API_KEY, transport=transport) as c:
        c.page_size = 2
        yield c, transport


def test_the_client_pages_through_every_list(
    paged: Paged, recorded: tuple[CSAClient, Recording]
) -> None:
    c, transport = recorded
    assert [s.id for s in c.scenes()] == [s["id"] for s in paged.whole("scenes")]
    assert [s.name for s in c.scenes()] == SCENES
    assert [f.name for f in c.frames(SCENES[0])] == FRAME_ORDER
    assert [m.name for m in c.models()] == [m for m, _ in MODELS]
    assert c.frames(SCENES[1]) == []
    # The first page from offset 0, each next one after the cursor of the full page before.
    pages = ("offset 0", "after", "after")
    assert transport.gets == [
        *[("/api/v1/scenes", o) for o in pages] * 2,
        *[(ROUTES["frames"], o) for o in pages],
        *[("/api/v1/models", o) for o in pages],
        (f"/api/v1/scenes/{SCENES[1]}/frames", "offset 0"),
    ]


def test_the_client_follows_the_cursors_and_keeps_the_filter(
    paged: Paged, recorded: tuple[CSAClient, Recording]
) -> None:
    c, transport = recorded
    # One full page: its cursor is followed to an empty page (a total read while others
    # delete rows cannot say that all is read).
    assert [m.name for m in c.models(lineage="beta")] == ["beta-0", "beta-1"]
    assert [m.name for m in c.models(lineage="alpha")] == ["alpha-0", "alpha-1", "alpha-2"]
    assert transport.gets == [
        ("/api/v1/models", w) for w in ("offset 0", "after", "offset 0", "after")
    ]


def test_the_client_reads_a_server_without_cursors_by_offset_to_the_total(paged: Paged) -> None:
    """A server with pages but without cursors (no Link header): the client reads by offset
    and stops at the total."""
    rows = paged.whole("scenes")
    seen: list[httpx.Request] = []

    def no_cursors(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        offset, limit = int(request.url.params["offset"]), int(request.url.params["limit"])
        return httpx.Response(
            200, json=rows[offset : offset + limit], headers={TOTAL_COUNT_HEADER: str(len(rows))}
        )

    with CSAClient(
        "http://older-server.invalid", api_key=API_KEY, transport=httpx.MockTransport(no_cursors)
    ) as c:
        c.page_size = 2
        assert [s.name for s in c.scenes()] == SCENES
    assert [r.url.params["offset"] for r in seen] == ["0", "2", "4"]


def test_the_client_reads_a_server_without_pages_in_one_request(paged: Paged) -> None:
    """An older server ignores limit and offset and sends no X-Total-Count: its one answer is
    the whole list (asking for the next page would read the same rows again)."""
    rows = paged.whole("scenes")
    seen: list[httpx.Request] = []

    def old_server(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        return httpx.Response(200, json=rows)

    with CSAClient(
        "http://old-server.invalid", api_key=API_KEY, transport=httpx.MockTransport(old_server)
    ) as c:
        c.page_size = 2
        assert [s.name for s in c.scenes()] == SCENES
    assert len(seen) == 1


def test_the_command_line_lists_every_model_version(paged: Paged, monkeypatch, capsys) -> None:
    monkeypatch.setattr(CSAClient, "page_size", 2)
    monkeypatch.setattr(cli, "console", Console(width=200))  # a row per version, names unwrapped
    capsys.readouterr()
    assert cli_main(["--url", paged.live.url, "--api-key", API_KEY, "models"]) == 0
    out = capsys.readouterr().out
    assert all(name in out for name, _ in MODELS)


def test_the_dashboard_pages_still_show_every_row(paged: Paged) -> None:
    """The dashboard reads the lists through the routers' unpaged helpers (it shows and pages
    them itself): its pages render with every scene, frame and model version."""
    with httpx.Client(
        base_url=paged.live.url,
        timeout=30,
        follow_redirects=False,
        headers={"Origin": paged.live.url},
    ) as ui:
        assert (
            ui.post("/ui/login", data={"api_key": API_KEY, "next": "/ui/scenes"}).status_code == 303
        )
        pages = {
            path: ui.get(path)
            for path in (
                "/ui/scenes",
                "/ui/work",
                "/ui/models",
                "/ui/memory",
                f"/ui/scenes/{SCENES[0]}",
            )
        }
    assert {path: r.status_code for path, r in pages.items()} == dict.fromkeys(pages, 200)
    assert all(
        name in pages["/ui/scenes"].text and name in pages["/ui/work"].text for name in SCENES
    )
    assert all(name in pages["/ui/models"].text for name, _ in MODELS)
    assert all(
        f'alt="frame {name}"' in pages[f"/ui/scenes/{SCENES[0]}"].text for name in FRAME_ORDER
    )


# --- cursors ----------------------------------------------------------------------------------


def _follow(paged: Paged, path: str, limit: int, **params: object) -> list[httpx.Response]:
    """Every page of ``path`` from the first, each next one from its predecessor's Link."""
    pages = [paged.http.get(path, params={"limit": limit, **params})]
    while "next" in pages[-1].links:
        pages.append(paged.http.get(pages[-1].links["next"]["url"]))
        assert len(pages) < 20
    return pages


@pytest.mark.parametrize("limit", [1, 2, 3, 5])
@pytest.mark.parametrize("route", list(ROUTES))
def test_cursors_read_the_list_once_in_order(paged: Paged, route: str, limit: int) -> None:
    whole = paged.whole(route)
    pages = _follow(paged, ROUTES[route], limit)
    assert all(r.status_code == 200 and r.headers[TOTAL_COUNT_HEADER] == "5" for r in pages)
    assert list(itertools.chain.from_iterable(r.json() for r in pages)) == whole
    # A full page links to the next one, and only a full page: the last page is short (or
    # empty, after a last full page).
    assert all(len(r.json()) == limit for r in pages[:-1]) and len(pages[-1].json()) < limit
    assert pages[0].links["next"]["url"].startswith(paged.live.url + ROUTES[route])


def test_a_cursor_keeps_the_filter_of_its_list(paged: Paged) -> None:
    pages = _follow(paged, ROUTES["models"], 1, lineage="alpha")
    assert [m["name"] for r in pages for m in r.json()] == ["alpha-0", "alpha-1", "alpha-2"]


def test_a_cursor_neither_repeats_nor_skips_rows_others_add_or_delete_meanwhile(
    paged: Paged,
) -> None:
    """A frame uploaded before the page read so far shifts every later offset by one: the
    next page by offset repeats a frame, the cursor's does not; a scene deleted before the
    page read so far shifts them back: the next page by offset skips a scene, the cursor's
    does not."""
    http = paged.http
    assert http.post("/api/v1/scenes", json={"name": "cursor-live"}).status_code == 201
    extra = ["cursor-x", "cursor-y", "cursor-z"]
    try:
        frames = "/api/v1/scenes/cursor-live/frames"
        rng = np.random.default_rng(1)

        def upload(name: str) -> None:
            files = {
                "color": ("c.png", png(rng.integers(0, 256, (H, W, 3), dtype=np.uint8))),
                "depth": ("d.png", png(np.full((H, W), 1500, np.uint16))),
                "pose": ("p.txt", POSE.encode()),
                "intrinsics": ("k.txt", K.encode()),
            }
            assert http.post(frames, files=files, data={"name": name}).status_code == 201

        for name in ("2", "4", "6"):
            upload(name)
        first = http.get(frames, params={"limit": 1})
        assert [f["name"] for f in first.json()] == ["2"]
        upload("1")  # sorts before the frame read
        by_offset = http.get(frames, params={"limit": 1, "offset": 1}).json()
        by_cursor = http.get(first.links["next"]["url"]).json()
        assert [f["name"] for f in by_offset] == ["2"]  # read twice
        assert [f["name"] for f in by_cursor] == ["4"]

        for name in extra:
            assert http.post("/api/v1/scenes", json={"name": name}).status_code == 201
        ids = {s["name"]: s["id"] for s in paged.whole("scenes")}
        before_x = [n for n, i in ids.items() if i < ids["cursor-x"]]
        # The page that ends at cursor-x, then cursor-x itself deleted.
        page = http.get("/api/v1/scenes", params={"limit": len(before_x) + 1})
        assert page.json()[-1]["name"] == "cursor-x"
        assert http.delete("/api/v1/scenes/cursor-x").status_code == 204
        by_offset = http.get(
            "/api/v1/scenes", params={"limit": 1, "offset": len(before_x) + 1}
        ).json()
        by_cursor = http.get(page.links["next"]["url"]).json()
        assert [s["name"] for s in by_offset] == ["cursor-z"]  # cursor-y skipped
        assert [s["name"] for s in by_cursor] == ["cursor-y", "cursor-z"]
    finally:
        for name in ["cursor-live", *extra]:
            http.delete(f"/api/v1/scenes/{name}")
    assert [s["name"] for s in paged.whole("scenes")] == SCENES


@pytest.mark.parametrize(
    "cursor",
    [
        "not a cursor!",
        "e30",  # {} : not a list
        encode_cursor(["7"]),  # a text where the key is a number
        encode_cursor([True]),
        encode_cursor([1, 2]),  # another list's key
        encode_cursor([2**40]),
        encode_cursor([]),
        "x" * 513,
    ],
)
def test_a_cursor_this_server_did_not_give_is_a_422_naming_after(paged: Paged, cursor: str) -> None:
    r = paged.http.get(ROUTES["scenes"], params={"after": cursor})
    assert r.status_code == 422, r.text[:300]
    assert r.json()["error"]["field"] == "after"
    r = paged.http.get(
        ROUTES["frames"], params={"after": encode_cursor([1])}
    )  # frames: (key, name)
    assert r.status_code == 422 and r.json()["error"]["field"] == "after"


def test_a_cursor_and_an_offset_together_are_a_422(paged: Paged) -> None:
    r = paged.http.get(ROUTES["scenes"], params={"after": encode_cursor([1]), "offset": 2})
    assert r.status_code == 422 and r.json()["error"]["field"] == "offset"


@pytest.mark.parametrize("text", ["\x00", "\ud800"], ids=["nul", "lone-surrogate"])
def test_a_frame_cursor_naming_text_no_column_holds_is_a_422(paged: Paged, text: str) -> None:
    """A cursor is JSON, whose escapes spell text no frame name holds: a lone surrogate
    (``"\\ud800"``) cannot be encoded for the database and answered 500 on both backends, and
    PostgreSQL refused a NUL character with a 422 that named no field. Both are cursors this
    server never gave out."""
    r = paged.http.get(ROUTES["frames"], params={"after": encode_cursor([1, f"a{text}"])})
    assert r.status_code == 422, r.text[:300]
    assert r.json()["error"]["field"] == "after"


def test_frames_after_the_largest_number_get_keys_the_cursors_can_hold(paged: Paged) -> None:
    """A frame may be named 2147483647, the largest order key. The next frame uploaded without
    a name was numbered 2147483648, a name the server refuses from a client, and a named frame
    after it got that order key too: PostgreSQL refused both uploads (a 422 that named no
    field), SQLite stored them, and then the server refused the cursor of a page ending at one.
    A frame without a name is now a 422 naming ``name``; a named one shares the largest key
    (ordered by name), and the cursors walk the whole list."""
    http = paged.http
    frames = "/api/v1/scenes/paged-top/frames"
    rng = np.random.default_rng(2)

    def upload(name: str | None) -> httpx.Response:
        files = {
            "color": ("c.png", png(rng.integers(0, 256, (H, W, 3), dtype=np.uint8))),
            "depth": ("d.png", png(np.full((H, W), 1500, np.uint16))),
            "pose": ("p.txt", POSE.encode()),
            "intrinsics": ("k.txt", K.encode()),
        }
        return http.post(frames, files=files, data={} if name is None else {"name": name})

    assert http.post("/api/v1/scenes", json={"name": "paged-top"}).status_code == 201
    try:
        assert upload(str(MAX_ID)).status_code == 201
        r = upload(None)
        assert r.status_code == 422, r.text[:300]
        assert r.json()["error"]["field"] == "name" and "give the frame a name" in r.text
        for name in ("later-b", "later-a"):
            assert upload(name).status_code == 201, name
        pages = _follow(paged, frames, 1)
        assert all(p.status_code == 200 for p in pages), pages[-1].text[:300]
        names = [f["name"] for p in pages for f in p.json()]
        assert names == [str(MAX_ID), "later-a", "later-b"]
    finally:
        http.delete("/api/v1/scenes/paged-top")
    assert [s["name"] for s in paged.whole("scenes")] == SCENES
