"""How much a segmentation network's predictions can gain from fusing views (not a test).

A fuser of per-frame labels (the map, the NeRF) can only remove the errors the views disagree
on. This measures, on a network's real predictions of a labelled scene, how much of the
network's error is of that kind, and what fusing gives under a few voting rules, all with the
same geometry: every training pixel's surface point (at its measured depth: exact on a
synthetic scene, noisy and with holes on its hard variant) falls in a 5 cm voxel, each voxel
sums what the training views predicted there, and every pixel (training or held-out) reads
back the voxel its own depth falls in (the map's "depth read-back"; a held-out
pixel in a voxel no training view saw keeps the network's prediction).

    python benchmarks/prediction_consensus.py --model runs/demo/pretrained.safetensors \\
        runs/demo/scenes/target/office_1000_0 synth:studio:0 --frames 250 --size 160x120 \\
        --variants clean,hard --adabn

Columns, mIoU % on training / held-out views:

- ``network``: the per-frame predictions;
- ``vote``: arg-max of the voxel's label counts (one vote per pixel, the Mapping baseline's
  hard fusion);
- ``confident vote``: the votes weighted by the network's largest softmax probability at the
  pixel (what weighting each ray's label loss by the network's confidence gives);
- ``near vote``: the votes weighted by 1 / z^2, z the pixel's depth (at least 0.3 m): the
  views that see the point from close by get more say;
- ``mean prob``: arg-max of the voxel's summed softmax probabilities (soft fusion);
- ``log prob``: arg-max of the summed log-probabilities (a product of independent experts);
- ``oracle``: each pixel takes its true label if any training view predicted that label in its
  voxel, else the vote: the ceiling of every fuser that picks, per surface point, one of the
  labels the views proposed;
- ``err: fixable / shared``: of the training pixels the network gets wrong, the share whose
  voxel's vote is right (the error disagrees with most views of the point) and the share whose
  vote is the same wrong label (most views make the same mistake: no consensus removes it).
"""

from __future__ import annotations

import argparse
import copy
import itertools

import numpy as np
import torch
from fusion_bench import miou, open_scene

from csa_core.adapt.baselines.voxel_map import PAPER_VOXEL_SIZE, pack_keys, voxel_coords
from csa_core.data.camera import backproject
from csa_core.data.nyu40 import NUM_CLASSES
from csa_core.data.scene import NYU40_FOLDER, Scene
from csa_core.data.synth import degrade_scene, parse_size
from csa_core.nerf.losses import NEAR_DEPTH
from csa_core.seg.adabn import adapt_batchnorm
from csa_core.seg.checkpoint import load_checkpoint
from csa_core.seg.predict import predict_logits


def voxel_keys(scene: Scene, frame, voxel: float) -> np.ndarray:
    """One int64 key per pixel of ``frame`` for the voxel its depth point falls in (-1: no
    depth), packed as the voxel map packs its cells."""
    pts = backproject(frame.depth, scene.intrinsics, frame.pose).reshape(-1, 3)
    ok = np.isfinite(pts).all(1)
    keys = np.full(len(pts), -1, np.int64)
    keys[ok] = pack_keys(voxel_coords(pts[ok], voxel))
    return keys


def fuse(scene: Scene, model, size, voxel: float, batch: int = 16) -> dict[str, dict]:
    """Per rule, ``{frame name: (H, W) NYU40 labels}`` for every frame of the scene, and the
    error split of the training pixels."""
    frames = scene.frames
    train = {f.name for f in scene.train_frames}
    keys = {f.name: voxel_keys(scene, f, voxel) for f in frames}
    depth = {f.name: f.depth.reshape(-1) for f in frames}
    probs: dict[str, torch.Tensor] = {}
    for i in range(0, len(frames), batch):
        chunk = frames[i : i + batch]
        logits = predict_logits(model, [f.color for f in chunk], batch, "cpu", size)
        for f, lg in zip(chunk, logits, strict=True):
            probs[f.name] = torch.softmax(lg, 0).reshape(NUM_CLASSES, -1).T.contiguous()
    table = np.unique(np.concatenate([keys[n][keys[n] >= 0] for n in train]))
    v, c = len(table), NUM_CLASSES
    votes = torch.zeros(v, c, dtype=torch.float64)
    soft = torch.zeros(v, c, dtype=torch.float64)
    logp = torch.zeros(v, c, dtype=torch.float64)
    conf = torch.zeros(v, c, dtype=torch.float64)
    near = torch.zeros(v, c, dtype=torch.float64)
    for name in train:
        k = keys[name]
        ok = k >= 0
        idx = torch.as_tensor(np.searchsorted(table, k[ok]))
        p = probs[name][torch.as_tensor(ok)].double()
        top, arg = p.max(1)
        hot = torch.nn.functional.one_hot(arg, c).double()
        votes.index_add_(0, idx, hot)
        conf.index_add_(0, idx, hot * top[:, None])
        z = torch.as_tensor(depth[name][ok]).double().clamp_min(NEAR_DEPTH)
        near.index_add_(0, idx, hot / z[:, None] ** 2)
        soft.index_add_(0, idx, p)
        logp.index_add_(0, idx, p.clamp_min(1e-6).log())
    rules = {
        "network": None,
        "vote": votes.argmax(1).numpy(),
        "confident vote": conf.argmax(1).numpy(),
        "near vote": near.argmax(1).numpy(),
        "mean prob": soft.argmax(1).numpy(),
        "log prob": logp.argmax(1).numpy(),
    }
    has_label = votes.numpy() > 0
    out: dict[str, dict] = {r: {} for r in [*rules, "oracle"]}
    fixable = shared = wrong = 0
    for f in frames:
        k = keys[f.name]
        own = probs[f.name].argmax(1).numpy()
        pos = np.searchsorted(table, k).clip(0, max(v - 1, 0))
        seen = (k >= 0) & (table[pos] == k) if v else np.zeros_like(k, bool)
        gt = f.labels[NYU40_FOLDER].reshape(-1).astype(np.int64)
        fused = {}
        for rule, best in rules.items():
            lab = own.copy()
            if best is not None:
                lab[seen] = best[pos[seen]]
            fused[rule] = lab
        vote = fused["vote"]
        oracle = vote.copy()
        cls = gt - 1
        known = seen & (gt > 0)
        hit = np.zeros_like(known)
        hit[known] = has_label[pos[known], cls[known]]
        oracle[hit] = cls[hit]
        fused["oracle"] = oracle
        for rule, lab in fused.items():
            out[rule][f.name] = (lab + 1).astype(np.uint8).reshape(f.depth.shape)
        if f.name in train:
            bad = known & (own != cls)
            wrong += int(bad.sum())
            fixable += int((bad & (vote == cls)).sum())
            shared += int((bad & (vote == own)).sum())
    out["errors"] = {"fixable": fixable / max(wrong, 1), "shared": shared / max(wrong, 1)}
    return out


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("scenes", nargs="+", help="scene folders or synth:FAMILY:SEED specs")
    p.add_argument("--model", required=True, help="a segmentation network checkpoint")
    p.add_argument("--frames", type=int, default=250, help="frames of a synthetic scene")
    p.add_argument("--size", default="160x120", help="WxH working size of a synthetic scene")
    p.add_argument(
        "--variants",
        default="clean",
        help="comma-separated: clean, hard (the Kinect-like copy of csa_core/data/synth/kinect.py: "
        "the network predicts its degraded colour, its noisy depth places the votes)",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the hard variant's degradation")
    p.add_argument("--voxel", type=float, default=PAPER_VOXEL_SIZE, help="voxel edge, metres")
    p.add_argument(
        "--adabn",
        action="store_true",
        help="recompute the network's BatchNorm statistics on each scene's training views first "
        "(AdaBN, as the adaptation's first step does; the pre-training images not mixed in)",
    )
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    model, card = load_checkpoint(args.model, device="cpu")
    size = tuple(card.input_size) if card.input_size else None
    rules = ["network", "vote", "confident vote", "near vote", "mean prob", "log prob", "oracle"]
    variants = args.variants.split(",")
    bad = sorted(set(variants) - {"clean", "hard"})
    if bad:
        raise SystemExit(f"--variants: unknown {', '.join(bad)} (clean, hard)")
    print("| scene | variant | " + " | ".join(rules) + " | err: fixable / shared |")
    print("|---" * (len(rules) + 3) + "|")
    for spec, variant in itertools.product(args.scenes, variants):
        scene, labelled = open_scene(spec, parse_size(args.size), args.frames)
        if not labelled:
            raise SystemExit(f"{spec}: no ground-truth labels ({NYU40_FOLDER}) to score against")
        if variant == "hard":
            scene = degrade_scene(scene, args.seed, source=None)
        net = model
        if args.adabn:
            net = copy.deepcopy(model)
            adapt_batchnorm(net, [f.color for f in scene.train_frames], device="cpu")
        res = fuse(scene, net, size, args.voxel)
        cells = [
            f"{100 * miou(res[r], scene.train_frames):.1f} / "
            f"{100 * miou(res[r], scene.val_frames):.1f}"
            for r in rules
        ]
        err = res["errors"]
        print(
            f"| {scene.name} | {variant} | "
            + " | ".join(cells)
            + f" | {100 * err['fixable']:.0f}% / {100 * err['shared']:.0f}% |"
        )


if __name__ == "__main__":
    main()
