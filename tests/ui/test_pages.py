"""What the dashboard's pages say, read as HTML over plain HTTP against a real server with its
embedded worker (no browser; tests/ui/test_dashboard.py drives the same pages in Chromium):
failed jobs, the frame strip, the class legend, the memory bank's size ratio, the continual
plot's axis, the "Try it" results before first use."""

from __future__ import annotations

import html
import importlib
import re
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest

from server import capabilities
from server.jobs.context import JobContext
from server.jobs.kinds import KINDS
from tests.server.conftest import (
    SCENE_SIZE,
    LiveServer,
    ParamsInputs,
    job_kind,
    start_server,
    test_settings,
)
from tests.ui.test_session import signed_in

pytestmark = pytest.mark.skipif(
    not capabilities.available("nerf"), reason="needs csa_core.nerf for a real fit"
)

W, H = SCENE_SIZE
TINY_NERF = {"steps": 60, "rays_per_step": 256, "occupancy_resolution": 32, "log2_table_size": 12}
# What a user met: an exception whose message is two long paths.
LONG_ERROR = "[Errno 17] " + " and ".join(
    f"/srv/csa/work/job-7-{'ab' * 20}/scenes/s1/office_0_0/color/{i}.png" for i in range(2)
)


def compute_fails(inputs: ParamsInputs, workdir: Path, ctx: JobContext) -> None:
    """A test job that fails the way a job meets an unexpected error: an exception with a long
    message, whose traceback the executor writes to the job's log."""
    ctx.progress(0.1, "about to fail", force=True)
    raise FileExistsError(LONG_ERROR)


@dataclass
class Site:
    live: LiveServer
    http: httpx.Client
    room: Path
    scene_id: int
    failed_job: int


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Iterator[Site]:
    from csa_core.data.synth import synthesize

    data = tmp_path_factory.mktemp("ui-pages")
    (room,) = synthesize(
        data / "scenes", scenes=1, frames=8, size=SCENE_SIZE, family="office", seed=5
    )
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(KINDS, "fails", job_kind("fails", compute_fails))
        live = start_server(test_settings(data / "service"))
        try:
            with live.client() as c:
                deadline = time.monotonic() + 10
                while c.health().workers_alive < 1 and time.monotonic() < deadline:
                    time.sleep(0.05)
                scene, _ = c.upload_scene_folder(room)
                fit = c.wait_job(
                    c.create_job(
                        "fit_nerf", scene=room.name, labels="ground_truth", **TINY_NERF
                    ).id,
                    timeout=300,
                )
                assert fit.status == "succeeded", fit.error
                from server.db.session import session_scope
                from server.jobs import queue

                with session_scope(live.services.sessions) as s:
                    failed_id = queue.enqueue(s, "fails", {}, None).id
                failed = c.wait_job(failed_id, timeout=60, raise_on_failure=False)
                assert (
                    failed.status == "failed" and failed.error == f"FileExistsError: {LONG_ERROR}"
                )
            client, _ = signed_in(live)
            try:
                yield Site(live, client, room, scene.id, failed_id)
            finally:
                client.close()
        finally:
            live.stop()


def page(site: Site, path: str) -> str:
    r = site.http.get(path)
    assert r.status_code == 200, (path, r.status_code, r.text[:300])
    return r.text


def element(text: str, tag: str, **attrs: str) -> str:
    """The first ``<tag ...>...</tag>`` whose attributes include ``attrs`` (no nesting of the
    same tag inside it)."""
    want = "".join(
        f'(?=[^>]*\\b{re.escape(k.rstrip("_").replace("_", "-"))}="{re.escape(v)}")'
        for k, v in attrs.items()
    )
    m = re.search(f"<{tag}\\b{want}[^>]*>(.*?)</{tag}>", text, re.S)
    assert m is not None, f"no <{tag} {attrs}> in the page"
    return m.group(0)


def test_jobs_page_folds_a_failed_jobs_error_into_its_column(site: Site) -> None:
    row = element(page(site, "/ui/jobs"), "tr", data_job_id=str(site.failed_job))
    cell = element(row, "td", data_field="message")
    # One line, cut with an ellipsis by the stylesheet; the whole message once opened.
    summary = re.fullmatch(
        r'<td class="message" data-field="message"><details class="error-text">'
        r"<summary [^>]*>(.*)</summary></details></td>",
        cell,
        re.S,
    )
    assert summary is not None, cell
    assert html.unescape(summary.group(1)) == f"FileExistsError: {LONG_ERROR}"
    css = site.http.get("/ui/static/dashboard.css").text
    rule = re.search(r"details\.error-text summary \{([^}]*)\}", css)
    assert (
        rule is not None
        and "text-overflow: ellipsis" in rule.group(1)
        and "white-space: nowrap" in rule.group(1)
    )
    assert re.search(r"td\.message \{[^}]*overflow-wrap: anywhere", css)


def test_job_page_shows_the_error_and_folds_the_traceback(site: Site) -> None:
    text = page(site, f"/ui/jobs/{site.failed_job}")
    error = element(text, "details", id="job-error")
    assert (
        "hidden" not in error.split(">", 1)[0]
        and f"FileExistsError: {html.escape(LONG_ERROR)}" in error
    )
    log = text.split('<div class="log" id="job-log">', 1)[1].split("</section>", 1)[
        0
    ]  # nested divs
    tracebacks = re.findall(
        r'<details class="log-entry"><summary>([^<]*)'
        r'<span class="muted">\((\d+) more lines\)</span></summary>(.*?)</details>',
        log,
        re.S,
    )
    assert len(tracebacks) == 1
    head, more, body = tracebacks[0]
    assert (
        head.endswith("ERROR Traceback (most recent call last): ")
        and int(more) == body.count("\n") + 1 >= 3
    )
    assert "compute_fails" in body and "raise FileExistsError" in body  # the whole traceback
    outside = re.sub(r"<details class=\"log-entry\">.*?</details>", "", log, flags=re.S)
    assert (
        "File &#34;" not in outside
        and 'File "' not in outside
        and "raise FileExistsError" not in outside
    )


def test_scene_page_counts_the_frames_pages_them_and_shows_the_class_colours(
    site: Site, monkeypatch
) -> None:
    from csa_core.data.nyu40 import CLASS_NAMES, PALETTE

    router = importlib.import_module(
        "server.ui.router"
    )  # the module (server.ui exports its router)
    text = page(site, f"/ui/scenes/{site.scene_id}")
    assert element(text, "h2", id="frame-count") == '<h2 id="frame-count">All 8 frames</h2>'
    monkeypatch.setattr(router, "FRAMES_PER_PAGE", 3)
    first = page(site, f"/ui/scenes/{site.scene_id}")
    assert "Frames 1–3 of 8" in element(first, "h2", id="frame-count")
    strip = element(first, "nav", id="frame-strip")
    assert re.findall(r'data-frame="([^"]+)"', strip) == ["0", "1", "2"]
    pager = element(first, "nav", id="frame-pages")
    assert (
        re.findall(r'href="\?page=(\d+)"', pager) == ["1", "2"]
        and '<strong aria-current="page">1</strong>' in pager
    )
    last = page(site, f"/ui/scenes/{site.scene_id}?page=2")
    assert "Frames 7–8 of 8" in element(last, "h2", id="frame-count")
    assert re.findall(r'data-frame="([^"]+)"', element(last, "nav", id="frame-strip")) == ["6", "7"]
    legend = element(first, "section", id="class-legend")
    items = re.findall(
        r'<li data-class-id="(\d+)"><span class="swatch" '
        r'style="background:#([0-9a-f]{6})"></span>\d+ ([^<]+)</li>',
        legend,
    )
    assert len(items) == len(CLASS_NAMES) == 41
    for class_id, color, name in items:
        assert name == CLASS_NAMES[int(class_id)]
        assert tuple(int(color[k : k + 2], 16) for k in (0, 2, 4)) == tuple(
            int(v) for v in PALETTE[int(class_id)]
        )


def test_memory_page_states_the_nerfs_size_against_the_images(site: Site) -> None:
    with site.live.client() as c:
        entry = c.scene_nerf(site.room.name)
    mapping = 6 * W * H * 4  # RGB + labels of the 6 training frames of 8, as Mapping keeps them
    text = page(site, "/ui/memory")
    row = element(text, "tr", data_scene=site.room.name)
    ratio = element(row, "td", data_field="ratio")
    assert re.sub(r"<[^>]+>", "", ratio) == f"{entry.size_bytes / mapping:.3g}×"
    assert f"{entry.size_bytes / mapping:.3g}×" in element(text, "strong", id="memory-ratio")
    assert (
        entry.size_bytes > mapping
    )  # a tiny room: here the NeRF is the larger, and the page says so
    assert "compact" not in text.lower()


def test_continual_plot_spans_the_whole_miou_range() -> None:
    """A 0.12-point change drawn on 0-100%: a flat line, not one across the whole axes."""
    from server.schemas.continual import ContinualMetricsOut, StepOut
    from server.ui.page_data import miou_per_step_plot, miou_per_step_png

    metrics = ContinualMetricsOut(
        lineage="base",
        root_model_id=1,
        split="val",
        steps=[StepOut(step=0, model_id=2, model="base-step1", scene_id=1, scene="office")],
        R=[[0.0796]],
        b=[0.0784],
        acc=0.0796,
        a=0.0796,
        fwt=None,
        bwt=None,
        missing=[],
    )
    assert miou_per_step_plot(metrics).ylim == (0.0, 100.0)
    img = cv2.imdecode(np.frombuffer(miou_per_step_png(metrics), np.uint8), cv2.IMREAD_COLOR)
    line = np.all(np.abs(img.astype(int) - (180, 119, 31)) <= 40, axis=2)  # matplotlib's C0, BGR
    rows = np.flatnonzero(line.any(axis=1))
    runs = np.split(rows, np.flatnonzero(np.diff(rows) > 1) + 1)
    # The data's line (and the legend's sample): short runs of rows; scaled to the data, the
    # line ran from the bottom of the axes to the top (over 200 rows).
    assert rows.size and max(len(r) for r in runs) < 15
    assert rows.max() > 0.7 * img.shape[0]  # near the bottom: 8% of the range


def test_try_page_shows_no_result_before_the_first_one(site: Site) -> None:
    text = page(site, "/ui/try")
    assert "hidden" in element(text, "div", id="render-result").split(">", 1)[0]
    css = site.http.get("/ui/static/dashboard.css").text
    # The stylesheet lays results out with display: flex, which would override the attribute.
    assert re.search(r"\[hidden\] \{ display: none !important; \}", css)
