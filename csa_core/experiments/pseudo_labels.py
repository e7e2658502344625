"""Experiment ``pseudo-labels``: how good are the labels each method would train on (paper Tab. 1)?

Per scene and seed, on the training views: the pre-trained network's predictions, Mapping's
labels (the predictions fused in a voxel map and read back) and the NeRF's rendered labels
(a Semantic-NeRF fitted to the same predictions), each scored against the ground truth.
Nothing is fine-tuned. Where the config re-estimates BatchNorm statistics before labelling
(``AdaptConfig.adabn_before_labels``, the ``cpu`` preset), the network predicts each scene
with its statistics re-estimated on that scene's camera images, as the continual step's
labels are made (``csa_core.adapt.finetune.begin_step``). The NeRF fit is the only seeded
step, so the network and Mapping columns have little or no spread over seeds.
"""

from __future__ import annotations

import copy
import time

from csa_core.adapt.baselines.mapping import mapping_pseudo_labels
from csa_core.adapt.config import AdaptConfig
from csa_core.adapt.finetune import apply_adabn, step_nerf_budget
from csa_core.adapt.pseudo_labels import label_miou, make_pseudo_labels
from csa_core.data.scene import Scene
from csa_core.experiments.inputs import ExperimentInputs
from csa_core.experiments.report import ExperimentReport, markdown_table, mean_std, pct
from csa_core.seg.models import SegmentationNet

NAME = "pseudo-labels"
# Label sources, in the order of the table's columns.
SOURCES: tuple[str, ...] = ("network", "mapping", "nerf")
TITLES = {"network": "Network", "mapping": "Mapping", "nerf": "NeRF (ours)"}


def labelling_network(model: SegmentationNet, scene: Scene, config: AdaptConfig) -> SegmentationNet:
    """The network that labels ``scene``'s training views under ``config``: ``model`` itself,
    or a copy with BatchNorm statistics re-estimated on the scene's camera images where
    ``config.adabn_before_labels`` (as the continual step labels)."""
    if not config.adabn_before_labels:
        return model
    net = copy.deepcopy(model)
    apply_adabn(
        net, [f.color for f in scene.train_frames], None, config.seg.seed, config.seg.device
    )
    return net


def run(inputs: ExperimentInputs) -> ExperimentReport:
    """Score the three label sources on every scene for every seed."""
    scores: dict[tuple[str, str], list[float]] = {}
    runs = []
    model = inputs.network()
    for seed in inputs.seeds:
        config = inputs.config(seed)
        for scene in inputs.scenes:
            t0 = time.perf_counter()
            # The NeRF of the fine-tuning modes: the whole fit before the pseudo-labels.
            budget = step_nerf_budget(config, scene, mode="gi_nl")
            net = labelling_network(model, scene, config)
            _, pseudo = make_pseudo_labels(net, scene, budget, config.seg.device, color=False)
            mapped = mapping_pseudo_labels(scene, pseudo.predictions)
            values = {
                "network": label_miou(pseudo.predictions, scene),
                "mapping": label_miou(mapped, scene),
                "nerf": label_miou(pseudo.labels, scene),
            }
            for source, v in values.items():
                scores.setdefault((scene.name, source), []).append(v)
            runs.append(
                {
                    "scene": scene.name,
                    "seed": seed,
                    "train_views": len(pseudo.names),
                    "miou": values,
                    "seconds": {**pseudo.seconds, "total": time.perf_counter() - t0},
                    "config": config.to_dict(),
                }
            )
    return _report(inputs, scores, runs)


def _report(
    inputs: ExperimentInputs,
    scores: dict[tuple[str, str], list[float]],
    runs: list[dict],
) -> ExperimentReport:
    n = len(inputs.seeds)
    names = [s.name for s in inputs.scenes]
    rows, csv_rows = [], []
    for scene in names:
        cells = []
        for source in SOURCES:
            m, s = mean_std(scores[(scene, source)])
            cells.append(pct(m, s, n))
            csv_rows.append([scene, source, m, s, n])
        rows.append([scene, *cells])
    means = []
    for source in SOURCES:
        per_seed = [
            sum(scores[(scene, source)][k] for scene in names) / len(names) for k in range(n)
        ]
        means.append(pct(*mean_std(per_seed), n))
    rows.append(["**mean**", *means])
    header = ["scene", *(f"{TITLES[s]} mIoU %" for s in SOURCES)]
    md = (
        f"### Pseudo-label quality on training views ({n} seed{'s' * (n > 1)}, "
        f"preset {inputs.preset})\n\n" + markdown_table(header, rows)
    )
    return ExperimentReport(
        name=NAME,
        markdown=md,
        csv_header=["scene", "labels", "miou_mean", "miou_std", "seeds"],
        csv_rows=csv_rows,
        runs=runs,
    )
