"""Dashboard sign-in, session cookies and cross-site protection, over plain HTTP against a
real server (no browser): the cookie never holds the key, the REST API never takes the
cookie, and state-changing dashboard requests need the session's CSRF token from this origin."""

from __future__ import annotations

import base64
import json
import stat
from collections.abc import Iterator
from contextlib import closing

import httpx
import pytest

from server.ui.session import COOKIE, SESSION_SECONDS, SessionSigner, load_secret
from tests.server.conftest import API_KEY, LiveServer, start_server, test_settings


@pytest.fixture(scope="module")
def live(tmp_path_factory) -> Iterator[LiveServer]:
    server = start_server(
        test_settings(
            tmp_path_factory.mktemp("ui-session"),
            embedded_worker=False,
            api_keys=[API_KEY, "second-key-abcdefgh"],
        )
    )
    yield server
    server.stop()


def http(live: LiveServer, **headers: str) -> httpx.Client:
    return httpx.Client(base_url=live.url, timeout=30, follow_redirects=False, headers=headers)


def signed_in(live: LiveServer, key: str = API_KEY) -> tuple[httpx.Client, str]:
    """A client holding a session cookie, and the session's CSRF token (read off a page)."""
    c = http(live, Origin=live.url)
    r = c.post("/ui/login", data={"api_key": key, "next": "/ui/jobs"})
    assert r.status_code == 303 and r.headers["location"] == "/ui/jobs"
    page = c.get("/ui/jobs")
    assert page.status_code == 200
    token = page.text.split('<meta name="csrf-token" content="', 1)[1].split('"', 1)[0]
    assert len(token) >= 32
    return c, token


def test_signer_round_trip_and_refusals() -> None:
    signer = SessionSigner(b"s" * 64)
    keys = ["key-one-0123456789", "key-two-0123456789"]
    cookie = signer.issue(keys[1], now=1000.0)
    session = signer.verify(cookie, keys, now=1001.0)
    assert session is not None and session.expires == 1000 + SESSION_SECONDS
    assert session.csrf_token == signer.csrf_token(session.nonce)
    body, sig = cookie.split(".")
    assert keys[1] not in base64.urlsafe_b64decode(body + "==").decode()
    assert signer.verify(cookie, keys, now=1000.0 + SESSION_SECONDS) is None  # expired
    assert signer.verify(cookie, keys[:1], now=1001.0) is None  # its key was removed
    assert signer.verify(cookie, keys[1:], now=1001.0) is not None
    forged = (
        base64.urlsafe_b64encode(
            json.dumps({"k": signer.key_id(keys[0]), "n": "x", "e": 10**10}).encode()
        )
        .decode()
        .rstrip("=")
    )
    assert signer.verify(f"{forged}.{sig}", keys, now=1001.0) is None  # signature of another body
    assert SessionSigner(b"t" * 64).verify(cookie, keys, now=1001.0) is None  # another secret
    for junk in (None, "", "a.b.c", "no-dot", "x" * 600):
        assert signer.verify(junk, keys, now=1001.0) is None
    other = signer.verify(signer.issue(keys[1], now=1000.0), keys, now=1001.0)
    assert other is not None and other.csrf_token != session.csrf_token  # one token per session


def test_secret_is_made_once_private_and_reused(tmp_path) -> None:
    first = load_secret(tmp_path)
    path = tmp_path / "ui_session_secret"
    assert stat.S_IMODE(path.stat().st_mode) == 0o600 and len(first) == 64
    assert load_secret(tmp_path) == first
    assert [p.name for p in tmp_path.iterdir()] == ["ui_session_secret"]  # no temporary left


def test_pages_without_a_session_redirect_to_sign_in(live: LiveServer) -> None:
    with http(live) as c:
        for path in (
            "/ui",
            "/ui/scenes",
            "/ui/jobs/1",
            "/ui/models",
            "/ui/continual",
            "/ui/memory",
            "/ui/try",
            "/ui/work",
        ):
            r = c.get(path)
            assert r.status_code == 303, path
            if path != "/ui":
                assert r.headers["location"].startswith("/ui/login?next=/ui/"), path
        c.cookies.set(COOKIE, "forged.value", domain="127.0.0.1", path="/ui")
        assert c.get("/ui/scenes").status_code == 303
        login = c.get("/ui/login")
        assert (
            login.status_code == 200
            and 'name="api_key"' in login.text
            and "Content-Security-Policy" in login.headers
        )


def test_the_dashboard_api_takes_only_the_session_and_the_rest_api_only_the_key(
    live: LiveServer,
) -> None:
    with http(live) as anonymous:
        assert anonymous.get("/ui/api/v1/scenes").status_code == 401
        assert anonymous.get("/ui/api/v1/scenes", headers={"X-API-Key": API_KEY}).status_code == 401
        assert anonymous.get("/ui/img/continual.png").status_code == 401
    c, _ = signed_in(live)
    with closing(c):
        assert c.get("/ui/api/v1/scenes").status_code == 200
        missing = c.get("/ui/scenes/no-such-scene")
        assert (
            missing.status_code == 404 and "scene &#39;no-such-scene&#39; not found" in missing.text
        )
        assert c.get("/ui/jobs/424242").status_code == 404
        assert c.get("/api/v1/scenes").status_code == 401  # the cookie opens no REST route
        assert c.get("/api/v1/scenes", headers={"X-API-Key": API_KEY}).status_code == 200
    paths = httpx.get(f"{live.url}/openapi.json").json()["paths"]
    assert not [p for p in paths if p.startswith("/ui")]


def test_wrong_or_missing_key_shows_the_sign_in_page(live: LiveServer) -> None:
    with http(live, Origin=live.url) as c:
        wrong = c.post("/ui/login", data={"api_key": "not-a-key", "next": "/ui/scenes"})
        assert (
            wrong.status_code == 401
            and "not valid" in wrong.text
            and 'name="api_key"' in wrong.text
        )
        assert "not-a-key" not in wrong.text and COOKIE not in wrong.headers.get("set-cookie", "")
        missing = c.post("/ui/login", data={"next": "/ui/scenes"})
        assert missing.status_code == 401 and "Enter an API key" in missing.text
    with http(live, Origin="http://evil.example") as c:
        cross = c.post("/ui/login", data={"api_key": API_KEY})
        assert cross.status_code == 403 and COOKIE not in cross.headers.get("set-cookie", "")


def test_session_cookie_is_http_only_strict_and_never_holds_the_key(live: LiveServer) -> None:
    with http(live, Origin=live.url) as c:
        r = c.post("/ui/login", data={"api_key": API_KEY, "next": "https://evil.example/"})
        assert r.status_code == 303 and r.headers["location"] == "/ui/scenes"  # no open redirect
        cookie = r.headers["set-cookie"]
        attrs = {a.strip().split("=")[0].lower() for a in cookie.split(";")}
        assert {
            "httponly",
            "path",
            "max-age",
            "samesite",
        } <= attrs and "samesite=strict" in cookie.lower()
        assert "Path=/ui" in cookie and API_KEY not in cookie
        body = cookie.split(";")[0].split("=", 1)[1].split(".")[0]
        assert API_KEY not in base64.urlsafe_b64decode(body + "==").decode()


def test_state_changes_need_the_csrf_token_and_this_origin(live: LiveServer) -> None:
    c, token = signed_in(live)
    with closing(c):
        assert c.post("/ui/api/v1/scenes", json={"name": "no-token"}).status_code == 403
        assert (
            c.post(
                "/ui/api/v1/scenes", json={"name": "bad-token"}, headers={"X-CSRF-Token": "x" * 43}
            ).status_code
            == 403
        )
        cross = c.post(
            "/ui/api/v1/scenes",
            json={"name": "cross"},
            headers={"X-CSRF-Token": token, "Origin": "http://evil.example"},
        )
        assert cross.status_code == 403 and "cross-site" in cross.json()["error"]["message"]
        ok = c.post(
            "/ui/api/v1/scenes",
            json={"name": "from-the-dashboard"},
            headers={"X-CSRF-Token": token},
        )
        assert ok.status_code == 201 and ok.json()["name"] == "from-the-dashboard"
        # A session's token is no good for another session.
        other, other_token = signed_in(live, "second-key-abcdefgh")
        with closing(other):
            assert other_token != token
            assert (
                other.post(
                    "/ui/api/v1/scenes", json={"name": "swapped"}, headers={"X-CSRF-Token": token}
                ).status_code
                == 403
            )
        assert c.post("/ui/logout", data={"csrf_token": "wrong"}).status_code == 403
        out = c.post("/ui/logout", data={"csrf_token": token})
        assert out.status_code == 303 and out.headers["location"] == "/ui/login"
        assert c.get("/ui/scenes").status_code == 303  # the cookie was cleared


def test_retry_queues_a_copy_of_a_cancelled_job_and_refuses_others(
    live: LiveServer, tmp_path
) -> None:
    """No worker runs here, so jobs stay queued until cancelled."""
    from csa_core.data.synth import synthesize

    (folder,) = synthesize(tmp_path, scenes=1, frames=3, size=(24, 18), family="office", seed=5)
    c, token = signed_in(live)
    csrf = {"X-CSRF-Token": token}
    with closing(c), live.client() as api:
        api.upload_scene_folder(folder)
        made = c.post(
            "/ui/api/v1/jobs",
            json={
                "kind": "fit_nerf",
                "params": {"scene": folder.name, "labels": "none", "steps": 5},
            },
            headers=csrf,
        )
        assert made.status_code == 202
        job = made.json()
        refused = c.post(f"/ui/api/jobs/{job['id']}/retry", headers=csrf)
        assert refused.status_code == 409 and "queued" in refused.json()["error"]["message"]
        assert (
            c.post(f"/ui/api/v1/jobs/{job['id']}/cancel", headers=csrf).json()["status"]
            == "cancelled"
        )
        assert c.post(f"/ui/api/jobs/{job['id']}/retry").status_code == 403  # no token
        again = c.post(f"/ui/api/jobs/{job['id']}/retry", headers=csrf)
        assert again.status_code == 202
        copy = again.json()
        assert copy["id"] != job["id"] and copy["status"] == "queued"
        assert (copy["kind"], copy["params"], copy["lineage"]) == (
            job["kind"],
            job["params"],
            job["lineage"],
        )
        assert f"retried as job {copy['id']}" in [line.message for line in api.job_log(job["id"])]
        assert f"retry of job {job['id']}" in [line.message for line in api.job_log(copy["id"])]
        page = c.get(f"/ui/jobs/{copy['id']}")
        assert page.status_code == 200 and f'href="/ui/jobs/{job["id"]}"' in page.text
        api.cancel_job(copy["id"])
        assert c.post("/ui/api/jobs/999999/retry", headers=csrf).status_code == 404


def test_a_pretrain_is_not_retried_while_a_copy_of_it_is_queued(live: LiveServer, tmp_path) -> None:
    """Retry queued a copy without asking whether the job's model name and lineage were still
    free: two retries of a cancelled pre-training queued two jobs that would each register a
    root of one lineage (the second failing on the name after all its training)."""
    from csa_core.data.synth import synthesize

    (folder,) = synthesize(tmp_path, scenes=1, frames=3, size=(24, 18), family="office", seed=6)
    c, token = signed_in(live)
    csrf = {"X-CSRF-Token": token}
    with closing(c), live.client() as api:
        api.upload_scene_folder(folder)
        params = {"scenes": [folder.name], "epochs": 1, "name": "retried-once"}
        job = c.post("/ui/api/v1/jobs", json={"kind": "pretrain", "params": params}, headers=csrf)
        assert job.status_code == 202, job.text[:300]
        api.cancel_job(job.json()["id"])
        copy = c.post(f"/ui/api/jobs/{job.json()['id']}/retry", headers=csrf)
        assert copy.status_code == 202, copy.text[:300]
        twice = c.post(f"/ui/api/jobs/{job.json()['id']}/retry", headers=csrf)
        assert twice.status_code == 409, twice.text[:300]
        error = twice.json()["error"]
        assert error["field"] == "params.name" and f"job {copy.json()['id']}" in error["message"]
        api.cancel_job(copy.json()["id"])
        third = c.post(f"/ui/api/jobs/{job.json()['id']}/retry", headers=csrf)
        assert third.status_code == 202, third.text[:300]
        api.cancel_job(third.json()["id"])


def test_dashboard_job_ids_have_the_api_s_range(live: LiveServer) -> None:
    """The job page and retry took ids up to 2**62, beyond the database's 32-bit ids (a
    PostgreSQL error instead of an answer naming the id); they take the REST API's range."""
    c, token = signed_in(live)
    with closing(c):
        for r in (
            c.get(f"/ui/jobs/{2**40}"),
            c.post(f"/ui/api/jobs/{2**40}/retry", headers={"X-CSRF-Token": token}),
        ):
            assert r.status_code == 422 and r.json()["error"]["field"] == "job_id", r.text[:300]
        assert c.get("/ui/jobs/2147483647").status_code == 404


def test_pages_escape_what_users_wrote(live: LiveServer) -> None:
    c, _ = signed_in(live)
    with closing(c), live.client() as api:
        api.create_scene("escaped", description='<script>alert("x")</script>')
        page = c.get("/ui/scenes")
        assert page.status_code == 200 and "<script>alert" not in page.text
        assert "&lt;script&gt;alert(&#34;x&#34;)&lt;/script&gt;" in page.text
        assert "script-src 'self'" in page.headers["content-security-policy"]


def test_dashboard_uploads_get_the_same_body_limits_as_the_api(live: LiveServer) -> None:
    from server.upload_limits import DEFAULT_LIMIT, BodyLimitMiddleware

    limits = BodyLimitMiddleware(None, live.settings)
    for path in (
        "/api/v1/scenes/s/archive",
        "/api/v1/scenes/s/frames",
        "/api/v1/models",
        "/api/v1/predict",
    ):
        assert (
            limits._limit("/ui" + path) == limits._limit(path)
            and limits._limit(path)[0] > DEFAULT_LIMIT
        )
    # The dashboard's prediction preview takes the images predict takes (it was held to the
    # 1 MiB of JSON bodies, below the 32 MiB its route reads: a phone photo got 413).
    assert limits._limit("/ui/api/predict-preview") == limits._limit("/api/v1/predict")
    assert limits._limit("/ui/api/v1/jobs")[0] == DEFAULT_LIMIT
    c, token = signed_in(live)
    with closing(c):
        photo = b"\xff\xd8" + bytes(2 * 1024 * 1024)  # 2 MiB, not an image the route can read
        r = c.post(
            "/ui/api/predict-preview",
            files={"image": ("p.jpg", photo, "image/jpeg")},
            headers={"X-CSRF-Token": token},
        )
        # Past the body limit and the CSRF check, the route itself answers: no model yet.
        assert r.status_code == 404 and "no current model" in r.text, r.text[:300]
        limit = live.settings.max_inference_upload_bytes
        r = c.post(
            "/ui/api/predict-preview",
            files={"image": ("p.jpg", bytes(limit + 2 * 1024 * 1024), "image/jpeg")},
            headers={"X-CSRF-Token": token},
        )
        assert r.status_code == 413, r.text[:300]
