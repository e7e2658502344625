"""Scene NeRFs loaded from the memory bank for rendering, kept by checkpoint id (LRU), and the
renders themselves: a bounded number at a time per process (docs/operations.md "Rendering").

Renders run in a pool of ``concurrency`` threads (``CSA_RENDER_CONCURRENCY``), each with
``threads`` torch threads (``Settings.render_threads``), so that renders side by side do not
oversubscribe the cores. A render that finds every thread busy waits its turn at most
``queue_seconds`` (``CSA_RENDER_QUEUE_SECONDS``) and is then refused with :class:`RenderBusy`,
503 with ``Retry-After``, instead of hanging until its client gives up. The API's route waits in
the event loop (:meth:`NerfCache.run`), holding no worker thread; the dashboard's panels wait in
their own thread (:meth:`NerfCache.render`).

Concurrent renders share one loaded model. Rendering only reads it: ``SemanticNerf.render_rays``
runs under inference mode, samplers are made per call and the occupancy grid is changed only by
training (``OccupancySampler.update_every_n_steps``, ``SemanticNerf.update_occupancy``); the C
hash kernel allocates its output per call and builds its library under a lock
(``csa_core/nerf/hash_kernel.py``). The exception is a model whose hash encoding is compiled
(``HashEncodingConfig.compile``): the compiled function is one per process
(``csa_core/nerf/hash_encoding.py``, ``_compiled_corners``) and torch.compile traces on first
calls, so such models render one at a time.

The cache keeps at most ``size`` models (``CSA_MODEL_CACHE_SIZE``). A model is loaded inside its
render's turn, once even when several renders ask for it at once, and one evicted while a render
uses it is freed when that render ends: at most ``size + concurrency`` models are in memory.
"""

from __future__ import annotations

import asyncio
import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import nullcontext
from functools import partial
from typing import Any, TypeVar

import numpy as np

from csa_core.data.camera import Intrinsics
from server.artifacts import ArtifactStore
from server.errors import APIError

T = TypeVar("T")

RENDER_BUSY = "render_busy"

_THREADS_LOCK = threading.Lock()
_COMPILED_LOCK = threading.Lock()  # renders of models with a compiled encoding, one at a time


class RenderBusy(APIError):
    """Every render thread stayed busy for the queue time: 503 with ``Retry-After``."""

    def __init__(self, concurrency: int, queue_seconds: float, retry_after: int):
        super().__init__(
            503,
            RENDER_BUSY,
            f"every render of this process is busy ({concurrency} at a time, "
            f"CSA_RENDER_CONCURRENCY) and this one waited {queue_seconds:g} s for its turn "
            f"(CSA_RENDER_QUEUE_SECONDS); retry in {retry_after} s",
            headers={"Retry-After": str(retry_after)},
        )
        self.retry_after = retry_after


def _render_thread(threads: int | None) -> None:
    """The start of a render thread: ``threads`` torch threads for what it runs.

    ``torch.set_num_threads`` sets the calling thread's count (OpenMP keeps one per thread) and
    also the count that threads which have not run torch yet start from (ATen keeps one per
    process): the jobs' thread must keep its own, so a short-lived thread sets that one back."""
    if threads is None:
        return
    try:
        import torch
    except ImportError:  # a build without torch renders nothing
        return
    with _THREADS_LOCK:
        default = torch.get_num_threads()
        torch.set_num_threads(threads)
        if default != threads:
            restore = threading.Thread(
                target=torch.set_num_threads, args=(default,), name="render-threads"
            )
            restore.start()
            restore.join()


def _compiled(nerf: Any) -> bool:
    """Whether ``nerf``'s hash encoding is compiled (``HashEncodingConfig.compile``)."""
    encoding = getattr(getattr(nerf, "field", None), "encoding", None)
    return bool(getattr(getattr(encoding, "cfg", None), "compile", False))


class NerfCache:
    def __init__(
        self,
        store: ArtifactStore,
        size: int,
        device: str | None,
        concurrency: int = 1,
        queue_seconds: float = 30.0,
        threads: int | None = None,
    ):
        self.store = store
        self.size = max(1, size)
        self.device = device  # None: auto, CUDA when present (Settings.device)
        self.concurrency = max(1, concurrency)
        self.queue_seconds = max(0.0, queue_seconds)
        self.threads = threads  # torch threads of each render thread (None: the process's)
        self._items: OrderedDict[int, Any] = OrderedDict()
        self._lock = threading.Lock()
        self._loading: dict[int, threading.Lock] = {}  # one load per id at a time
        self._pool: ThreadPoolExecutor | None = None  # started by the first render
        self._admitted = 0  # renders handed to the pool and not finished: running or waiting
        self._seconds: float | None = None  # a running mean of a render's time, for Retry-After

    # -- the models ------------------------------------------------------------------------

    def get(self, nerf_id: int, files: dict[str, str]) -> Any:
        from csa_core.device import resolve_device
        from csa_core.nerf.checkpoint import load_checkpoint

        (_, sha), *rest = files.items()
        if rest:
            raise ValueError(f"NeRF {nerf_id}: expected one checkpoint file, found {len(files)}")
        with self._lock:
            if nerf_id in self._items:
                self._items.move_to_end(nerf_id)
                return self._items[nerf_id]
            loading = self._loading.setdefault(nerf_id, threading.Lock())
        with loading:
            with self._lock:  # loaded by the render this one waited for
                if nerf_id in self._items:
                    self._items.move_to_end(nerf_id)
                    return self._items[nerf_id]
            try:
                nerf = load_checkpoint(
                    self.store.open_verified(sha), device=resolve_device(self.device)
                )
                with self._lock:
                    self._items[nerf_id] = nerf
                    while len(self._items) > self.size:
                        self._items.popitem(last=False)
            finally:
                with self._lock:
                    self._loading.pop(nerf_id, None)
        return nerf

    def cached_ids(self) -> list[int]:
        """The ids of the models kept, least recently used first."""
        with self._lock:
            return list(self._items)

    # -- rendering -------------------------------------------------------------------------

    def render_view(
        self, nerf_id: int, files: dict[str, str], pose: np.ndarray, intrinsics: Intrinsics
    ) -> dict[str, np.ndarray]:
        """``color`` (H, W, 3) uint8 RGB, ``depth`` (H, W) metres, ``labels`` (H, W) uint8 NYU40
        ids, rendered in the calling thread: call it inside a render's turn (:meth:`run`,
        :meth:`call`)."""
        nerf = self.get(nerf_id, files)
        with _COMPILED_LOCK if _compiled(nerf) else nullcontext():
            view = self._draw(nerf, pose, intrinsics)
        return {"color": view.color, "depth": view.depth, "labels": view.labels}

    def _draw(self, nerf: Any, pose: np.ndarray, intrinsics: Intrinsics) -> Any:
        from csa_core.nerf.render import render_image

        return render_image(nerf, pose, intrinsics, semantics=True)

    def render(
        self, nerf_id: int, files: dict[str, str], pose: np.ndarray, intrinsics: Intrinsics
    ) -> dict[str, np.ndarray]:
        """:meth:`render_view` in its turn, the calling thread waiting (see :meth:`call`)."""
        return self.call(partial(self.render_view, nerf_id, files, pose, intrinsics))

    def call(self, fn: Callable[[], T]) -> T:
        """``fn()`` (a render: :meth:`render_view` and what goes with it) on a render thread,
        the calling thread waiting; :class:`RenderBusy` when it waited its turn longer than
        ``queue_seconds``."""
        future, wait = self._submit(fn)
        try:
            return future.result(timeout=wait)
        except TimeoutError:
            if future.cancel():  # still waiting for a thread: it never runs
                raise self._busy() from None
            return future.result()  # it started (or ended) in time

    async def run(self, fn: Callable[[], T]) -> T:
        """:meth:`call`, waiting in the event loop instead of a thread. A request cancelled while
        it waits takes its render out of the queue (one already running finishes unread)."""
        future, wait = self._submit(fn)
        waiter = asyncio.wrap_future(future)
        try:
            if wait is not None:
                done, _ = await asyncio.wait({waiter}, timeout=wait)
                if not done and future.cancel():
                    raise self._busy()
            return await waiter
        except asyncio.CancelledError:
            future.cancel()
            raise

    def _submit(self, fn: Callable[[], T]) -> tuple[Future[T], float | None]:
        """The render handed to the pool, and how long to wait for its turn (``None``: a thread
        is free for it, no limit)."""
        with self._lock:
            if self._pool is None:
                self._pool = ThreadPoolExecutor(
                    self.concurrency,
                    thread_name_prefix="render",
                    initializer=_render_thread,
                    initargs=(self.threads,),
                )
            free = self._admitted < self.concurrency  # the pool runs in order: this one starts now
            future = self._pool.submit(self._timed, fn)
            self._admitted += 1
        future.add_done_callback(self._finished)
        return future, None if free else self.queue_seconds

    def _timed(self, fn: Callable[[], T]) -> T:
        t0 = time.perf_counter()
        try:
            return fn()
        finally:
            seconds = time.perf_counter() - t0
            with self._lock:
                self._seconds = (
                    seconds if self._seconds is None else 0.8 * self._seconds + 0.2 * seconds
                )

    def _finished(self, _: Future) -> None:
        """A render ended, failed or was taken out of the queue."""
        with self._lock:
            self._admitted -= 1

    def _busy(self) -> RenderBusy:
        """The refusal of a render that waited too long; ``Retry-After``: about the time for
        the renders still waiting, and one more, to get their turn."""
        with self._lock:
            waiting = max(0, self._admitted - self.concurrency)
            seconds = self._seconds if self._seconds is not None else max(1.0, self.queue_seconds)
        retry = max(1, math.ceil(seconds * (1 + waiting / self.concurrency)))
        return RenderBusy(self.concurrency, self.queue_seconds, min(retry, 3600))

    def in_flight(self) -> int:
        """Renders running or waiting for their turn."""
        with self._lock:
            return self._admitted

    def close(self) -> None:
        """Drop the renders still waiting; those running finish in their threads."""
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)
