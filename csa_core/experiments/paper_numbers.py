"""The paper's own numbers, shown beside ours by ``csa experiment paper``.

All of them are from docs/method.md "Reference numbers" (the paper, mean of 10 ScanNet
scenes, mIoU %; the reported cost on an RTX 3090). The paper's Tab. 3 and its supplementary
ablations are not recorded there, so the report shows no paper number for them rather than
one from memory.
"""

from __future__ import annotations

# docs/method.md "Reference numbers": pseudo-label mIoU % (paper Tab. 1), by label source.
TAB1: dict[str, float] = {"network": 41.7, "mapping": 44.0, "nerf": 44.7, "joint": 45.0}

# docs/method.md "Reference numbers": validation mIoU % after one-step adaptation (paper
# Tab. 2); "pretrained" is the network before adaptation. No numbers for Mapping or CoTTA.
TAB2: dict[str, float] = {"pretrained": 44.8, "gi_nl": 45.2, "ni_nl": 45.9, "joint": 47.4}

# docs/method.md "Reference numbers": the reported cost of the paper's NeRF (hash grid,
# RTX 3090) and of Semantic-NeRF's MLP version.
FRAMEWORK: dict[str, float] = {
    "step_seconds": 0.06,
    "fit_minutes": 5.0,
    "checkpoint_mb": 50.0,
    "mlp_checkpoint_mb": 4.9,
    "mlp_slowdown": 127.0,
}
