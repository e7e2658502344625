"""Renders side by side (server/nerf_cache.py, docs/operations.md "Rendering"): concurrent renders
of one cached NeRF give the labels sequential ones give, no more run at once than the setting,
each on its share of torch threads, a render that waits past the queue time is answered 503 with
Retry-After, and the cache still keeps at most its size of models.

Nothing here measures time: renders are held and released with events."""

from __future__ import annotations

import gc
import threading
import weakref
from collections.abc import Callable, Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import httpx
import numpy as np
import pytest

from server import capabilities
from server.nerf_cache import RENDER_BUSY, NerfCache, RenderBusy
from server.settings import Settings
from tests.server.conftest import API_KEY, start_server, test_settings

needs_nerf = pytest.mark.skipif(not capabilities.available("nerf"), reason="renders a NeRF")

WAIT = 120.0  # seconds an event may take before the test fails (a deadlock guard, not a timing)


class Store:
    """What the cache reads of an ArtifactStore: checkpoint files by checksum."""

    def __init__(self, files: dict[str, Path]):
        self.files = files

    def open_verified(self, sha256: str) -> Path:
        return self.files[sha256]


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    """A tiny NeRF fitted for a moment (tests/nerf/conftest.py; its views hold several classes),
    saved."""
    from csa_core.nerf.checkpoint import save_checkpoint
    from csa_core.nerf.fit import fit_semantic_nerf
    from tests.nerf.conftest import synthetic_scene, tiny_config

    nerf, _ = fit_semantic_nerf(
        synthetic_scene(), "label-nyu40", tiny_config(steps=150), device="cpu", progress=False
    )
    path = tmp_path_factory.mktemp("nerf") / "nerf.safetensors"
    save_checkpoint(nerf, path)
    return path


@pytest.fixture
def store(checkpoint: Path) -> Store:
    return Store({"a": checkpoint, "b": checkpoint, "c": checkpoint})


def views(checkpoint: Path) -> tuple[Any, list[np.ndarray]]:
    """The checkpoint's camera and its training poses."""
    from csa_core.nerf.checkpoint import load_checkpoint

    nerf = load_checkpoint(checkpoint)
    return nerf.info.intrinsics, [np.asarray(p, dtype=np.float64) for p in nerf.info.train_poses]


class Gate:
    """An instrumented render: counts the renders inside it and holds each until ``at_least``
    are in at once (or until :meth:`open`), then renders for real or returns a blank view."""

    def __init__(self, cache: NerfCache, at_least: int, real: bool = True):
        self.real_draw = cache._draw
        self.at_least, self.real = at_least, real
        self.lock = threading.Lock()
        self.inside = self.most = self.calls = 0
        self.entered = threading.Event()  # a render is inside
        self.go = threading.Event()  # at_least renders were inside at once, or opened
        self.threads: list[int] = []  # torch threads of each render
        self.idents: list[int] = []  # the thread of each render
        cache._draw = self.draw  # type: ignore[method-assign]

    def open(self) -> None:
        self.go.set()

    def draw(self, nerf: Any, pose: np.ndarray, intrinsics: Any) -> Any:
        import torch

        with self.lock:
            self.inside += 1
            self.calls += 1
            self.most = max(self.most, self.inside)
            self.threads.append(torch.get_num_threads())
            self.idents.append(threading.get_ident())
            if self.inside >= self.at_least:
                self.go.set()
        self.entered.set()
        try:
            if not self.go.wait(WAIT):
                raise AssertionError(f"{self.at_least} renders never ran at once")
            if self.real:
                return self.real_draw(nerf, pose, intrinsics)
            h, w = intrinsics.height, intrinsics.width
            return SimpleNamespace(
                color=np.zeros((h, w, 3), np.uint8),
                depth=np.zeros((h, w), np.float32),
                labels=np.zeros((h, w), np.uint8),
            )
        finally:
            with self.lock:
                self.inside -= 1


def until(condition: Callable[[], bool]) -> None:
    """Wait for ``condition`` (fails after WAIT seconds: a hang, not a slow machine)."""
    stop = threading.Event()
    for _ in range(int(WAIT / 0.01)):
        if condition():
            return
        stop.wait(0.01)
    raise AssertionError("the renders never got there")


def in_threads(calls: list[Callable[[], Any]]) -> list[Any]:
    """Each call in a thread of its own, started together; their results (or exceptions)."""
    results: list[Any] = [None] * len(calls)
    start = threading.Barrier(len(calls))

    def one(i: int) -> None:
        start.wait()
        try:
            results[i] = calls[i]()
        except BaseException as e:  # noqa: BLE001 - handed to the test
            results[i] = e

    threads = [threading.Thread(target=one, args=(i,)) for i in range(len(calls))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(WAIT)
        assert not t.is_alive(), "a render never ended"
    return results


@needs_nerf
def test_concurrent_renders_of_one_cached_model_give_the_labels_of_sequential_ones(
    store: Store, checkpoint: Path, monkeypatch
) -> None:
    import csa_core.nerf.checkpoint as ckpt

    intr, poses = views(checkpoint)
    poses = poses[:4]
    sequential = NerfCache(store, 2, "cpu", concurrency=1, queue_seconds=WAIT, threads=1)
    expected = [sequential.render(1, {"n": "a"}, pose, intr) for pose in poses]
    sequential.close()
    assert all(len(np.unique(e["labels"])) > 1 for e in expected)  # labels, not one class

    loads = []
    real_load = ckpt.load_checkpoint
    monkeypatch.setattr(
        ckpt, "load_checkpoint", lambda *a, **kw: loads.append(1) or real_load(*a, **kw)
    )
    cache = NerfCache(store, 2, "cpu", concurrency=len(poses), queue_seconds=WAIT, threads=1)
    gate = Gate(cache, at_least=len(poses))  # every render inside the model at once
    got = in_threads([lambda pose=pose: cache.render(1, {"n": "a"}, pose, intr) for pose in poses])
    cache.close()
    assert gate.most == len(poses)
    assert len(loads) == 1 and cache.cached_ids() == [1]  # one model, loaded once, shared
    for want, have in zip(expected, got, strict=True):
        assert not isinstance(have, BaseException), have
        np.testing.assert_array_equal(have["labels"], want["labels"])
        np.testing.assert_array_equal(have["color"], want["color"])
        np.testing.assert_array_equal(have["depth"], want["depth"])


@needs_nerf
def test_no_more_renders_run_at_once_than_the_setting_each_on_its_share_of_threads(
    store: Store, checkpoint: Path
) -> None:
    import torch

    intr, poses = views(checkpoint)
    default = torch.get_num_threads()
    threads = 2 if default == 1 else 1  # differs from the process's, so that it shows
    cache = NerfCache(store, 1, "cpu", concurrency=2, queue_seconds=WAIT, threads=threads)
    gate = Gate(cache, at_least=99, real=False)  # holds every render until opened
    done: list[Any] = []
    clients = [
        threading.Thread(target=lambda: done.append(cache.render(1, {"n": "a"}, poses[0], intr)))
        for _ in range(7)
    ]
    for t in clients:
        t.start()
    try:
        # Two renders held inside, the other five handed over and waiting their turn.
        until(lambda: gate.inside == 2 and cache.in_flight() == 7)
    finally:
        gate.open()
        for t in clients:
            t.join(WAIT)
    cache.close()
    assert len(done) == 7 and gate.calls == 7
    assert gate.most == 2 and len(set(gate.idents)) == 2  # two render threads, never more
    assert set(gate.threads) == {threads}
    seen: list[int] = []
    fresh = threading.Thread(target=lambda: seen.append(torch.get_num_threads()))
    fresh.start()
    fresh.join()
    assert seen == [default]  # threads that start later keep the process's count (the jobs')
    assert cache.in_flight() == 0


@needs_nerf
def test_a_render_that_waits_past_the_queue_time_is_refused_with_retry_after(
    store: Store, checkpoint: Path
) -> None:
    intr, poses = views(checkpoint)
    cache = NerfCache(store, 1, "cpu", concurrency=1, queue_seconds=0, threads=1)
    gate = Gate(cache, at_least=2, real=False)  # holds the first render until opened
    first = threading.Thread(target=lambda: cache.render(1, {"n": "a"}, poses[0], intr))
    first.start()
    try:
        assert gate.entered.wait(WAIT)  # the one render thread is taken
        with pytest.raises(RenderBusy) as refused:
            cache.render(1, {"n": "a"}, poses[0], intr)
    finally:
        gate.open()
        first.join(WAIT)
    assert refused.value.status == 503 and refused.value.code == RENDER_BUSY
    assert int(refused.value.headers["Retry-After"]) >= 1
    assert "CSA_RENDER_QUEUE_SECONDS" in refused.value.message
    assert gate.calls == 1 and cache.in_flight() == 0  # the refused one never ran
    cache.render(1, {"n": "a"}, poses[0], intr)  # and left nothing queued: this one runs
    assert gate.calls == 2
    cache.close()


@needs_nerf
def test_the_cache_keeps_at_most_its_size_and_frees_what_it_evicts(
    store: Store, checkpoint: Path
) -> None:
    intr, poses = views(checkpoint)
    cache = NerfCache(store, 2, "cpu", concurrency=2, queue_seconds=WAIT, threads=1)
    first = weakref.ref(cache.get(1, {"n": "a"}))
    cache.get(2, {"n": "b"})
    cache.get(1, {"n": "a"})  # 1 used last: 2 goes next
    cache.render(3, {"n": "c"}, poses[0], intr)
    assert cache.cached_ids() == [1, 3]
    results = in_threads(
        [lambda i=i: cache.render(i, {"n": "abc"[i % 3]}, poses[0], intr) for i in range(4, 8)]
    )
    assert not [r for r in results if isinstance(r, BaseException)], results
    kept = cache.cached_ids()
    assert len(kept) == 2 and set(kept) <= {4, 5, 6, 7}
    gc.collect()
    assert first() is None  # evicted and no render holds it: freed
    cache.close()


# -- the route -------------------------------------------------------------------------------


@pytest.fixture
def busy_server(tmp_path, checkpoint: Path) -> Iterator[tuple[Any, int]]:
    """A server rendering one view at a time that refuses a render at once when it is busy,
    with a scene and its NeRF (registered directly in the memory bank)."""
    from server.db.session import session_scope
    from server.memory_bank import add_nerf

    live = start_server(
        test_settings(tmp_path, embedded_worker=False, render_concurrency=1, render_queue_seconds=0)
    )
    try:
        with live.client() as c:
            scene = c.create_scene("render-busy")
        services = live.services
        with session_scope(services.sessions) as s:
            add_nerf(
                s,
                services.store,
                scene.id,
                checkpoint,
                job_id=None,
                preset="test",
                labels_source="ground_truth",
                quality={},
            )
        yield live, scene.id
    finally:
        live.stop()


@needs_nerf
def test_the_route_answers_503_with_retry_after_while_its_renders_are_busy(
    busy_server, checkpoint: Path
) -> None:
    live, _ = busy_server
    cache: NerfCache = live.server.config.app.state.nerf_cache
    assert cache.concurrency == 1 and cache.queue_seconds == 0
    intr, poses = views(checkpoint)
    body = {"pose": poses[0].tolist(), "intrinsics": intr.to_dict(), "channels": ["labels"]}
    gate = Gate(cache, at_least=2)  # holds the first render until opened, then renders
    url = "/api/v1/scenes/render-busy/render"
    with httpx.Client(base_url=live.url, headers={"X-API-Key": API_KEY}, timeout=WAIT) as http:
        answers: list[httpx.Response] = []
        first = threading.Thread(target=lambda: answers.append(http.post(url, json=body)))
        first.start()
        try:
            assert gate.entered.wait(WAIT)  # the first render holds the one render thread
            refused = http.post(url, json=body)
        finally:
            gate.open()
            first.join(WAIT)
        assert refused.status_code == 503, refused.text
        assert int(refused.headers["Retry-After"]) >= 1
        assert refused.json()["error"]["code"] == RENDER_BUSY
        assert answers and answers[0].status_code == 200, answers and answers[0].text
        again = http.post(url, json=body)  # nothing was left queued: it renders at once
        assert again.status_code == 200, again.text
        assert set(again.json()["images"]) == {"labels"}
    assert gate.calls == 2 and gate.most == 1


def test_the_default_concurrency_takes_half_the_cores_for_renders(
    monkeypatch,
) -> None:
    import server.settings as settings_module

    for name in ("CSA_RENDER_CONCURRENCY", "CSA_RENDER_QUEUE_SECONDS", "CSA_TORCH_THREADS"):
        monkeypatch.delenv(name, raising=False)

    def settings(cores: int, **values: object) -> Settings:
        monkeypatch.setattr(settings_module, "available_cores", lambda: cores)
        return Settings(_env_file=None, **values)

    # (cores, (renders at once, torch threads of each)): renders together take half the cores.
    for cores, want in ((1, (1, 1)), (2, (1, 1)), (4, (2, 1)), (8, (4, 1)), (16, (4, 2))):
        s = settings(cores)
        assert (s.resolved_render_concurrency, s.render_threads) == want, cores
    s = settings(16, torch_threads=8)
    assert (s.resolved_render_concurrency, s.render_threads) == (4, 1)
    s = settings(2, render_concurrency=6)
    assert (s.resolved_render_concurrency, s.render_threads) == (6, 1)  # asked for: one each
    monkeypatch.setenv("CSA_RENDER_CONCURRENCY", "3")
    monkeypatch.setenv("CSA_RENDER_QUEUE_SECONDS", "2.5")
    s = settings(16)
    assert (s.resolved_render_concurrency, s.render_threads, s.render_queue_seconds) == (3, 2, 2.5)
