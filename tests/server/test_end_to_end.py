"""The service end to end: a real uvicorn server on 127.0.0.1 with its embedded worker, a
temporary database (SQLite, then PostgreSQL) and artifact folder, driven through ``CSAClient``
and ``csa-client``.

Scenes are tiny procedural rooms (8 frames of 40x30); jobs use tiny settings so the whole
flow runs in well under a minute on a 2-core CPU.
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest

from client import CSAClient, NotAvailable
from client.cli import main as cli_main
from server import capabilities
from tests.server.conftest import (
    API_KEY,
    SCENE_SIZE,
    LiveServer,
    both_backends,
    database_url,
    start_server,
    test_settings,
)

pytestmark = both_backends

# A NeRF fit small enough for a test: few rays and steps, a small table and occupancy grid.
TINY_NERF = {"steps": 60, "rays_per_step": 256, "occupancy_resolution": 32, "log2_table_size": 12}

needs_seg = pytest.mark.skipif(
    not capabilities.available("seg"), reason="csa_core.seg is not available in this build"
)
needs_nerf = pytest.mark.skipif(
    not capabilities.available("nerf"), reason="csa_core.nerf is not available in this build"
)


def decode(png: bytes) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img is not None
    return img


@dataclass
class Service:
    live: LiveServer
    client: CSAClient
    pretrain_scene: Path
    target_scene: Path


@pytest.fixture(scope="module")
def service(request, tmp_path_factory, db_backend: str) -> Iterator[Service]:
    from csa_core.data.synth import synthesize

    data = tmp_path_factory.mktemp("e2e")
    (pre,) = synthesize(
        data / "scenes", scenes=1, frames=8, size=SCENE_SIZE, family="apartment", seed=1
    )
    (target,) = synthesize(
        data / "scenes", scenes=1, frames=8, size=SCENE_SIZE, family="office", seed=2
    )
    live = start_server(
        test_settings(data / "service", database_url=database_url(request, db_backend))
    )
    with live.client() as client:
        deadline = time.monotonic() + 10
        while client.health().workers_alive < 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        yield Service(live, client, pre, target)
    live.stop()


@pytest.fixture(scope="module")
def uploaded(service: Service) -> Service:
    for folder in (service.pretrain_scene, service.target_scene):
        scene, result = service.client.upload_scene_folder(folder)
        assert len(result.added) == 8 and scene.num_labelled_frames == 8
    return service


@pytest.fixture(scope="module")
def pretrained(uploaded: Service):
    """A tiny pre-training job: one epoch on the pre-training room."""
    c = uploaded.client
    job = c.pretrain([uploaded.pretrain_scene.name], epochs=1, batch_size=4, name="base")
    events: list[str] = []
    done = c.wait_job(job.id, timeout=300, on_progress=lambda j: events.append(j.status))
    assert done.status == "succeeded", done.error
    assert events[-1] == "succeeded"
    return c.model("base")


def test_health_reports_worker_and_capabilities(service: Service) -> None:
    h = service.client.health()
    assert h.status == "ok" and h.database == "ok" and h.workers_alive == 1
    assert set(h.capabilities) == {"nerf", "seg", "adapt"}


def test_upload_is_visible_and_idempotent(uploaded: Service) -> None:
    c = uploaded.client
    names = {s.name for s in c.scenes()}
    assert {uploaded.pretrain_scene.name, uploaded.target_scene.name} <= names
    scene, again = c.upload_scene_folder(uploaded.target_scene)
    assert again.added == [] and len(again.unchanged) == 8 and scene.num_frames == 8


@needs_seg
def test_pretrain_registers_a_current_model_with_metrics(uploaded: Service, pretrained) -> None:
    c = uploaded.client
    model = pretrained
    assert model.is_current and model.parent_id is None and model.lineage == "base"
    assert model.arch and model.size_bytes > 0
    assert 0.0 <= model.metrics["val_miou"] <= 1.0
    job = c.job(model.job_id)
    assert job.kind == "pretrain" and job.result["model_id"] == model.id
    assert any("started on worker" in line.message for line in c.job_log(job.id))


@needs_seg
def test_predict_returns_a_nyu40_label_map(uploaded: Service, pretrained) -> None:
    image = uploaded.target_scene / "color" / "0.png"
    pred = uploaded.client.predict(image)
    labels = decode(pred.png)
    assert labels.shape == (SCENE_SIZE[1], SCENE_SIZE[0]) and labels.dtype == np.uint8
    assert labels.min() >= 1 and labels.max() <= 40
    assert pred.model_id == pretrained.id
    by_name = uploaded.client.predict(image, model="base", format="color")
    assert decode(by_name.png).shape == (SCENE_SIZE[1], SCENE_SIZE[0], 3)


@needs_seg
def test_evaluate_fills_scores_and_model_download_matches_its_checksum(
    uploaded: Service, pretrained, tmp_path: Path
) -> None:
    c = uploaded.client
    job = c.wait_job(c.evaluate(scenes=[uploaded.target_scene.name]).id, timeout=120)
    miou = job.result["miou"]
    assert len(miou) == 1 and 0.0 <= next(iter(miou.values())) <= 1.0
    model = c.model("current")
    assert f"{uploaded.target_scene.name}/val" in model.evaluations
    path = c.download_model("current", tmp_path / "base.safetensors")
    assert hashlib.sha256(path.read_bytes()).hexdigest() == model.sha256
    copy = c.register_model(path, name="base-copy")
    assert copy.lineage == "base-copy" and copy.sha256 == model.sha256 and not copy.is_current


@needs_seg
@needs_nerf
def test_fit_nerf_on_predictions_fills_the_memory_bank_and_renders(
    uploaded: Service, pretrained
) -> None:
    c = uploaded.client
    scene = uploaded.target_scene.name
    job = c.create_job("fit_nerf", scene=scene, labels="predictions", **TINY_NERF)
    seen: list[float] = []
    done = c.wait_job(job.id, timeout=300, on_progress=lambda j: seen.append(j.progress))
    assert done.status == "succeeded", done.error
    assert seen == sorted(seen) and seen[-1] == 1.0
    bank = c.memory()
    (entry,) = [e for e in bank.entries if e.scene == scene]
    assert entry.size_bytes > 0 and bank.total_bytes >= entry.size_bytes
    assert entry.labels_source == "predictions:base"
    assert (
        entry.quality["val_views"] == 2 and entry.quality["val_psnr"] > 12.0
    )  # a blank render scores ~3 dB
    assert c.scene(scene).has_nerf

    pose = np.loadtxt(uploaded.target_scene / "pose" / "1.txt")
    view = c.render(scene, pose.tolist(), channels=["color", "depth", "labels", "labels_color"])
    assert (view.width, view.height) == SCENE_SIZE and view.nerf_id == entry.id
    color, depth, labels = (
        decode(view.images["color"]),
        decode(view.images["depth"]),
        decode(view.images["labels"]),
    )
    assert color.shape == (30, 40, 3) and depth.dtype == np.uint16 and labels.dtype == np.uint8
    # 0, unknown, only where the fitted field renders no surface (the `fast` preset's
    # render_unseen_unknown; a view without depth is not tested against the cells).
    assert depth.max() > 0 and labels.max() <= 40 and (labels >= 1).mean() > 0.9
    half = {"fx": 15.0, "fy": 15.0, "cx": 9.5, "cy": 7.0, "width": 20, "height": 15}
    assert decode(
        c.render(scene, pose.tolist(), intrinsics=half, channels=["depth"]).images["depth"]
    ).shape == (15, 20)


def test_adapt_answers_501_when_the_core_lacks_it(uploaded: Service, monkeypatch, capsys) -> None:
    """A build without csa_core.adapt (simulated here: the server runs in this process)."""
    missing = capabilities.Capability(
        "adapt", ("csa_core.adapt:not_in_this_build",), "continual adaptation"
    )
    monkeypatch.setitem(capabilities.CAPABILITIES, "adapt", missing)
    with pytest.raises(NotAvailable) as e:
        uploaded.client.adapt(uploaded.target_scene.name)
    assert e.value.status == 501 and "not available in this build" in str(e.value)
    kinds = {k.kind: k for k in uploaded.client.job_kinds()}
    assert (
        not kinds["adapt"].available and "csa_core.adapt.not_in_this_build" in kinds["adapt"].reason
    )
    assert uploaded.client.health().capabilities["adapt"] is not None
    base = ["--url", uploaded.live.url, "--api-key", API_KEY]
    assert cli_main([*base, "adapt", "--scene", uploaded.target_scene.name, "--wait"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("csa-client: error: HTTP 501 not_available") and err.count("\n") == 1


@needs_seg
def test_continual_metrics_of_a_lineage_without_steps(uploaded: Service, pretrained) -> None:
    m = uploaded.client.continual_metrics()
    assert m.lineage == "base" and m.root_model_id == pretrained.id
    assert m.steps == [] and m.R == [] and m.acc is None


def test_prometheus_metrics(uploaded: Service) -> None:
    text = uploaded.client.prometheus_metrics()
    assert "# TYPE csa_http_requests_total counter" in text
    assert (
        'csa_http_requests_total{method="POST",route="/api/v1/scenes/{scene_ref}/archive",status="200"}'
        in text
    )
    assert "csa_frames 16" in text and "csa_workers_alive 1" in text


@needs_seg
def test_command_line_client(uploaded: Service, pretrained, tmp_path: Path, capsys) -> None:
    base = ["--url", uploaded.live.url, "--api-key", API_KEY]
    assert cli_main([*base, "upload", str(uploaded.target_scene)]) == 0
    assert "0 added, 8 unchanged" in capsys.readouterr().out
    assert cli_main([*base, "models"]) == 0
    assert "base" in capsys.readouterr().out
    out = tmp_path / "pred.png"
    assert (
        cli_main(
            [*base, "predict", str(uploaded.target_scene / "color" / "3.png"), "--out", str(out)]
        )
        == 0
    )
    assert decode(out.read_bytes()).shape == (30, 40)
    assert cli_main([*base, "jobs"]) == 0 and "pretrain" in capsys.readouterr().out
    assert cli_main([*base, "metrics"]) == 0
    assert cli_main([*base, "--api-key", "wrong", "models"]) == 1
    assert "HTTP 401 unauthorized: invalid API key" in capsys.readouterr().err
    if (
        capabilities.available("nerf")
        and uploaded.client.scene(uploaded.target_scene.name).has_nerf
    ):
        assert (
            cli_main(
                [
                    *base,
                    "render",
                    "--scene",
                    uploaded.target_scene.name,
                    "--pose",
                    str(uploaded.target_scene / "pose" / "2.txt"),
                    "--out",
                    str(tmp_path / "view"),
                ]
            )
            == 0
        )
        assert sorted(p.name for p in (tmp_path / "view").iterdir()) == [
            "color.png",
            "depth.png",
            "labels.png",
        ]


@needs_seg
def test_progress_stream_is_server_sent_events(uploaded: Service, pretrained) -> None:
    import httpx

    with httpx.Client(
        base_url=uploaded.live.url, headers={"X-API-Key": API_KEY}, timeout=10
    ) as http:
        with http.stream("GET", f"/api/v1/jobs/{pretrained.job_id}/events") as r:
            assert r.status_code == 200 and r.headers["content-type"].startswith(
                "text/event-stream"
            )
            lines = [line for line in r.iter_lines() if line]
    events = [line.split(": ", 1)[1] for line in lines if line.startswith("event:")]
    assert events == ["progress", "end"]
    assert '"status":"succeeded"' in lines[lines.index("event: progress") + 1]


@pytest.mark.skipif(
    not capabilities.available("adapt"),
    reason="the adapt job needs csa_core.adapt, not in this build",
)
def test_adapt_is_a_continual_step(uploaded: Service, pretrained) -> None:
    """Last in this file: it adds a step to the lineage the tests above see without one."""
    c = uploaded.client
    scene = uploaded.target_scene.name
    done = c.wait_job(c.adapt(scene, preset="tiny").id, timeout=600)
    assert done.lineage == "base"
    new = c.model(done.result["model_id"])
    assert new.parent_id == pretrained.id and new.adapted_scene == scene and new.lineage == "base"
    assert new.is_current and new.name == "base-step1"
    assert 0.0 <= new.metrics["val_miou"] <= 1.0 and "pseudo_label_miou" in new.metrics
    entry = c.scene_nerf(scene)
    assert entry.labels_source == "adapt:base" and entry.job_id == done.id and entry.size_bytes > 0
    m = c.continual_metrics(lineage="base")
    assert [s.model_id for s in m.steps] == [new.id] and [s.scene for s in m.steps] == [scene]
    assert m.R[0][0] == new.metrics["val_miou"] and m.b[0] is not None and m.missing == []
    assert m.acc == m.R[0][0] and m.fwt is None and m.bwt is None  # one step: no transfer terms
    pred = c.predict(uploaded.target_scene / "color" / "0.png")
    assert pred.model_id == new.id
