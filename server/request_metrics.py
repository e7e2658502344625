"""HTTP request counters and latencies, kept in memory for the Prometheus endpoint."""

from __future__ import annotations

import re
import threading
import time
from collections import defaultdict
from collections.abc import Callable

from starlette.routing import compile_path
from starlette.types import ASGIApp, Message, Receive, Scope, Send

# Latency histogram buckets (seconds), Prometheus' defaults.
BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)

# The methods counted by name; any other (HTTP lets a client send any token as a method, and
# this runs before authentication) is counted as OTHER, so that no client can add series.
METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})
OTHER_METHOD = "OTHER"


class RequestStats:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.count: dict[tuple[str, str, str], int] = defaultdict(int)
        self.latency_sum: dict[tuple[str, str], float] = defaultdict(float)
        self.latency_count: dict[tuple[str, str], int] = defaultdict(int)
        self.latency_buckets: dict[tuple[str, str], list[int]] = defaultdict(
            lambda: [0] * len(BUCKETS)
        )
        self.started = time.time()

    def observe(self, method: str, route: str, status: int, seconds: float) -> None:
        with self._lock:
            self.count[(method, route, str(status))] += 1
            key = (method, route)
            self.latency_sum[key] += seconds
            self.latency_count[key] += 1
            buckets = self.latency_buckets[key]
            for i, bound in enumerate(BUCKETS):
                if seconds <= bound:
                    buckets[i] += 1

    def snapshot(self):
        with self._lock:
            return (
                dict(self.count),
                dict(self.latency_sum),
                dict(self.latency_count),
                {k: list(v) for k, v in self.latency_buckets.items()},
            )


class RouteTemplates:
    """Maps a request path to its route template (``/api/v1/jobs/{job_id}``), so metrics
    have one series per route rather than one per id."""

    def __init__(self, paths: Callable[[], list[str]]):
        self._paths = paths
        self._compiled: list[tuple[re.Pattern[str], str]] | None = None

    def __call__(self, path: str) -> str:
        if self._compiled is None:
            self._compiled = [(compile_path(p)[0], p) for p in self._paths()]
        for regex, template in self._compiled:
            if regex.match(path):
                return template
        return "unmatched"


class RequestMetricsMiddleware:
    """Counts every HTTP request by method, route template and status."""

    def __init__(self, app: ASGIApp, stats: RequestStats, templates: RouteTemplates):
        self.app = app
        self.stats = stats
        self.templates = templates

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = 500

        async def send_wrapper(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            method = scope["method"] if scope["method"] in METHODS else OTHER_METHOD
            self.stats.observe(
                method, self.templates(scope["path"]), status, time.perf_counter() - start
            )
