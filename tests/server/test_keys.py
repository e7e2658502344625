"""API keys as data with scopes (docs/operations.md): every route of the OpenAPI document with
every kind of key, the hashing of the secret, expiry, revocation at the next request, device
ownership of scenes, and ``csa keys``. One server without a worker per backend; its keys are
made through the admin routes with the settings' key, which is an admin key."""

from __future__ import annotations

import datetime as dt
import hashlib
from collections.abc import Iterator
from contextlib import closing
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote

import cv2
import httpx
import numpy as np
import pytest
from sqlalchemy import select, text, update

from csa_core.cli.main import main as csa_main
from server.audit import record
from server.db.models import ApiKey, AuditEntry, Scene
from server.db.session import session_scope
from server.keys import SCOPES, Principal, hash_secret
from server.schemas.common import NUL_PROBLEM
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

# The scope each operation of the OpenAPI document needs (None: public). The test fails when a
# route is added without an entry here, so every new route is classified on purpose.
REQUIRED_SCOPE: dict[tuple[str, str], str | None] = {
    ("GET", "/health"): None,
    ("GET", "/metrics"): "operator",
    ("POST", "/api/v1/scenes"): "device",
    ("GET", "/api/v1/scenes"): "device",
    ("GET", "/api/v1/scenes/{scene_ref}"): "device",
    ("DELETE", "/api/v1/scenes/{scene_ref}"): "operator",
    ("POST", "/api/v1/scenes/{scene_ref}/frames"): "device",
    ("GET", "/api/v1/scenes/{scene_ref}/frames"): "device",
    ("GET", "/api/v1/scenes/{scene_ref}/frames/{name}"): "device",
    ("GET", "/api/v1/scenes/{scene_ref}/frames/{name}/{part}"): "device",
    ("POST", "/api/v1/scenes/{scene_ref}/archive"): "device",
    ("GET", "/api/v1/jobs/kinds"): "operator",
    ("POST", "/api/v1/jobs"): "operator",
    ("GET", "/api/v1/jobs"): "operator",
    ("GET", "/api/v1/jobs/{job_id}"): "operator",
    ("GET", "/api/v1/jobs/{job_id}/log"): "operator",
    ("POST", "/api/v1/jobs/{job_id}/cancel"): "operator",
    ("GET", "/api/v1/jobs/{job_id}/events"): "operator",
    ("GET", "/api/v1/models"): "operator",
    ("POST", "/api/v1/models"): "operator",
    ("GET", "/api/v1/models/{model_ref}"): "operator",
    ("POST", "/api/v1/models/{model_ref}/current"): "operator",
    ("GET", "/api/v1/models/{model_ref}/download"): "operator",
    ("GET", "/api/v1/memory"): "operator",
    ("GET", "/api/v1/memory/{scene_ref}"): "operator",
    ("GET", "/api/v1/memory/{scene_ref}/download"): "operator",
    ("GET", "/api/v1/metrics/continual"): "operator",
    ("POST", "/api/v1/predict"): "device",
    ("POST", "/api/v1/scenes/{scene_ref}/render"): "operator",
    ("POST", "/api/v1/keys"): "admin",
    ("GET", "/api/v1/keys"): "admin",
    ("POST", "/api/v1/keys/{key_ref}/revoke"): "admin",
    ("GET", "/api/v1/audit"): "admin",
}


def png(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return buf.tobytes()


def frame_files(seed: int) -> dict:
    rng = np.random.default_rng(seed)
    return {
        "color": ("c.png", png(rng.integers(0, 256, (H, W, 3), dtype=np.uint8))),
        "depth": ("d.png", png(np.full((H, W), 1500, np.uint16))),
        "pose": ("p.txt", POSE.encode()),
        "intrinsics": ("k.txt", K.encode()),
    }


@dataclass
class Keyed:
    live: LiveServer
    keys: dict[str, str]  # device, other-device, operator, admin, revoked, expired

    def http(self, who: str | None) -> httpx.Client:
        headers = {"X-API-Key": self.keys[who] if who in self.keys else who} if who else {}
        return httpx.Client(base_url=self.live.url, headers=headers, timeout=30)

    def make_key(self, name: str, scope: str, **extra: object) -> dict:
        with self.http(API_KEY) as admin:
            r = admin.post("/api/v1/keys", json={"name": name, "scope": scope, **extra})
        assert r.status_code == 201, r.text
        return r.json()


@pytest.fixture(scope="module")
def keyed(request, tmp_path_factory, db_backend: str) -> Iterator[Keyed]:
    settings = test_settings(
        tmp_path_factory.mktemp("keys"),
        database_url=database_url(request, db_backend),
        embedded_worker=False,
    )
    live = start_server(settings)
    k = Keyed(live, {"admin-settings": API_KEY})
    for name, scope in (
        ("device", "device"),
        ("other-device", "device"),
        ("operator", "operator"),
        ("admin", "admin"),
    ):
        k.keys[name] = k.make_key(f"walk-{name}", scope)["key"]
    k.keys["revoked"] = k.make_key("walk-revoked", "admin")["key"]
    k.keys["expired"] = k.make_key("walk-expired", "admin", expires_in="1m")["key"]
    with k.http(API_KEY) as admin:
        assert admin.post("/api/v1/keys/walk-revoked/revoke").status_code == 200
    with session_scope(live.services.sessions) as db:  # expired a minute ago
        db.execute(
            update(ApiKey)
            .where(ApiKey.name == "walk-expired")
            .values(expires_at=dt.datetime(2000, 1, 1))
        )
    for who, scene in (
        ("device", "dev-scene"),
        ("other-device", "other-scene"),
        ("operator", "op-scene"),
    ):
        with k.http(who) as c:
            assert c.post("/api/v1/scenes", json={"name": scene}).status_code == 201
            assert (
                c.post(
                    f"/api/v1/scenes/{scene}/frames",
                    files=frame_files(len(scene)),
                    data={"name": "0"},
                ).status_code
                == 201
            )
    yield k
    live.stop()


def _operations(live: LiveServer) -> list[tuple[str, str]]:
    spec = httpx.get(f"{live.url}/openapi.json", timeout=30).json()
    return [(method.upper(), path) for path, ops in spec["paths"].items() for method in ops]


def _request(c: httpx.Client, method: str, path: str) -> httpx.Response:
    """One request to an operation with placeholder values: the device's own scene (its key
    must reach it), ids and names that exist nowhere, and empty bodies (a 422, never a change).
    DELETE names no scene that exists, so an allowed delete is a 404 and the walk goes on."""
    values = {
        "scene_ref": "no-such-scene" if method == "DELETE" else "dev-scene",
        "name": "0",
        "part": "color",
        "job_id": "999999",
        "model_ref": "no-such-model",
        "key_ref": "no-such-key",
    }
    url = path.format(**values)
    if method in ("POST", "PUT", "PATCH"):
        return c.request(method, url, json={})
    return c.request(method, url)


def test_every_route_refuses_every_key_below_its_scope(keyed: Keyed) -> None:
    operations = _operations(keyed.live)
    assert sorted(operations) == sorted(REQUIRED_SCOPE), (
        "classify every route of the OpenAPI document in REQUIRED_SCOPE"
    )
    seen = 0
    for method, path in operations:
        needed = REQUIRED_SCOPE[(method, path)]
        if needed is None:
            with keyed.http(None) as c:
                assert _request(c, method, path).status_code == 200
            continue
        for who in (None, "revoked", "expired", "garbage-key-0123456789"):
            with keyed.http(who) as c:
                r = _request(c, method, path)
            assert r.status_code == 401, (method, path, who, r.status_code, r.text[:200])
            assert r.json()["error"]["code"] == "unauthorized"
        for who, scope in (
            ("device", "device"),
            ("operator", "operator"),
            ("admin", "admin"),
            ("admin-settings", "admin"),
        ):
            with keyed.http(who) as c:
                r = _request(c, method, path)
            seen += 1
            if SCOPES.index(scope) < SCOPES.index(needed):
                assert r.status_code == 403, (method, path, who, r.status_code, r.text[:200])
                assert f"needs scope {needed!r}" in r.json()["error"]["message"]
            else:  # reached the route: whatever it answers, it is not the key that is refused
                assert r.status_code not in (401, 403), (
                    method,
                    path,
                    who,
                    r.status_code,
                    r.text[:200],
                )
    assert seen == 4 * (len(REQUIRED_SCOPE) - 1)


def test_the_secret_is_stored_only_as_its_hash(keyed: Keyed) -> None:
    made = keyed.make_key("hash-check", "device", expires_in="30d")
    key = made["key"]
    assert key.startswith("csa_") and len(key) >= 4 + 43  # 32 random bytes, URL-safe base64
    assert made["prefix"] == key[:12] and made["state"] == "active"
    assert (
        dt.timedelta(days=29, hours=23)
        < dt.datetime.fromisoformat(made["expires_at"])
        - dt.datetime.fromisoformat(made["created_at"])
        <= dt.timedelta(days=30)
    )
    with keyed.live.services.sessions() as db:
        row = db.scalar(select(ApiKey).where(ApiKey.name == "hash-check"))
        assert row.secret_sha256 == hashlib.sha256(key.encode()).hexdigest() == hash_secret(key)
        rows = db.execute(text("SELECT * FROM api_keys")).all()
    secret = key[len("csa_") :]
    assert rows and not any(secret in str(value) for r in rows for value in r)
    with keyed.http("admin") as c:
        listed = c.get("/api/v1/keys").json()
    assert {k["name"] for k in listed} >= {"hash-check", "walk-device"}
    assert all("key" not in k and "secret_sha256" not in k for k in listed)


def test_revocation_and_expiry_take_effect_at_the_next_request(keyed: Keyed) -> None:
    key = keyed.make_key("short-lived", "device")["key"]
    with keyed.http(key) as c:
        assert c.get("/api/v1/scenes").status_code == 200
        with keyed.http("admin") as admin:
            r = admin.post("/api/v1/keys/short-lived/revoke")
            assert r.status_code == 200 and r.json()["state"] == "revoked"
        r = c.get("/api/v1/scenes")  # the same connection, the very next request
        assert r.status_code == 401 and "revoked" in r.json()["error"]["message"]

    made = keyed.make_key("expiring", "device", expires_in="2h")
    with keyed.http(made["key"]) as c:
        assert c.get("/api/v1/scenes").status_code == 200
        with session_scope(keyed.live.services.sessions) as db:
            db.execute(
                update(ApiKey)
                .where(ApiKey.name == "expiring")
                .values(
                    expires_at=dt.datetime.now(dt.UTC).replace(tzinfo=None)
                    - dt.timedelta(seconds=1)
                )
            )
        r = c.get("/api/v1/scenes")
        assert r.status_code == 401 and "expired" in r.json()["error"]["message"]
    with keyed.http("admin") as admin:
        states = {k["name"]: k["state"] for k in admin.get("/api/v1/keys").json()}
        assert states["expiring"] == "expired" and states["short-lived"] == "revoked"
        # revoke by prefix; names stay taken after revocation; bad input names its field
        prefix = keyed.make_key("by-prefix", "device")["prefix"]
        assert admin.post(f"/api/v1/keys/{prefix}/revoke").json()["name"] == "by-prefix"
        r = admin.post("/api/v1/keys", json={"name": "short-lived", "scope": "device"})
        assert r.status_code == 409 and r.json()["error"]["field"] == "name"
        r = admin.post("/api/v1/keys", json={"name": "x1", "scope": "device", "expires_in": "soon"})
        assert r.status_code == 422 and r.json()["error"]["field"] == "expires_in"
        r = admin.post("/api/v1/keys", json={"name": "data-dir-api-key", "scope": "admin"})
        assert (
            r.status_code == 422 and r.json()["error"]["field"] == "name"
        )  # the generated key's name
        r = admin.post("/api/v1/keys", json={"name": "x2", "scope": "root"})
        assert r.status_code == 422 and "scope" in r.json()["error"]["field"]
        assert admin.post("/api/v1/keys/no-such/revoke").status_code == 404


def test_lifetimes_past_the_last_expiry_date_are_a_422(keyed: Keyed, capsys) -> None:
    """``expires_in`` takes six digits and a unit: 999999w is past the year 9999, the last a
    datetime holds, and answered 500 (OverflowError), and ``csa keys create --expires 999999w``
    failed with a traceback. A lifetime over 100 years is refused naming the field, and no key
    is made; 100 years is still a lifetime."""
    with keyed.http(API_KEY) as admin:
        for lifetime in ("999999w", "36501d"):
            r = admin.post(
                "/api/v1/keys",
                json={"name": "too-long-lived", "scope": "device", "expires_in": lifetime},
            )
            assert r.status_code == 422, r.text[:300]
            error = r.json()["error"]
            assert error["field"] == "expires_in" and "more than 36500 days" in error["message"]
        assert "too-long-lived" not in {k["name"] for k in admin.get("/api/v1/keys").json()}
    made = keyed.make_key("a-century", "device", expires_in="36500d")
    assert dt.datetime.fromisoformat(made["expires_at"]).year >= 2100
    where = _database_options(keyed)
    code, _, err = _cli(
        capsys,
        "keys",
        *where,
        "create",
        "--scope",
        "device",
        "--name",
        "robot-9",
        "--expires",
        "999999w",
    )
    assert code == 1 and "more than 36500 days" in err


def test_a_device_key_reaches_only_its_own_scenes(keyed: Keyed) -> None:
    with keyed.http("device") as c:
        r = c.get("/api/v1/scenes")
        assert [s["name"] for s in r.json()] == ["dev-scene"] and r.headers["X-Total-Count"] == "1"
        for method, url in (
            ("GET", "/api/v1/scenes/other-scene"),
            ("GET", "/api/v1/scenes/op-scene/frames"),
            ("GET", "/api/v1/scenes/other-scene/frames/0"),
            ("GET", "/api/v1/scenes/other-scene/frames/0/color"),
        ):
            r = c.request(method, url)
            assert r.status_code == 403, (url, r.text)
            assert "need scope 'operator'" in r.json()["error"]["message"]
        r = c.post("/api/v1/scenes/other-scene/frames", files=frame_files(7), data={"name": "1"})
        assert r.status_code == 403
        r = c.post("/api/v1/scenes/dev-scene/frames", files=frame_files(8), data={"name": "1"})
        assert r.status_code == 201
        assert c.get("/api/v1/scenes/dev-scene/frames").headers["X-Total-Count"] == "2"
        assert c.get("/api/v1/scenes/no-such-scene").status_code == 404
        assert c.delete("/api/v1/scenes/dev-scene").status_code == 403  # deleting needs operator
    with keyed.http("operator") as c:
        names = {s["name"] for s in c.get("/api/v1/scenes").json()}
        assert {"dev-scene", "other-scene", "op-scene"} <= names
        assert c.get("/api/v1/scenes/other-scene/frames/0/color").status_code == 200
    with keyed.live.services.sessions() as db:
        owners = dict(
            db.execute(
                select(Scene.name, ApiKey.name).join(ApiKey, ApiKey.id == Scene.owner_key_id)
            ).all()
        )
    assert owners["dev-scene"] == "walk-device" and owners["other-scene"] == "walk-other-device"


def test_the_audit_log_records_writes(keyed: Keyed) -> None:
    with keyed.http("device") as c:
        made = c.post("/api/v1/scenes", json={"name": "audited"})
        assert made.status_code == 201
        assert c.delete("/api/v1/scenes/audited").status_code == 403
        assert c.get("/api/v1/scenes").status_code == 200  # a read: not recorded
    with keyed.http(None) as c:
        assert (
            c.post("/api/v1/scenes", json={"name": "anonymous"}).status_code == 401
        )  # no key: not recorded
    with keyed.http("device") as c:
        r = c.get("/api/v1/audit")
        assert r.status_code == 403 and "needs scope 'admin'" in r.json()["error"]["message"]
    with keyed.http("admin") as c:
        r = c.get("/api/v1/audit", params={"key_name": "walk-device", "limit": 2})
        assert r.status_code == 200 and 'rel="next"' in r.headers["Link"]
        newest = r.json()
        total = int(r.headers["X-Total-Count"])
        whole = c.get("/api/v1/audit", params={"key_name": "walk-device"}).json()
    assert len(whole) == total and [e["id"] for e in whole] == sorted(
        (e["id"] for e in whole), reverse=True
    )
    refused, created = newest
    assert (refused["method"], refused["route"], refused["path"], refused["status"]) == (
        "DELETE",
        "/api/v1/scenes/{scene_ref}",
        "/api/v1/scenes/audited",
        403,
    )
    assert refused["ids"] == {"scene_ref": "audited"} and refused["scope"] == "device"
    assert (created["method"], created["route"], created["status"]) == (
        "POST",
        "/api/v1/scenes",
        201,
    )
    assert (
        created["ids"] == {"created_id": made.json()["id"]} and created["key_name"] == "walk-device"
    )
    with keyed.live.services.sessions() as db:
        entries = list(db.scalars(select(AuditEntry)))
    assert all(e.method in ("POST", "PUT", "PATCH", "DELETE") for e in entries)
    assert not any(
        e.route in ("/api/v1/predict", "/api/v1/scenes/{scene_ref}/render") for e in entries
    )
    assert not any("anonymous" in e.path for e in entries)
    assert any(
        e.key_name == "CSA_API_KEYS#1"
        and e.route == "/api/v1/keys/{key_ref}/revoke"
        and e.ids == {"key_ref": "walk-revoked"}
        for e in entries
    )


def _string_parameters(live: LiveServer) -> list[tuple[str, str, str, str]]:
    """(method, path, "path" or "query", name) of every text parameter in the OpenAPI document."""
    spec = httpx.get(f"{live.url}/openapi.json", timeout=30).json()
    return [
        (method.upper(), path, p["in"], p["name"])
        for path, ops in spec["paths"].items()
        for method, op in ops.items()
        for p in op.get("parameters", [])
        if any(s.get("type") == "string" for s in p["schema"].get("anyOf", [p["schema"]]))
    ]


# Parameters whose only rule is "no NUL character" (the others have a pattern, a set of values
# or, for ``after``, the cursors' own check, and are refused naming them all the same).
PLAIN_TEXT = {"scene_ref", "name", "model_ref", "key_ref", "key_name", "method"}


def test_nul_characters_in_path_and_query_parameters_are_a_422_naming_them(
    keyed: Keyed,
) -> None:
    """A NUL character (``%00``) in a reference or a filter (``/keys/%00/revoke``,
    ``/audit?key_name=%00``) reached the database: PostgreSQL refused it and the answer was a
    422 naming no field, and SQLite answered an empty list. Every text parameter of every
    route, in the path or the query, the dashboard's too, is refused with a 422 naming it."""
    params = _string_parameters(keyed.live)
    assert {(m, p, n) for m, p, _, n in params} >= {
        ("POST", "/api/v1/keys/{key_ref}/revoke", "key_ref"),
        ("GET", "/api/v1/audit", "key_name"),
        ("GET", "/api/v1/audit", "method"),
        ("GET", "/api/v1/scenes/{scene_ref}/frames", "after"),
        ("GET", "/api/v1/scenes/{scene_ref}/frames/{name}", "name"),
    }
    placeholders = {
        "scene_ref": "dev-scene",
        "name": "0",
        "part": "color",
        "model_ref": "no-such-model",
        "key_ref": "no-such-key",
    }
    nul = "a\x00b"
    with keyed.http("admin-settings") as c:
        for method, path, where, name in params:
            url = path.format(
                **{**placeholders, name: quote(nul)} if where == "path" else placeholders
            )
            r = c.request(method, url, params={name: nul} if where == "query" else None)
            assert r.status_code == 422, (method, path, name, r.status_code, r.text[:300])
            error = r.json()["error"]
            assert error["field"] == name and error["message"].startswith(f"{name}: "), error
            if name in PLAIN_TEXT:
                assert error["message"].startswith(f"{name}: {NUL_PROBLEM}"), error
    with keyed.http("device") as c:  # a device key's scene is looked up before the route runs
        for method in ("GET", "POST"):
            r = c.request(method, "/api/v1/scenes/a%00b/frames")
            assert r.status_code == 422 and r.json()["error"]["field"] == "scene_ref", r.text
    origin = {"Origin": keyed.live.url}
    with httpx.Client(base_url=keyed.live.url, timeout=30, follow_redirects=False) as ui:
        r = ui.post("/ui/login", data={"api_key": keyed.keys["admin"]}, headers=origin)
        assert r.status_code == 303, r.text[:300]
        for url, name in (
            ("/ui/audit?key_name=%00", "key_name"),
            ("/ui/continual?lineage=%00", "lineage"),
            ("/ui/scenes/a%00b", "scene_ref"),
            ("/ui/scenes/dev-scene?frame=%00", "frame"),
            ("/ui/img/scenes/dev-scene/frames/a%00b/truth.png", "name"),
        ):
            r = ui.get(url)
            assert r.status_code == 422, (url, r.status_code, r.text[:300])
            assert r.json()["error"] == {
                "code": "invalid",
                "message": f"{name}: {NUL_PROBLEM}",
                "field": name,
            }


def test_writes_to_paths_holding_a_nul_character_are_audited(keyed: Keyed) -> None:
    """A write whose path holds ``%00`` lost its audit entry on PostgreSQL, whose text cannot
    hold a NUL character (the insert failed after the answer), and kept the NUL on SQLite. The
    entry is written on both, with the four characters ``\\x00`` in its place; the answer is
    the 422 naming the parameter (or the 403 of a scope), never a 500."""
    with keyed.http("device") as c:
        r = c.post("/api/v1/scenes/robot%00room/frames")
        assert r.status_code == 422 and r.json()["error"]["field"] == "scene_ref", r.text
        assert c.delete("/api/v1/scenes/robot%00room").status_code == 403  # needs operator
    with keyed.http(API_KEY) as admin:
        r = admin.post("/api/v1/keys/%00/revoke")
        assert r.status_code == 422 and r.json()["error"]["field"] == "key_ref", r.text
        deleted, posted = admin.get(
            "/api/v1/audit", params={"key_name": "walk-device", "limit": 2}
        ).json()
        (revoked,) = admin.get(
            "/api/v1/audit", params={"key_name": "CSA_API_KEYS#1", "limit": 1}
        ).json()
    assert (posted["route"], posted["path"], posted["ids"], posted["status"]) == (
        "/api/v1/scenes/{scene_ref}/frames",
        "/api/v1/scenes/robot\\x00room/frames",
        {"scene_ref": "robot\\x00room"},
        422,
    )
    assert (deleted["method"], deleted["path"], deleted["status"]) == (
        "DELETE",
        "/api/v1/scenes/robot\\x00room",
        403,
    )
    assert (revoked["path"], revoked["ids"], revoked["status"]) == (
        "/api/v1/keys/\\x00/revoke",
        {"key_ref": "\\x00"},
        422,
    )
    # Every text the writer stores, a lone surrogate and an over-long path too.
    record(
        keyed.live.services.sessions,
        Principal("nul\x00key", "dev\x00ice"),
        "PO\x00ST",
        "/api/v1/r\x00/{x}",
        "/api/v1/r\x00\udcff/" + "p" * 2000,
        {"x\x00": "v\x00\udcff", "created_id": 7},
        201,
    )
    with keyed.live.services.sessions() as db:
        entry = db.scalar(select(AuditEntry).where(AuditEntry.key_name == "nul\\x00key"))
    assert entry is not None
    assert (entry.scope, entry.method, entry.route) == (
        "dev\\x00ice",
        "PO\\x00ST",
        "/api/v1/r\\x00/{x}",
    )
    assert entry.path.startswith("/api/v1/r\\x00\\udcff/ppp") and len(entry.path) == 1024
    assert entry.ids == {"x\\x00": "v\\x00\\udcff", "created_id": 7}


def _database_options(keyed: Keyed) -> list[str]:
    """``csa keys`` options that reach the live server's database."""
    settings = keyed.live.settings
    url = ["--database-url", settings.database_url] if settings.database_url else []
    return ["--data-dir", str(settings.data_dir), *url]


def _cli(capsys, *args: str) -> tuple[int, str, str]:
    code = csa_main(list(args))
    out = capsys.readouterr()
    return code, out.out, out.err


def _create_device_key(capsys, where: list[str], name: str, *options: str):
    """``csa keys create --scope device --name NAME [OPTIONS]`` against ``where``."""
    return _cli(capsys, "keys", *where, "create", "--scope", "device", "--name", name, *options)


def test_csa_keys_commands(keyed: Keyed, capsys) -> None:
    where = _database_options(keyed)
    code, out, err = _create_device_key(capsys, where, "robot-7", "--expires", "30d")
    assert code == 0 and "store it now" in err
    key = out.strip()
    assert key.startswith("csa_") and "\n" not in key
    with keyed.http(key) as c:
        assert c.post("/api/v1/scenes", json={"name": "robot-7-room"}).status_code == 201
        code, out, _ = _cli(capsys, "keys", *where, "list")
        assert code == 0
        line = next(row for row in out.splitlines() if row.startswith("robot-7 "))
        assert key[:12] in line and " device " in line and " active " in line and key not in out
        code, out, _ = _cli(capsys, "keys", *where, "revoke", key[:12])
        assert code == 0 and "revoked key 'robot-7'" in out
        r = c.get("/api/v1/scenes")  # revoked in the database by another program: the next request
        assert r.status_code == 401 and "revoked" in r.json()["error"]["message"]
    code, out, _ = _cli(capsys, "keys", *where, "list", "--active")
    assert code == 0 and "robot-7" not in out
    code, _, err = _create_device_key(capsys, where, "robot-7")
    assert code == 1 and "robot-7" in err and "exists" in err
    code, _, err = _create_device_key(capsys, where, "robot-8", "--expires", "3x")
    assert code == 1 and "not a duration" in err
    code, _, err = _cli(capsys, "keys", *where, "revoke", "nobody")
    assert code == 1 and "not found" in err


def test_csa_keys_create_names_its_options_in_errors(keyed: Keyed, capsys) -> None:
    """``csa keys create --expires 3x`` said ``expires_in: '3x' is not a duration``, the name
    of the REST body's field, which the command has no option for. Its errors name the option
    and what is wrong; the route still names its body's field."""
    where = _database_options(keyed)
    for expires, problem in (
        ("3x", "'3x' is not a duration (a positive number and a unit m, h, d or w: 30d, 12h)"),
        ("0d", "'0d' is not a duration"),
        ("999999w", "'999999w' is more than 36500 days"),
    ):
        code, out, err = _create_device_key(capsys, where, "robot-10", "--expires", expires)
        assert code == 1 and out == ""
        assert f"csa keys create: --expires: {problem}" in err and "expires_in" not in err
    code, _, err = _create_device_key(capsys, where, "9 lives")
    assert code == 1 and "csa keys create: --name: '9 lives' is not a key name" in err
    with keyed.http(API_KEY) as admin:
        assert "robot-10" not in {k["name"] for k in admin.get("/api/v1/keys").json()}
        r = admin.post(
            "/api/v1/keys", json={"name": "robot-10", "scope": "device", "expires_in": "3x"}
        )
    assert r.status_code == 422
    assert r.json()["error"]["field"] == "expires_in"
    assert r.json()["error"]["message"].startswith("expires_in: '3x' is not a duration")


def test_the_dashboard_signs_in_by_key_and_shows_what_the_scope_allows(keyed: Keyed) -> None:
    origin = {"Origin": keyed.live.url}

    def signed_in(key: str) -> httpx.Client:
        c = httpx.Client(base_url=keyed.live.url, timeout=30, follow_redirects=False)
        r = c.post("/ui/login", data={"api_key": key, "next": "/ui/scenes"}, headers=origin)
        assert r.status_code == 303, r.text[:300]
        return c

    device_key = keyed.make_key("ui-device", "device")["key"]
    with closing(signed_in(device_key)) as c:
        page = c.get("/ui/scenes")
        assert page.status_code == 200 and "ui-device (device)" in page.text
        assert 'href="/ui/jobs"' not in page.text and 'href="/ui/audit"' not in page.text
        assert "dev-scene" not in page.text  # another key's scene
        for url in ("/ui/jobs", "/ui/audit", "/ui/api/v1/jobs", "/ui/scenes/dev-scene"):
            assert c.get(url).status_code == 403, url
        csrf = c.get("/ui/scenes").text.split('name="csrf-token" content="')[1].split('"')[0]
        r = c.post(
            "/ui/api/v1/scenes", json={"name": "ui-scene"}, headers={**origin, "X-CSRF-Token": csrf}
        )
        assert r.status_code == 201
        assert (
            "ui-scene" in c.get("/ui/scenes").text
            and c.get("/ui/scenes/ui-scene").status_code == 200
        )
        with keyed.http("admin") as admin:
            assert admin.post("/api/v1/keys/ui-device/revoke").status_code == 200
        r = c.get("/ui/scenes")  # the session ends with its key
        assert r.status_code == 303 and r.headers["location"].startswith("/ui/login")
        assert c.get("/ui/api/v1/scenes").status_code == 401
    with closing(signed_in(keyed.keys["admin"])) as c:
        page = c.get("/ui/audit", params={"key_name": "ui-device"})
        assert page.status_code == 200 and 'href="/ui/audit"' in page.text
        assert (
            "/ui/api/v1/scenes" in page.text and "ui-device" in page.text
        )  # the dashboard's write
        assert "/ui/login" in page.text  # and its sign-in
    with httpx.Client(base_url=keyed.live.url, timeout=30) as c:
        r = c.post("/ui/login", data={"api_key": keyed.keys["revoked"]}, headers=origin)
        assert r.status_code == 401


def test_the_embedded_default_key_is_an_admin_key(tmp_path: Path, db_backend: str) -> None:
    if db_backend != "sqlite":
        pytest.skip("the embedded default is SQLite in the data folder")
    live = start_server(test_settings(tmp_path, api_keys=[], embedded_worker=False))
    try:
        key = (tmp_path / "api_key").read_text().strip()
        assert (tmp_path / "api_key").stat().st_mode & 0o777 == 0o600
        with httpx.Client(base_url=live.url, headers={"X-API-Key": key}, timeout=30) as c:
            assert c.get("/api/v1/keys").status_code == 200
            assert c.post("/api/v1/scenes", json={"name": "embedded"}).status_code == 201
            entry = c.get("/api/v1/audit").json()[0]
        assert entry["key_name"] == "data-dir-api-key" and entry["scope"] == "admin"
    finally:
        live.stop()
    live = start_server(
        test_settings(tmp_path, api_keys=[], embedded_worker=False)
    )  # the same key after a restart
    try:
        with httpx.Client(base_url=live.url, headers={"X-API-Key": key}, timeout=30) as c:
            assert c.get("/api/v1/scenes/embedded").status_code == 200
    finally:
        live.stop()
