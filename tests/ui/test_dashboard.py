"""The dashboard in a real browser: headless Chromium against a real uvicorn server with its
embedded worker, on tiny procedural rooms (8 frames of 40x30).

One browser session for the module, signed in once; the tests run in order and build on
each other like a person would: upload a scene from the page, look at its frames, start an
adaptation step and watch it finish, then find the new version, the R matrix and the memory
bank, and try the model on an uploaded image. What pages show is checked against the REST
API's numbers. Every page is written as a screenshot (see tests/ui/conftest.py).
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

from client import CSAClient
from csa_core.data.label_images import colorize
from server import capabilities
from tests.server.conftest import API_KEY, SCENE_SIZE, LiveServer, start_server, test_settings
from tests.ui.conftest import scene_archive

pytestmark = pytest.mark.skipif(
    not all(capabilities.available(c) for c in ("seg", "nerf", "adapt")),
    reason="the dashboard flow needs csa_core.seg, csa_core.nerf and csa_core.adapt",
)

W, H = SCENE_SIZE
# A NeRF fit small enough for a test (the service tests use the same).
TINY_NERF = {"steps": 60, "rays_per_step": 256, "occupancy_resolution": 32, "log2_table_size": 12}


def decode(png: bytes) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img is not None
    return img


def size_text(n: int) -> str:
    """Bytes as the pages write them."""
    return f"{n / 1e6:.2f} MB" if n >= 1e6 else f"{n / 1e3:.2f} kB" if n >= 1e3 else f"{n} B"


@dataclass
class Dashboard:
    live: LiveServer
    api: CSAClient
    page: object  # playwright Page, signed in
    shots: Path
    pretrain_scene: Path
    target_scene: Path
    archive: Path

    def goto(self, path: str) -> None:
        self.page.goto(self.live.url + path)
        self.page.wait_for_selector("body[data-ready]")

    def shot(self, name: str) -> Path:
        path = self.shots / f"{name}.png"
        self.page.screenshot(path=str(path), full_page=True)
        return path

    def image_loaded(self, selector: str, timeout: float = 60.0) -> tuple[int, int]:
        """(width, height) of an image once the browser has decoded it."""
        self.page.wait_for_function(
            "sel => { const i = document.querySelector(sel); return i && i.complete && "
            "i.naturalWidth > 0; }",
            arg=selector,
            timeout=timeout * 1000,
        )
        return tuple(self.page.eval_on_selector(selector, "i => [i.naturalWidth, i.naturalHeight]"))

    def wait_text(self, selector: str, text: str, timeout: float = 60.0) -> None:
        """Until the element's text contains ``text`` (a function, not a string to evaluate:
        the pages' Content-Security-Policy forbids eval)."""
        self.page.wait_for_function(
            "([sel, text]) => (document.querySelector(sel)?.textContent || '').includes(text)",
            arg=[selector, text],
            timeout=timeout * 1000,
        )

    def wait_job_status(self, status: str, timeout: float = 120.0) -> None:
        self.page.wait_for_function(
            "s => document.getElementById('job').dataset.status === s",
            arg=status,
            timeout=timeout * 1000,
        )

    def fetch_png(self, url: str) -> bytes:
        """A picture the page shows, fetched with the page's own session cookie."""
        response = self.page.request.get(self.live.url + url)
        assert response.status == 200, (url, response.status, response.text()[:300])
        return response.body()


@pytest.fixture(scope="module")
def dash(tmp_path_factory, browser, screenshots) -> Iterator[Dashboard]:
    from csa_core.data.synth import synthesize

    data = tmp_path_factory.mktemp("ui")
    (pre,) = synthesize(
        data / "scenes", scenes=1, frames=8, size=SCENE_SIZE, family="apartment", seed=1
    )
    (target,) = synthesize(
        data / "scenes", scenes=1, frames=8, size=SCENE_SIZE, family="office", seed=2
    )
    archive = scene_archive(target, data / f"{target.name}.tar.gz")
    live = start_server(test_settings(data / "service"))
    context = browser.new_context(viewport={"width": 1280, "height": 800})
    try:
        with live.client() as api:
            deadline = time.monotonic() + 10
            while api.health().workers_alive < 1 and time.monotonic() < deadline:
                time.sleep(0.05)
            api.upload_scene_folder(pre)
            job = api.pretrain([pre.name], epochs=1, batch_size=4, name="base")
            assert api.wait_job(job.id, timeout=300).status == "succeeded"
            yield Dashboard(live, api, context.new_page(), screenshots, pre, target, archive)
    finally:
        context.close()
        live.stop()


def test_a_missing_or_wrong_key_shows_the_sign_in_page_and_no_data(
    dash: Dashboard, browser
) -> None:
    context = browser.new_context(viewport={"width": 1280, "height": 800})
    try:
        page = context.new_page()
        for path in ("/ui/scenes", "/ui/models", f"/ui/scenes/{dash.pretrain_scene.name}"):
            page.goto(dash.live.url + path)
            assert "/ui/login?next=" in page.url
            assert page.locator("#sign-in").is_visible() and page.locator("table, nav").count() == 0
            assert dash.pretrain_scene.name not in page.inner_text("body")
        page.fill("#api-key", "definitely-not-the-key")
        page.click("#sign-in-button")
        page.wait_for_selector("#sign-in-error")
        assert "not valid" in page.inner_text("#sign-in-error")
        assert "/ui/login" in page.url and dash.pretrain_scene.name not in page.inner_text("body")
        assert context.cookies() == []
        page.screenshot(path=str(dash.shots / "sign-in-refused.png"), full_page=True)
    finally:
        context.close()


def test_sign_in_lands_on_the_scenes(dash: Dashboard) -> None:
    page = dash.page
    page.goto(dash.live.url + "/ui/scenes")
    assert "/ui/login" in page.url
    dash.shot("sign-in")
    page.fill("#api-key", API_KEY)
    page.click("#sign-in-button")
    page.wait_for_url("**/ui/scenes")
    row = page.locator(f'#scenes tr[data-scene="{dash.pretrain_scene.name}"]')
    assert row.locator("td").nth(1).inner_text() == "8"
    (cookie,) = page.context.cookies()
    assert cookie["httpOnly"] and cookie["sameSite"] == "Strict" and API_KEY not in cookie["value"]


def test_upload_a_scene_archive_from_the_page(dash: Dashboard) -> None:
    page = dash.page
    dash.goto("/ui/work")
    page.fill("#upload-scene", dash.target_scene.name)
    page.set_input_files("#upload-file", str(dash.archive))
    page.click("#upload-button")
    page.wait_for_selector("#upload-scene-link")
    assert "8 frames added" in page.inner_text("#upload-result")
    scene = dash.api.scene(dash.target_scene.name)
    assert scene.num_frames == 8 and scene.num_labelled_frames == 8
    dash.shot("start-work")


def test_scenes_list_shows_frames_labels_and_depth_coverage(dash: Dashboard) -> None:
    page = dash.page
    dash.goto("/ui/scenes")
    depth = [
        cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        for p in sorted((dash.target_scene / "depth").glob("*.png"))
    ]
    coverage = sum(int(np.count_nonzero(d)) for d in depth) / sum(d.size for d in depth)
    cells = page.locator(f'#scenes tr[data-scene="{dash.target_scene.name}"] td').all_inner_texts()
    assert cells[1:4] == ["8", "8", f"{100 * coverage:.1f}%"]
    assert cells[4] == f"{W}×{H}" and cells[5] == "none"
    dash.shot("scenes")


def test_scene_page_shows_the_frames_and_the_networks_labels(dash: Dashboard) -> None:
    page = dash.page
    scene = dash.api.scene(dash.target_scene.name)
    dash.goto(f"/ui/scenes/{scene.id}")
    assert page.locator("#frame-strip .thumb").count() == 8
    assert page.inner_text("#frame-count") == "All 8 frames"
    # Every thumbnail of the page is in view (the strip wraps instead of scrolling sideways).
    assert page.eval_on_selector("#frame-strip", "s => s.scrollWidth <= s.clientWidth")
    assert (
        page.locator("#class-legend li").count() == 41
        and page.locator("#class-legend").is_visible()
    )
    page.click('#frame-strip .thumb[data-frame="3"]')
    page.wait_for_selector('#frame-panels[data-frame="3"]')
    dash.page.wait_for_selector("body[data-ready]")
    for panel in ("prediction", "overlay", "truth"):
        assert dash.image_loaded(f'img[data-panel="{panel}"]') == (W, H)
    assert "no NeRF of this scene yet" in page.inner_text("#frame-panels")
    # The panel is the REST API's prediction of the same image, in the NYU40 colours.
    shown = decode(dash.fetch_png(f"/ui/img/scenes/{scene.id}/frames/3/prediction.png"))
    rest = decode(dash.api.predict(dash.target_scene / "color" / "3.png", format="color").png)
    np.testing.assert_array_equal(shown, rest)
    truth = decode(dash.fetch_png(f"/ui/img/scenes/{scene.id}/frames/3/truth.png"))
    gt = cv2.imread(str(dash.target_scene / "label-nyu40" / "3.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(truth[:, :, ::-1], colorize(gt))
    dash.shot("scene")


def test_fit_a_nerf_from_the_page(dash: Dashboard) -> None:
    page = dash.page
    scene = dash.api.scene(dash.target_scene.name)
    dash.goto("/ui/work")
    page.select_option("#fit-scene", str(scene.id))
    page.fill("#fit-steps", str(TINY_NERF["steps"]))
    page.click("#fit-nerf summary")
    page.fill("#fit-rays", str(TINY_NERF["rays_per_step"]))
    page.fill("#fit-table", str(TINY_NERF["log2_table_size"]))
    page.fill("#fit-occupancy", str(TINY_NERF["occupancy_resolution"]))
    page.click("#fit-button")
    page.wait_for_url("**/ui/jobs/*")
    page.wait_for_selector("body[data-ready]")
    dash.wait_job_status("succeeded", timeout=300)
    job = dash.api.job(int(page.get_attribute("#job", "data-job-id")))
    assert job.kind == "fit_nerf" and job.status == "succeeded"
    assert job.params["steps"] == TINY_NERF["steps"] and job.params["labels"] == "predictions"
    assert job.params["rays_per_step"] == TINY_NERF["rays_per_step"]
    assert (
        dash.api.scene(scene.id).has_nerf
        and job.result["nerf_id"] == dash.api.scene_nerf(scene.id).id
    )


def test_start_an_adaptation_step_and_watch_its_progress_to_the_end(dash: Dashboard) -> None:
    page = dash.page
    scene = dash.api.scene(dash.target_scene.name)
    dash.goto("/ui/work")
    page.select_option("#adapt-scene", str(scene.id))
    page.select_option("#adapt-preset", "tiny")
    page.click("#adapt-button")
    page.wait_for_url("**/ui/jobs/*")
    page.wait_for_selector("body[data-ready]")
    page.evaluate("window.stillThisPage = true")  # progress must arrive without a reload
    assert page.get_attribute("#job", "data-status") in ("queued", "running")
    seen: list[float] = []
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
        status = page.get_attribute("#job", "data-status")
        value = page.eval_on_selector("#job-progress", "p => p.value")
        if not seen or value != seen[-1]:
            seen.append(value)
        if status in ("succeeded", "failed", "cancelled"):
            break
        page.wait_for_timeout(100)
    job_id = int(page.get_attribute("#job", "data-job-id"))
    job = dash.api.job(job_id)
    assert job.status == "succeeded", "\n".join(line.message for line in dash.api.job_log(job_id))[
        -4000:
    ]
    dash.wait_text("#job-percent", "100%")
    assert page.eval_on_selector("#job-progress", "p => p.value") == 1.0 and seen[-1] == 1.0
    assert seen[0] < 1.0 and seen == sorted(seen)  # the bar moved, live, up to the end
    assert page.evaluate("window.stillThisPage") is True
    assert page.inner_text("#job-status") == "succeeded"
    dash.wait_text("#job-log", "succeeded")
    assert page.locator("#job-result-link").is_visible() and page.locator("#job-cancel").is_hidden()
    dash.shot("job")


def test_jobs_list(dash: Dashboard) -> None:
    page = dash.page
    dash.goto("/ui/jobs")
    adapt = dash.api.jobs(kind="adapt")[0]
    row = page.locator(f'#jobs tr[data-job-id="{adapt.id}"]')
    assert row.get_attribute("data-status") == "succeeded"
    assert row.locator('[data-field="percent"]').inner_text() == "100%"
    dash.shot("jobs")


def test_models_page_shows_the_new_version_in_its_lineage(dash: Dashboard) -> None:
    page = dash.page
    base, step = dash.api.model("base"), dash.api.model("base-step1")
    assert step.parent_id == base.id and step.is_current
    dash.goto("/ui/models")
    child = page.locator(f"li#model-{base.id} > ul > li#model-{step.id}")
    assert child.count() == 1 and child.locator("[data-current]").count() == 1
    cells = page.locator('table.evals tr[data-model="base-step1"] td').all_inner_texts()
    assert f"{100 * step.evaluations[f'{dash.target_scene.name}/val']:.1f}%" in cells
    dash.shot("models")
    # Set current and back, from the page.
    page.click(f'[data-set-current="{base.id}"]')
    page.wait_for_selector(f"li#model-{base.id} > .model [data-current]")
    assert dash.api.model("current").id == base.id
    page.click(f'[data-set-current="{step.id}"]')
    page.wait_for_selector(f"li#model-{step.id} > .model [data-current]")
    assert dash.api.model("current").id == step.id
    download = page.request.get(f"{dash.live.url}/ui/api/v1/models/{step.id}/download")
    assert download.status == 200 and download.headers["x-checksum-sha256"] == step.sha256


def test_continual_page_shows_the_r_matrix_and_scores(dash: Dashboard) -> None:
    page = dash.page
    m = dash.api.continual_metrics(lineage="base")
    assert len(m.steps) == 1 and m.R[0][0] is not None and m.b[0] is not None
    dash.goto("/ui/continual?lineage=base")
    assert page.locator('#r-matrix tr[data-row="0"] td').all_inner_texts() == [
        f"{100 * m.R[0][0]:.1f}%"
    ]
    assert page.locator('#r-matrix tr[data-row="b"] td').all_inner_texts() == [
        f"{100 * m.b[0]:.1f}%"
    ]
    assert page.inner_text('[data-score="acc"]') == f"{100 * m.acc:.1f}%"
    assert (
        page.inner_text('[data-score="fwt"]') == "–"
        and page.inner_text('[data-score="bwt"]') == "–"
    )
    assert page.get_attribute('#r-matrix tr[data-row="0"] td', "style").startswith("background:#")
    width, height = dash.image_loaded("#miou-plot")
    assert width > 300 and height > 200
    dash.shot("continual")


def test_memory_bank_page_compares_with_mapping_and_cotta(dash: Dashboard, tmp_path: Path) -> None:
    from csa_core.adapt.baselines.cotta import module_bytes
    from csa_core.seg import load_checkpoint

    page = dash.page
    entry = dash.api.scene_nerf(dash.target_scene.name)
    dash.goto("/ui/memory")
    cells = page.locator(f'#memory tr[data-scene="{dash.target_scene.name}"] td').all_inner_texts()
    assert cells[1] == size_text(entry.size_bytes)
    assert cells[5] == "8 (6)"  # 80% of 8 frames train
    assert cells[6] == size_text(6 * W * H * 4)  # RGB + label bytes of 6 training frames
    assert cells[7] == f"{entry.size_bytes / (6 * W * H * 4):.3g}×"  # the ratio, not a word
    path = dash.api.download_model("current", tmp_path / "current.safetensors")
    net, _ = load_checkpoint(path, device="cpu")
    footprint = {
        m: page.locator(f'#footprint tr[data-method="{m}"] td.num').inner_text()
        for m in ("csa", "mapping", "cotta")
    }
    assert footprint == {
        "csa": size_text(entry.size_bytes),
        "mapping": size_text(6 * W * H * 4),
        "cotta": size_text(2 * module_bytes(net)),
    }
    dash.shot("memory")


def test_scene_page_shows_the_nerf_pseudo_label_after_the_step(dash: Dashboard) -> None:
    page = dash.page
    scene = dash.api.scene(dash.target_scene.name)
    dash.goto(f"/ui/scenes/{scene.id}?frame=2")
    assert dash.image_loaded('img[data-panel="pseudo"]') == (W, H)
    assert "pseudo-label" in page.inner_text("#frame-panels")
    shown = decode(dash.fetch_png(f"/ui/img/scenes/{scene.id}/frames/2/pseudo.png"))
    pose = np.loadtxt(dash.target_scene / "pose" / "2.txt")
    rest = decode(
        dash.api.render(scene.name, pose.tolist(), channels=["labels_color"]).images["labels_color"]
    )
    np.testing.assert_array_equal(shown, rest)
    dash.shot("scene-after-step")


def test_try_it_labels_an_uploaded_image_and_renders_a_training_pose(dash: Dashboard) -> None:
    page = dash.page
    image = dash.target_scene / "color" / "5.png"
    dash.goto("/ui/try")
    # Before the first use: no empty pictures and no empty legend.
    for result in (
        "#predict-result",
        "#predict-overlay",
        "#predict-legend",
        "#render-result",
        "#render-color",
    ):
        assert page.locator(result).is_hidden(), result
    page.set_input_files("#predict-file", str(image))
    page.click("#predict-button")
    page.wait_for_selector("#predict-result:not([hidden])")
    assert dash.image_loaded("#predict-overlay") == (W, H)
    ids = decode(dash.api.predict(image).png)
    present, counts = np.unique(ids, return_counts=True)
    legend = [
        int(x)
        for x in page.eval_on_selector_all(
            "#predict-legend li", "items => items.map(i => i.dataset.classId)"
        )
    ]
    assert sorted(legend) == sorted(present.tolist())
    assert legend[0] == int(present[np.argmax(counts)])  # most frequent first
    assert "base-step1" in page.inner_text("#predict-model")
    page.select_option("#render-view", f"{dash.api.scene(dash.target_scene.name).id}/1")
    page.click("#render-button")
    page.wait_for_selector("#render-result:not([hidden])")
    assert dash.image_loaded("#render-color") == (W, H) and dash.image_loaded("#render-labels") == (
        W,
        H,
    )
    dash.shot("try-it")


def test_a_failed_job_shows_its_reason_and_can_be_retried(dash: Dashboard) -> None:
    page = dash.page
    api = dash.api
    api.ensure_scene("half-labelled")
    for name in ("0", "1"):
        f = dash.pretrain_scene
        api.upload_frame(
            "half-labelled",
            f / "color" / f"{name}.png",
            f / "depth" / f"{name}.png",
            f / "pose" / f"{name}.txt",
            intrinsics=f / "intrinsic" / "intrinsic_color.txt",
            name=name,
        )
    job = api.create_job("fit_nerf", scene="half-labelled", labels="ground_truth", steps=5)
    failed = api.wait_job(job.id, timeout=120, raise_on_failure=False)
    assert failed.status == "failed" and "no ground-truth labels" in failed.error
    dash.goto(f"/ui/jobs/{job.id}")
    assert "no ground-truth labels" in page.inner_text("#job-error")
    assert page.locator("#job-retry").is_visible() and page.locator("#job-cancel").is_hidden()
    # The error is one line until opened; the log's multi-line entries (tracebacks) are folded.
    # A computed line height of "normal" parses as NaN: then about 1.2 times the font size.
    one_line = (
        "s => { const st = getComputedStyle(s); "
        "const line = parseFloat(st.lineHeight) || 1.2 * parseFloat(st.fontSize); "
        "return s.getBoundingClientRect().height < 2 * line; }"
    )
    assert page.eval_on_selector("#job-error summary", one_line)
    page.click("#job-error summary")
    assert page.eval_on_selector("#job-error", "d => d.open")
    assert page.eval_on_selector_all("#job-log details", "ds => ds.every(d => !d.open)")
    dash.goto("/ui/jobs")
    cell = f'#jobs tr[data-job-id="{job.id}"] [data-field="message"]'
    assert "no ground-truth labels" in page.inner_text(cell)
    assert page.eval_on_selector(f"{cell} details.error-text summary", one_line)
    assert page.eval_on_selector(cell, "td => td.scrollWidth <= td.clientWidth + 1")
    dash.goto(f"/ui/jobs/{job.id}")
    dash.shot("job-failed")
    page.click("#job-retry")
    page.wait_for_url(
        lambda url: url.rstrip("/").split("/")[-1] not in ("", str(job.id)) and "/ui/jobs/" in url
    )
    page.wait_for_selector("body[data-ready]")
    assert f"job #{job.id}" in page.inner_text("#job")
    dash.wait_job_status("failed")
    assert "no ground-truth labels" in page.inner_text("#job-error")


def test_cancel_a_running_job_from_its_page(dash: Dashboard) -> None:
    page = dash.page
    job = dash.api.create_job(
        "fit_nerf", scene=dash.target_scene.name, labels="none", steps=100_000, rays_per_step=64
    )
    dash.goto(f"/ui/jobs/{job.id}")
    dash.wait_job_status("running")
    page.click("#job-cancel")
    dash.wait_job_status("cancelled")
    assert page.locator("#job-retry").is_visible()
    assert not math.isclose(dash.api.job(job.id).progress, 1.0)
    dash.goto("/ui/jobs")
    statuses = page.eval_on_selector_all(
        "#jobs tr[data-job-id]", "rows => rows.map(r => r.dataset.status)"
    )
    assert statuses == [j.status for j in dash.api.jobs()]
    assert {"succeeded", "failed", "cancelled"} <= set(statuses)
    dash.shot("jobs-all")


def test_signing_out_ends_the_session(dash: Dashboard) -> None:
    page = dash.page
    dash.goto("/ui/models")
    page.click("header .logout button")
    page.wait_for_url("**/ui/login")
    page.goto(dash.live.url + "/ui/models")
    assert (
        "/ui/login?next=" in page.url and "base-step1" not in page.content()
    )  # no data, not even hidden
