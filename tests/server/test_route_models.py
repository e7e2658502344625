"""The app makes every route's validation models when it is created, not while it serves.

FastAPI makes a route's models (its parameters, body and answers) under a process-wide warnings
filter that hides pydantic's ``UnsupportedFieldAttributeWarning`` about the alias FastAPI gives
each parameter (``after``, ``limit``, ...). Made at the first request, in a server thread, that
filter could be undone meanwhile by another thread restoring its own filters (the test runner
does so around every test), and the warning escaped in some test orders. ``create_app`` now
makes them all in the thread that creates the app (server/app.py), so serving makes none.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import httpx
import pytest
from pydantic import TypeAdapter
from pydantic.warnings import UnsupportedFieldAttributeWarning

from tests.server.conftest import API_KEY, start_server, test_settings


def test_serving_paged_lists_makes_no_validation_models_and_warns_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    live = start_server(test_settings(tmp_path, embedded_worker=False))
    made: list[object] = []
    real_init = TypeAdapter.__init__

    def counted_init(self, *args, **kwargs) -> None:
        made.append(args[0] if args else kwargs.get("type"))
        real_init(self, *args, **kwargs)

    monkeypatch.setattr(TypeAdapter, "__init__", counted_init)
    try:
        with (
            warnings.catch_warnings(record=True) as caught,
            httpx.Client(base_url=live.url, headers={"X-API-Key": API_KEY}, timeout=30) as c,
        ):
            warnings.simplefilter("always")
            for name in ("paged-a", "paged-b"):
                assert c.post("/api/v1/scenes", json={"name": name}).status_code == 201
            first = c.get("/api/v1/scenes", params={"limit": 1})
            assert first.status_code == 200 and 'rel="next"' in first.headers["Link"]
            after = httpx.URL(first.links["next"]["url"]).params["after"]
            second = c.get("/api/v1/scenes", params={"limit": 1, "after": after})
            assert [s["name"] for s in first.json() + second.json()] == ["paged-a", "paged-b"]
            assert c.get("/api/v1/scenes", params={"after": "x", "offset": 1}).status_code == 422
            for path in ("/api/v1/keys", "/api/v1/audit", "/api/v1/models"):
                assert c.get(path, params={"limit": 1}).status_code == 200, path
            assert c.get("/ui/login").status_code == 200
    finally:
        live.stop()
    assert made == [], f"{len(made)} validation models made while serving"
    assert not [w for w in caught if issubclass(w.category, UnsupportedFieldAttributeWarning)]
