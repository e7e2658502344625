"""A soak test of the service: a real ``csa serve`` on loopback under mixed traffic (not a test).

It starts ``csa serve`` on 127.0.0.1 (a free port; nothing else is ever contacted) with a fresh
PostgreSQL database on the server at 127.0.0.1:5432 (trust authentication; a private server is
started when none answers, as the tests do: ``tests/pg.py``, which drops the database at the
end) or, with ``--sqlite``, SQLite in a temporary folder. The setup, with the settings' admin
key: a synthetic room of 160x120 frames uploaded as an archive, a tiny NeRF fit of it (ground
truth labels), an untrained segmentation network registered as the current model (predictions
cost what a trained one costs; their labels are not the point), and one key per client.

Then ``--clients`` clients (default 32) run for ``--minutes`` (default 10; ``--smoke``: about
20 s, 8 clients, smaller fits): even clients are **device** keys that create their own scene
and upload 160x120 frames to it, ask for predictions, list their scenes and frames; odd
clients are **operator** keys that render views of the fitted NeRF, ask for predictions, list
jobs, models, the memory bank and scenes, and queue a tiny NeRF fit at most every
``--job-interval`` seconds. Every client stops by itself after its time or
``--max-requests`` requests, whichever comes first.

It prints p50/p95/p99 latency per route (the route's template), the answers by status per
route, the server's RSS over time and its memory summary (``/proc/PID/status``: VmRSS when the
server is up, when the traffic starts and ends, VmHWM for the peak, and the growth over the
traffic's second half, past the warm-up), and exits non-zero when any answer was a 5xx or a
request failed without an answer (docs/operations.md "Soak"). A render refused 503
``render_busy`` (every render of the server busy for ``CSA_RENDER_QUEUE_SECONDS``) is load
shed, not a failure: it is counted apart, and its client waits the ``Retry-After`` it was given::

    python benchmarks/soak.py --smoke --sqlite          # ~1 minute with the setup
    python benchmarks/soak.py --minutes 2               # PostgreSQL, 32 clients
    python benchmarks/soak.py                           # 10 minutes
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import random
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter, defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(REPO))

HOST = "127.0.0.1"  # loopback only: the server listens here and every request goes here
API = "/api/v1"
FRAME_SIZE = (160, 120)
TINY_NERF = {"steps": 60, "rays_per_step": 256, "occupancy_resolution": 32, "log2_table_size": 12}
SMOKE_NERF = {"steps": 20, "rays_per_step": 128, "occupancy_resolution": 16, "log2_table_size": 10}
NO_ANSWER = 0  # the status recorded for a request that got no answer (timeout, reset)
# the code of a render refused while the server's renders are busy (server/nerf_cache.py)
SHED = "render_busy"


@dataclass
class Room:
    """The frames of a synthetic room, in memory: what the clients upload and ask about."""

    name: str
    folder: Path
    colors: list[bytes]
    depths: list[bytes]
    poses: list[str]
    intrinsics: str
    depth_intrinsics: str | None

    @classmethod
    def read(cls, folder: Path) -> Room:
        names = sorted((p.stem for p in (folder / "color").glob("*.png")), key=int)
        dintr = folder / "intrinsic" / "intrinsic_depth.txt"
        return cls(
            name=folder.name,
            folder=folder,
            colors=[(folder / "color" / f"{n}.png").read_bytes() for n in names],
            depths=[(folder / "depth" / f"{n}.png").read_bytes() for n in names],
            poses=[(folder / "pose" / f"{n}.txt").read_text() for n in names],
            intrinsics=(folder / "intrinsic" / "intrinsic_color.txt").read_text(),
            depth_intrinsics=dintr.read_text() if dintr.is_file() else None,
        )

    def pose_matrix(self, i: int) -> list[list[float]]:
        return [
            [float(v) for v in line.split()] for line in self.poses[i].split("\n") if line.strip()
        ]


@dataclass
class Record:
    """Every answer: route template -> latencies (s) and statuses."""

    latencies: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))
    statuses: dict[str, Counter] = field(default_factory=lambda: defaultdict(Counter))
    failures: Counter = field(default_factory=Counter)  # "route: ExceptionName" of unanswered ones
    shed: Counter = field(default_factory=Counter)  # route -> 503s that shed load (SHED)

    def add(self, route: str, seconds: float, status: int) -> None:
        self.latencies[route].append(seconds)
        self.statuses[route][status] += 1

    @property
    def server_errors(self) -> int:
        """5xx answers, but for the load shed (:data:`SHED`)."""
        errors = sum(n for c in self.statuses.values() for s, n in c.items() if s >= 500)
        return errors - sum(self.shed.values())

    @property
    def unanswered(self) -> int:
        return sum(c[NO_ANSWER] for c in self.statuses.values())


def free_port() -> int:
    with socket.socket() as s:
        s.bind((HOST, 0))
        return s.getsockname()[1]


def memory_mib(pid: int) -> dict[str, float] | None:
    """``rss`` (VmRSS: resident now) and ``hwm`` (VmHWM: the most resident since the process
    started) of ``pid`` in MiB, from Linux ``/proc``; None when it is gone (or not Linux)."""
    found = {}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            key, _, value = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                found[key] = int(value.split()[0]) / 1024  # kB
    except (OSError, ValueError, IndexError):
        return None
    if "VmRSS" not in found:
        return None
    return {"rss": found["VmRSS"], "hwm": found.get("VmHWM", found["VmRSS"])}


def rss_mib(pid: int) -> float | None:
    """The resident set of ``pid`` in MiB (Linux ``/proc``); None when it is gone."""
    memory = memory_mib(pid)
    return None if memory is None else memory["rss"]


def slope_per_minute(points: list[tuple[float, float]]) -> float | None:
    """The least-squares slope of (seconds, MiB) points, in MiB per minute; None under 3 points."""
    if len(points) < 3:
        return None
    n = len(points)
    mt = sum(t for t, _ in points) / n
    mv = sum(v for _, v in points) / n
    var = sum((t - mt) ** 2 for t, _ in points)
    if var <= 0:
        return None
    return 60 * sum((t - mt) * (v - mv) for t, v in points) / var


def memory_summary(
    up: dict[str, float] | None,
    traffic_start: dict[str, float] | None,
    end: dict[str, float] | None,
    rss: list[tuple[float, float]],
) -> dict[str, float | None]:
    """The server's memory over a soak, MiB: VmRSS when it was up (before the setup), when the
    traffic started and when it ended, the peak (VmHWM at the end, which catches peaks between
    samples too, or the highest sample where that is higher: Linux raises VmHWM lazily, so a
    short peak that the allocator gave back can stay below a sample of VmRSS), the growth over
    the traffic, and the slope over its second half (MiB/min; the first half holds the warm-up:
    the network, the NeRF and the allocator's pools)."""
    seconds = rss[-1][0] if rss else 0.0
    late = [(t, v) for t, v in rss if t >= seconds / 2]
    start_rss = traffic_start["rss"] if traffic_start else None
    end_rss = end["rss"] if end else None
    sampled_max = max((v for _, v in rss), default=None)
    peak = end["hwm"] if end else None
    if peak is not None and sampled_max is not None:
        peak = max(peak, sampled_max)
    return {
        "up_mib": up["rss"] if up else None,
        "traffic_start_mib": start_rss,
        "end_mib": end_rss,
        "peak_mib": peak,
        "sampled_max_mib": sampled_max,
        "growth_mib": None if start_rss is None or end_rss is None else end_rss - start_rss,
        "late_slope_mib_per_min": slope_per_minute(late),
    }


def percentile(values: list[float], q: float) -> float:
    """The ``q``-th percentile (0..100), nearest rank."""
    ordered = sorted(values)
    rank = max(1, math.ceil(q / 100 * len(ordered)))
    return ordered[rank - 1]


# -- the server ------------------------------------------------------------------------------


def start_server(
    data_dir: Path, database_url: str | None, admin_key: str, log: Path
) -> tuple[subprocess.Popen, str]:
    """``csa serve`` on 127.0.0.1 and a free port, in its own process; waits for /health."""
    port = free_port()
    env = dict(os.environ)
    env.update(
        CSA_API_KEYS=admin_key,
        CSA_DEVICE="cpu",
        CSA_TORCH_THREADS="1",
        CSA_WORKER_POLL_SECONDS="0.2",
        CSA_PUBLIC_DOCS="false",
    )
    csa = Path(sys.executable).with_name("csa")
    command = [str(csa)] if csa.is_file() else [sys.executable, "-m", "csa_core.cli.main"]
    command += [
        "serve",
        "--host",
        HOST,
        "--port",
        str(port),
        "--data-dir",
        str(data_dir),
        "--log-level",
        "warning",
    ]
    if database_url:
        command += ["--database-url", database_url]
    with open(log, "wb") as out:
        proc = subprocess.Popen(
            command, env=env, stdout=out, stderr=subprocess.STDOUT, cwd=data_dir
        )
    url = f"http://{HOST}:{port}"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(
                f"csa serve exited with {proc.returncode}: {log.read_text()[-2000:]}"
            )
        try:
            if httpx.get(f"{url}/health", timeout=2).status_code == 200:
                return proc, url
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    stop_server(proc)
    raise RuntimeError(f"csa serve did not answer /health within 120 s: {log.read_text()[-2000:]}")


def stop_server(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)  # uvicorn's graceful stop: the worker finishes its step
        try:
            proc.wait(timeout=90)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=30)


def cancel_jobs(url: str, admin_key: str) -> int:
    """Cancel the jobs the clients left queued or running, so that the server stops at once."""
    cancelled = 0
    with httpx.Client(base_url=url, headers={"X-API-Key": admin_key}, timeout=60) as admin:
        for status in ("queued", "running"):
            r = admin.get(f"{API}/jobs", params={"status": status, "limit": 1000})
            for job in r.json() if r.status_code == 200 else []:
                if admin.post(f"{API}/jobs/{job['id']}/cancel").status_code == 200:
                    cancelled += 1
    return cancelled


# -- setup -----------------------------------------------------------------------------------


def _check(r: httpx.Response, what: str) -> Any:
    if r.status_code >= 300:
        raise RuntimeError(f"setup: {what} answered {r.status_code}: {r.text[:500]}")
    return r.json() if r.content else None


def setup(
    url: str, admin_key: str, room: Room, clients: int, nerf: dict, work: Path, timeout_s: float
) -> dict[str, Any]:
    """The NeRF scene, the current model and one key per client; returns the keys and the job."""
    import tarfile

    from csa_core.seg.checkpoint import save_checkpoint
    from csa_core.seg.models import build_model

    with httpx.Client(base_url=url, headers={"X-API-Key": admin_key}, timeout=300) as admin:
        _check(admin.post(f"{API}/scenes", json={"name": room.name}), "create the NeRF scene")
        packed = work / "room.tar"
        with tarfile.open(packed, "w") as tf:
            for sub in ("color", "depth", "pose", "intrinsic", "label-nyu40"):
                for p in sorted((room.folder / sub).iterdir()):
                    tf.add(p, arcname=f"{sub}/{p.name}", recursive=False)
        with open(packed, "rb") as f:
            _check(
                admin.post(
                    f"{API}/scenes/{room.name}/archive",
                    files={"archive": ("room.tar", f, "application/x-tar")},
                ),
                "archive upload",
            )
        job = _check(
            admin.post(
                f"{API}/jobs",
                json={
                    "kind": "fit_nerf",
                    "params": {"scene": room.name, "labels": "ground_truth", **nerf},
                },
            ),
            "queue the NeRF fit",
        )
        ckpt = work / "untrained.safetensors"
        save_checkpoint(ckpt, build_model())
        with open(ckpt, "rb") as f:
            files = {"checkpoint": ("untrained.safetensors", f, "application/octet-stream")}
            _check(
                admin.post(
                    f"{API}/models",
                    files=files,
                    data={"name": "soak-untrained", "make_current": "true"},
                ),
                "register the model",
            )
        keys = {}
        for i in range(clients):
            scope = "device" if i % 2 == 0 else "operator"
            made = _check(
                admin.post(f"{API}/keys", json={"name": f"soak-{scope}-{i}", "scope": scope}),
                "make a key",
            )
            keys[i] = made["key"]
        deadline = time.monotonic() + timeout_s
        while True:
            state = _check(admin.get(f"{API}/jobs/{job['id']}"), "poll the NeRF fit")
            if state["status"] == "succeeded":
                break
            if state["status"] in ("failed", "cancelled") or time.monotonic() > deadline:
                raise RuntimeError(
                    f"setup: the NeRF fit is {state['status']}: {state.get('error')}"
                )
            time.sleep(0.5)
    return {"keys": keys, "fit_job": job["id"]}


# -- the clients -----------------------------------------------------------------------------


def _error_code(r: httpx.Response) -> str | None:
    try:
        return r.json()["error"]["code"]
    except (ValueError, KeyError, TypeError):
        return None


def _retry_after(r: httpx.Response) -> float:
    try:
        return max(0.0, float(r.headers.get("Retry-After", "1")))
    except ValueError:
        return 1.0


@dataclass
class Client:
    index: int
    key: str
    room: Room
    nerf: dict
    deadline: float
    max_requests: int
    job_interval: float
    record: Record
    rng: random.Random
    timeout: float = 120.0  # seconds of silence that end a request (recorded as no answer)
    sent: int = 0
    uploaded: int = 0
    last_job: float = -math.inf

    @property
    def device(self) -> bool:
        return self.index % 2 == 0

    @property
    def scene(self) -> str:
        return f"soak-scene-{self.index}"

    async def call(
        self, http: httpx.AsyncClient, route: str, method: str, path: str, **kw: Any
    ) -> httpx.Response | None:
        self.sent += 1
        t0 = time.perf_counter()
        try:
            r = await http.request(method, path, **kw)
        except httpx.HTTPError as e:
            self.record.add(route, time.perf_counter() - t0, NO_ANSWER)
            self.record.failures[f"{route}: {type(e).__name__}"] += 1
            return None
        self.record.add(route, time.perf_counter() - t0, r.status_code)
        if r.status_code == 503 and _error_code(r) == SHED:
            # Load shed: the server asks to come back later; a client waits that long.
            self.record.shed[route] += 1
            wait = _retry_after(r)
            await asyncio.sleep(min(wait, max(0.0, self.deadline - time.monotonic())))
        return r

    def frame_form(self, i: int) -> tuple[dict, dict]:
        room = self.room
        files = {
            "color": ("c.png", room.colors[i], "image/png"),
            "depth": ("d.png", room.depths[i], "image/png"),
            "pose": ("p.txt", room.poses[i].encode(), "text/plain"),
            "intrinsics": ("k.txt", room.intrinsics.encode(), "text/plain"),
        }
        if room.depth_intrinsics is not None:
            files["depth_intrinsics"] = ("kd.txt", room.depth_intrinsics.encode(), "text/plain")
        return files, {"name": str(self.uploaded)}

    async def device_step(self, http: httpx.AsyncClient) -> None:
        n = len(self.room.colors)
        pick = self.rng.random()
        if pick < 0.40:
            files, data = self.frame_form(self.uploaded % n)
            r = await self.call(
                http,
                "POST /scenes/{scene}/frames",
                "POST",
                f"{API}/scenes/{self.scene}/frames",
                files=files,
                data=data,
            )
            if r is not None and r.status_code in (200, 201):
                self.uploaded += 1
        elif pick < 0.65:
            await self.predict(http)
        elif pick < 0.75:
            await self.call(http, "GET /scenes", "GET", f"{API}/scenes")
        elif pick < 0.90:
            await self.call(
                http,
                "GET /scenes/{scene}/frames",
                "GET",
                f"{API}/scenes/{self.scene}/frames",
                params={"limit": 50},
            )
        else:
            await self.call(http, "GET /scenes/{scene}", "GET", f"{API}/scenes/{self.scene}")

    async def predict(self, http: httpx.AsyncClient) -> None:
        """One prediction of a random colour image of the room (both scopes' traffic)."""
        image = self.room.colors[self.rng.randrange(len(self.room.colors))]
        await self.call(
            http,
            "POST /predict",
            "POST",
            f"{API}/predict",
            files={"image": ("i.png", image, "image/png")},
        )

    async def operator_step(self, http: httpx.AsyncClient) -> None:
        n = len(self.room.colors)
        pick = self.rng.random()
        if pick < 0.05 and time.monotonic() - self.last_job >= self.job_interval:
            self.last_job = time.monotonic()
            body = {
                "kind": "fit_nerf",
                "params": {"scene": self.room.name, "labels": "ground_truth", **self.nerf},
            }
            await self.call(http, "POST /jobs", "POST", f"{API}/jobs", json=body)
        elif pick < 0.35:
            body = {
                "pose": self.room.pose_matrix(self.rng.randrange(n)),
                "channels": ["color", "labels"],
            }
            await self.call(
                http,
                "POST /scenes/{scene}/render",
                "POST",
                f"{API}/scenes/{self.room.name}/render",
                json=body,
            )
        elif pick < 0.55:
            await self.predict(http)
        elif pick < 0.70:
            await self.call(http, "GET /jobs", "GET", f"{API}/jobs", params={"limit": 20})
        elif pick < 0.80:
            await self.call(http, "GET /models", "GET", f"{API}/models")
        elif pick < 0.90:
            await self.call(http, "GET /memory", "GET", f"{API}/memory")
        else:
            await self.call(http, "GET /scenes", "GET", f"{API}/scenes", params={"limit": 50})

    async def run(self, url: str) -> None:
        headers = {"X-API-Key": self.key}
        # No request starts after the deadline; the last one ends within the timeout.
        async with httpx.AsyncClient(base_url=url, headers=headers, timeout=self.timeout) as http:
            if self.device:
                await self.call(
                    http, "POST /scenes", "POST", f"{API}/scenes", json={"name": self.scene}
                )
            while time.monotonic() < self.deadline and self.sent < self.max_requests:
                if self.device:
                    await self.device_step(http)
                else:
                    await self.operator_step(http)


async def run_clients(
    url: str,
    keys: dict[int, str],
    room: Room,
    args,
    nerf: dict,
    record: Record,
    pid: int,
    rss: list[tuple[float, float]],
) -> None:
    start = time.monotonic()
    deadline = start + args.minutes * 60
    clients = [
        Client(
            i,
            keys[i],
            room,
            nerf,
            deadline,
            args.max_requests,
            args.job_interval,
            record,
            random.Random(args.seed * 1000 + i),
            args.timeout,
        )
        for i in range(len(keys))
    ]

    async def sample_rss() -> None:
        while time.monotonic() < deadline:
            value = rss_mib(pid)
            if value is not None:
                rss.append((time.monotonic() - start, value))
            await asyncio.sleep(args.rss_every)

    sampler = asyncio.create_task(sample_rss())
    await asyncio.gather(*(c.run(url) for c in clients))
    sampler.cancel()
    value = rss_mib(pid)
    if value is not None:
        rss.append((time.monotonic() - start, value))


# -- report ----------------------------------------------------------------------------------


def report(
    record: Record,
    rss: list[tuple[float, float]],
    seconds: float,
    print_: Callable[[str], None] = print,
    memory: dict[str, float | None] | None = None,
) -> dict[str, Any]:
    routes = sorted(record.latencies)
    rows = []
    for route in routes:
        lat = record.latencies[route]
        rows.append(
            {
                "route": route,
                "requests": len(lat),
                "p50_ms": 1000 * percentile(lat, 50),
                "p95_ms": 1000 * percentile(lat, 95),
                "p99_ms": 1000 * percentile(lat, 99),
                "statuses": {str(s): n for s, n in sorted(record.statuses[route].items())},
            }
        )
    total = sum(r["requests"] for r in rows)
    print_(f"\n{total} requests in {seconds:.0f} s ({total / max(seconds, 1e-9):.1f}/s)")
    header = f"{'route':<32} {'n':>6} {'p50 ms':>8} {'p95 ms':>8} {'p99 ms':>8}  statuses"
    print_(header)
    print_("-" * len(header))
    for r in rows:
        statuses = " ".join(
            f"{s}:{n}" if s != str(NO_ANSWER) else f"none:{n}" for s, n in r["statuses"].items()
        )
        print_(
            f"{r['route']:<32} {r['requests']:>6} {r['p50_ms']:>8.0f} {r['p95_ms']:>8.0f} "
            f"{r['p99_ms']:>8.0f}  {statuses}"
        )
    by_status: Counter = Counter()
    for c in record.statuses.values():
        by_status.update(c)
    errors = {
        ("none" if s == NO_ANSWER else str(s)): n
        for s, n in sorted(by_status.items())
        if s >= 400 or s == NO_ANSWER
    }
    print_(f"errors by status: {errors or 'none'}")
    for what, n in record.failures.most_common():
        print_(f"  no answer: {what} x{n}")
    shed = sum(record.shed.values())
    if shed:
        routes_shed = ", ".join(f"{route} x{n}" for route, n in record.shed.most_common())
        print_(f"load shed (503 {SHED}, Retry-After honoured; not server errors): {routes_shed}")
    print_("server RSS (MiB) over time:")
    step = max(1, len(rss) // 20)
    for t, mib in rss[::step]:
        print_(f"  {t:7.0f} s  {mib:8.1f}")
    if rss:
        print_(f"  start {rss[0][1]:.1f}, end {rss[-1][1]:.1f}, max {max(m for _, m in rss):.1f}")
    if memory is not None:
        print_(memory_line(memory))
    return {
        "seconds": seconds,
        "requests": total,
        "routes": rows,
        "errors": errors,
        "server_errors": record.server_errors,
        "shed": dict(record.shed),
        "unanswered": record.unanswered,
        "rss_mib": rss,
        "memory": memory,
    }


def memory_line(memory: dict[str, float | None]) -> str:
    """The memory summary in one line (see :func:`memory_summary`)."""

    def mib(key: str, sign: str = "") -> str:
        value = memory.get(key)
        return "n/a" if value is None else f"{value:{sign},.1f}"

    return (
        f"server memory (MiB, /proc/PID/status): up {mib('up_mib')}, traffic start "
        f"{mib('traffic_start_mib')}, end {mib('end_mib')}, peak {mib('peak_mib')} (VmHWM); "
        f"growth over the traffic {mib('growth_mib', '+')}, over its second half "
        f"{mib('late_slope_mib_per_min', '+')} MiB/min"
    )


# -- main ------------------------------------------------------------------------------------


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "--clients", type=int, default=None, help="concurrent clients (default 32; --smoke: 8)"
    )
    p.add_argument(
        "--minutes", type=float, default=None, help="traffic time (default 10; --smoke: 1/3)"
    )
    p.add_argument(
        "--smoke",
        action="store_true",
        help="about 20 s of traffic, 8 clients, smaller fits (the test's mode)",
    )
    p.add_argument(
        "--sqlite", action="store_true", help="SQLite in the data folder instead of PostgreSQL"
    )
    p.add_argument("--max-requests", type=int, default=100_000, help="requests per client at most")
    p.add_argument(
        "--job-interval",
        type=float,
        default=120.0,
        help="seconds between one operator client's job submissions",
    )
    p.add_argument(
        "--frames",
        type=int,
        default=None,
        help="frames of the synthetic room (default 12; --smoke: 6)",
    )
    p.add_argument(
        "--rss-every",
        type=float,
        default=None,
        help="seconds between RSS samples (default 10; --smoke: 1)",
    )
    p.add_argument(
        "--timeout", type=float, default=120.0, help="seconds a request may take (then: no answer)"
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", type=Path, default=None, help="also write the results here")
    p.add_argument("--keep", action="store_true", help="keep the data folder (its path is printed)")
    args = p.parse_args(argv)
    args.clients = args.clients or (8 if args.smoke else 32)
    args.minutes = args.minutes if args.minutes is not None else (1 / 3 if args.smoke else 10.0)
    args.frames = args.frames or (6 if args.smoke else 12)
    args.rss_every = args.rss_every or (1.0 if args.smoke else 10.0)
    if min(args.clients, args.max_requests) < 1 or min(args.minutes, args.timeout) <= 0:
        p.error("--clients, --minutes, --max-requests and --timeout must be positive")
    if args.frames < 2:
        p.error(f"--frames: {args.frames} is too few (at least 2)")
    return args


def log_errors(log: Path, limit: int = 5) -> list[tuple[str, int]]:
    """The server log's distinct exceptions (a traceback's last line: ``module.Error: text``)
    and their counts, most frequent first, so that a soak with 5xx says what went wrong."""
    counts: Counter[str] = Counter()
    in_traceback = False
    try:
        lines = log.read_text(errors="replace").splitlines()
    except OSError:
        return []
    for line in lines:
        if line.startswith("Traceback (most recent call last)"):
            in_traceback = True
        elif in_traceback and line and not line[0].isspace():
            counts[line.strip()[:300]] += 1
            in_traceback = False
    return counts.most_common(limit)


def run_in_own_loop(coroutine) -> None:
    """``asyncio.run(coroutine)``, in a thread of its own when this thread already runs an event
    loop (a caller inside one, e.g. a test process where a browser driver left its loop running)."""
    try:
        asyncio.get_running_loop()
    except RuntimeError:
        asyncio.run(coroutine)
        return
    errors: list[BaseException] = []

    def target() -> None:
        try:
            asyncio.run(coroutine)
        except BaseException as e:  # noqa: BLE001 - re-raised in the caller's thread
            errors.append(e)

    thread = threading.Thread(target=target, name="soak-clients")
    thread.start()
    thread.join()
    if errors:
        raise errors[0]


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Run the soak; returns the results (``server_errors`` and ``unanswered`` decide the exit)."""
    args = parse_args(argv)
    from csa_core.data.synth import synthesize

    work = Path(tempfile.mkdtemp(prefix="csa-soak-"))
    postgres = None
    proc = None
    try:
        database_url = None
        if not args.sqlite:
            from tests.pg import PostgresUnavailable, open_postgres

            try:
                postgres = open_postgres()
            except PostgresUnavailable as e:
                raise SystemExit(f"soak: no PostgreSQL server ({e}); use --sqlite") from None
            database_url = postgres.create()
        (folder,) = synthesize(
            work / "rooms",
            scenes=1,
            frames=args.frames,
            size=FRAME_SIZE,
            family="office",
            seed=args.seed,
        )
        room = Room.read(folder)
        admin_key = secrets.token_urlsafe(32)
        nerf = SMOKE_NERF if args.smoke else TINY_NERF
        t0 = time.monotonic()
        (work / "service").mkdir()
        proc, url = start_server(work / "service", database_url, admin_key, work / "serve.log")
        up = memory_mib(proc.pid)
        print(
            f"csa serve at {url} (pid {proc.pid}, {'SQLite' if args.sqlite else 'PostgreSQL'}), "
            f"up in {time.monotonic() - t0:.1f} s"
        )
        t0 = time.monotonic()
        made = setup(url, admin_key, room, args.clients, nerf, work, timeout_s=600)
        print(
            f"setup: {args.clients} keys, model registered, NeRF fitted "
            f"({time.monotonic() - t0:.1f} s)"
        )
        print(f"traffic: {args.clients} clients for {args.minutes * 60:.0f} s ...", flush=True)
        record: Record = Record()
        rss: list[tuple[float, float]] = []
        t0 = time.monotonic()
        traffic_start = memory_mib(proc.pid)
        run_in_own_loop(run_clients(url, made["keys"], room, args, nerf, record, proc.pid, rss))
        memory = memory_summary(up, traffic_start, memory_mib(proc.pid), rss)
        results = report(record, rss, time.monotonic() - t0, memory=memory)
        errors = log_errors(work / "serve.log")
        if record.server_errors and errors:
            print("the server's log, its exceptions:")
            for line, n in errors:
                print(f"  {n} x {line}")
        alive = proc.poll() is None
        if alive:
            print(f"cancelled {cancel_jobs(url, admin_key)} jobs left by the clients")
        results.update(
            clients=args.clients,
            minutes=args.minutes,
            database="sqlite" if args.sqlite else "postgresql",
            server_alive=alive,
            log_errors=[{"exception": line, "count": n} for line, n in errors],
        )
        if not alive:
            print(
                f"the server died during the soak (exit {proc.returncode}); "
                f"its log: {work / 'serve.log'}"
            )
        if args.json is not None:
            args.json.write_text(json.dumps(results, indent=2))
        return results
    finally:
        if proc is not None:
            t0 = time.monotonic()
            stop_server(proc)
            print(f"server stopped in {time.monotonic() - t0:.1f} s")
        if postgres is not None:
            postgres.close()
        if args.keep:
            print(f"data kept in {work}")
        else:
            shutil.rmtree(work, ignore_errors=True)


def exit_code(results: dict[str, Any]) -> int:
    """Non-zero on any 5xx, any request without an answer, or a server that died."""
    return (
        1 if results["server_errors"] or results["unanswered"] or not results["server_alive"] else 0
    )


if __name__ == "__main__":
    sys.exit(exit_code(main()))
