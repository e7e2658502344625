"""What the dashboard's pages show, gathered from the service's own answers.

Pages read the same objects the REST API answers with, from the same functions of the
service layer (``server/services``: scenes, model versions, the memory bank, continual
metrics), plus a few summaries only a person looking at a page needs: the depth coverage of a
scene, a model lineage as a tree, the memory bank's cost against what the baselines would keep.
"""

from __future__ import annotations

import math
import tempfile
import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from sqlalchemy.orm import Session

from csa_core.data.image_files import read_depth_mm
from csa_core.data.scene import split_point
from server.artifacts import ArtifactStore
from server.errors import APIError
from server.keys import Principal
from server.model_cache import ModelCache
from server.schemas.continual import ContinualMetricsOut
from server.schemas.memory import NerfOut
from server.schemas.models import ModelOut
from server.schemas.scenes import SceneOut
from server.services import continual, frames, models, nerfs, scenes

if TYPE_CHECKING:
    from csa_core.experiments.report import Plot

DEPTH_SAMPLE_FRAMES = 12  # depth coverage is measured on this many evenly spaced frames

# Quality numbers a NeRF entry may carry (fit_nerf and adapt jobs), in the order shown.
NERF_QUALITY: tuple[tuple[str, str, str], ...] = (
    ("val_psnr", "val PSNR", "db"),
    ("train_psnr", "train PSNR", "db"),
    ("val_depth_mae_m", "val depth error", "m"),
    ("pseudo_label_miou", "pseudo-label mIoU", "pct"),
    ("final_label_miou", "rendered-label mIoU", "pct"),
)


def evenly_spaced(items: Sequence[Any], count: int) -> list[Any]:
    if len(items) <= count:
        return list(items)
    return [items[round(i * (len(items) - 1) / (count - 1))] for i in range(count)]


class DepthCoverage:
    """Fraction of depth pixels with a measurement, over a sample of a scene's frames;
    remembered per set of depth files, since stored files never change."""

    def __init__(self, store: ArtifactStore, size: int = 256):
        self.store = store
        self.size = size
        self._items: OrderedDict[tuple[str, ...], float] = OrderedDict()
        self._lock = threading.Lock()

    def __call__(self, depth_shas: Sequence[str]) -> float | None:
        sample = tuple(evenly_spaced(list(depth_shas), DEPTH_SAMPLE_FRAMES))
        if not sample:
            return None
        with self._lock:
            if sample in self._items:
                self._items.move_to_end(sample)
                return self._items[sample]
        valid = total = 0
        for sha in sample:
            depth = read_depth_mm(self.store.open_verified(sha))
            valid += int(np.count_nonzero(depth))
            total += depth.size
        value = valid / total if total else None
        with self._lock:
            self._items[sample] = value
            while len(self._items) > self.size:
                self._items.popitem(last=False)
        return value


def quality_items(quality: dict[str, Any]) -> list[tuple[str, str]]:
    """(label, formatted value) of the known quality numbers a NeRF entry has."""
    out = []
    for key, label, unit in NERF_QUALITY:
        value = quality.get(key)
        if not isinstance(value, int | float) or not math.isfinite(value):
            continue
        text = {"db": f"{value:.1f} dB", "m": f"{value:.3f} m", "pct": f"{100 * value:.1f}%"}[unit]
        out.append((label, text))
    return out


@dataclass
class SceneRow:
    scene: SceneOut
    depth_coverage: float | None
    nerf: NerfOut | None
    nerf_quality: list[tuple[str, str]]


def scene_rows(
    db: Session, coverage: DepthCoverage, visible_to: Principal | None = None
) -> list[SceneRow]:
    bank = {e.scene_id: e for e in nerfs.memory_bank(db, include_inactive=False).entries}
    rows = []
    for scene in scenes.all_scenes(db, visible_to):
        shas = frames.depth_files(db, scene.id)
        nerf = bank.get(scene.id)
        rows.append(
            SceneRow(scene, coverage(shas), nerf, quality_items(nerf.quality) if nerf else [])
        )
    return rows


@dataclass
class ModelNode:
    model: ModelOut
    children: list[ModelNode] = field(default_factory=list)


@dataclass
class Lineage:
    name: str
    roots: list[ModelNode]
    versions: list[ModelOut]


def lineages(db: Session) -> list[Lineage]:
    """Every lineage as a tree of versions (a version's children were adapted from it)."""
    versions = models.all_models(db)
    nodes = {m.id: ModelNode(m) for m in versions}
    by_lineage: dict[str, Lineage] = {}
    for m in versions:
        lin = by_lineage.setdefault(m.lineage, Lineage(m.lineage, [], []))
        lin.versions.append(m)
        parent = nodes.get(m.parent_id) if m.parent_id is not None else None
        if parent is not None and parent.model.lineage == m.lineage:
            parent.children.append(nodes[m.id])
        else:
            lin.roots.append(nodes[m.id])
    return list(by_lineage.values())


def evaluated_scenes(models: Sequence[ModelOut], split: str = "val") -> list[str]:
    """Scene names any of ``models`` was scored on (``split``), in first-seen order."""
    names: dict[str, None] = {}
    for m in models:
        for key in m.evaluations:
            scene, _, s = key.rpartition("/")
            if s == split:
                names[scene] = None
    return list(names)


def continual_metrics(
    db: Session, lineage: str | None, split: str = "val"
) -> ContinualMetricsOut | None:
    """The continual route's answer, or None when there is no model (or lineage) to show."""
    try:
        return continual.continual_metrics(db, lineage, split)
    except APIError as e:
        if e.status == 404:
            return None
        raise


def miou_per_step_plot(metrics: ContinualMetricsOut) -> Plot:
    """mIoU on each scene (one line per scene) before adapting (step 0) and after each step, on
    the whole 0-100% range: scaled to the data, a change of a tenth of a point looked like a
    steep rise."""
    from csa_core.experiments.report import Plot, Series

    steps = len(metrics.steps)
    series = []
    for j, step in enumerate(metrics.steps):
        ys = [metrics.b[j], *(row[j] for row in metrics.R)]
        series.append(
            Series(
                step.scene or f"scene {step.scene_id}",
                list(range(steps + 1)),
                [100 * v if v is not None else math.nan for v in ys],
            )
        )
    labels = [
        "pre-trained",
        *(f"step {i}: {s.scene or s.scene_id}" for i, s in enumerate(metrics.steps)),
    ]
    return Plot(
        file="miou.png",
        title=f"mIoU per scene over the steps of {metrics.lineage} ({metrics.split})",
        xlabel="after",
        ylabel="mIoU (%)",
        series=series,
        xticks=list(range(steps + 1)),
        xticklabels=labels,
        ylim=(0.0, 100.0),
    )


def miou_per_step_png(metrics: ContinualMetricsOut) -> bytes:
    """:func:`miou_per_step_plot` drawn by the experiments' plot code."""
    from csa_core.experiments.report import save_plot

    plot = miou_per_step_plot(metrics)
    with tempfile.TemporaryDirectory(prefix="csa-ui-plot-") as d:
        path = Path(d) / plot.file
        save_plot(path, plot)
        return path.read_bytes()


@dataclass
class MemoryRow:
    nerf: NerfOut
    quality: list[tuple[str, str]]
    frames: int
    train_frames: int
    mapping_bytes: int | None  # the training images and labels Mapping would store


@dataclass
class MemorySummary:
    rows: list[MemoryRow]
    nerf_bytes: int
    mapping_bytes: int
    cotta_bytes: int | None
    cotta_model: str | None
    cotta_reason: str | None


def mapping_bytes(num_frames: int, width: int, height: int) -> tuple[int, int]:
    """(training frames, bytes) Mapping keeps to replay a scene: its training images and their
    labels as uint8 arrays, as ``MappingMemory.footprint()`` counts them (its voxel map, which
    needs the depth fusion to size, is left out, so this is a lower bound)."""
    from csa_core.adapt.baselines.mapping import MappingFootprint

    n = split_point(num_frames)
    return n, MappingFootprint(
        map_bytes=0,
        image_bytes=n * width * height * 3,
        label_bytes=n * width * height,
        num_images=n,
    ).total_bytes


def cotta_bytes(db: Session, cache: ModelCache) -> tuple[int | None, str | None, str | None]:
    """(bytes, model name, why not) of CoTTA's two extra copies (teacher and source) of the
    current network, measured on the loaded network."""
    from server import capabilities

    checkpoint = models.current_checkpoint(db)
    if checkpoint is None:
        return None, None, "no current model"
    reason = capabilities.missing_reason("seg")
    if reason is not None:
        return None, checkpoint.model_name, reason
    from csa_core.adapt.baselines.cotta import CoTTAFootprint, module_bytes

    net, _ = cache.get(checkpoint.sha256)
    one = module_bytes(net)
    return (
        CoTTAFootprint(teacher_bytes=one, source_bytes=one, optimizer_bytes=0).extra_copies_bytes,
        checkpoint.model_name,
        None,
    )


def memory_summary(db: Session, cache: ModelCache) -> MemorySummary:
    bank = nerfs.memory_bank(db, include_inactive=False)
    by_id = {s.id: s for s in scenes.all_scenes(db)}
    rows = []
    for entry in bank.entries:
        scene = by_id.get(entry.scene_id)
        if scene is None or scene.intrinsics is None:
            rows.append(
                MemoryRow(
                    entry, quality_items(entry.quality), scene.num_frames if scene else 0, 0, None
                )
            )
            continue
        n_train, kept = mapping_bytes(
            scene.num_frames, scene.intrinsics.width, scene.intrinsics.height
        )
        rows.append(MemoryRow(entry, quality_items(entry.quality), scene.num_frames, n_train, kept))
    cotta, cotta_model, why = cotta_bytes(db, cache)
    return MemorySummary(
        rows, bank.total_bytes, sum(r.mapping_bytes or 0 for r in rows), cotta, cotta_model, why
    )


def nerf_scenes(db: Session) -> list[tuple[SceneOut, list[str]]]:
    """Scenes with a NeRF in the memory bank and the names of their training frames (the
    poses a NeRF was fitted on: the first part of the frames in order)."""
    out = []
    for scene in scenes.all_scenes(db):
        if not scene.has_nerf:
            continue
        names = frames.names_in_order(db, scene.id)
        out.append((scene, names[: split_point(len(names))]))
    return out
