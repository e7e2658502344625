"""Configuration of the Semantic-NeRF: one dataclass per component, presets as config values.

``reference`` follows the paper and its official code (docs/method.md "Reference numbers");
``fast`` is our CPU-friendly variant (smaller table, depth-guided training samples,
occupancy-grid rendering, fp16 checkpoints). Every fitted checkpoint stores the full config.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Iterable
from dataclasses import dataclass
from dataclasses import field as _field
from typing import TYPE_CHECKING, Any, Literal

from csa_core.data.nyu40 import NUM_CLASSES
from csa_core.overrides import apply_overrides

if TYPE_CHECKING:
    from torch import Tensor


@dataclass
class HashEncodingConfig:
    """Multi-resolution hash grid (Instant-NGP)."""

    num_levels: int = 16  # docs/method.md "Reference numbers": 16 levels
    features_per_level: int = 2  # docs/method.md "Reference numbers": 2 features per level
    log2_table_size: int = 19  # docs/method.md "Reference numbers": table 2^19
    base_resolution: int = 16  # docs/method.md "Reference numbers": base resolution 16
    finest_resolution: int = 2048  # Instant-NGP / torch-ngp default for unit-cube scenes
    # Ours: torch.compile the corner computation (integer hashing and trilinear weights, many
    # small elementwise steps that inductor fuses into one loop). Measured on 2 CPU cores
    # (benchmarks/results/speed.md, "Label fusion speed"): field forward + backward 1.4x, inference
    # 1.9x, but 30 s (cached) to 100 s (first time) to compile in every new process, so off by
    # default; falls back to eager if compiling fails.
    compile: bool = False
    # Ours: ``auto`` encodes float32 positions on the CPU with a fused C kernel
    # (csa_core/nerf/hash_kernel.py; benchmarks/results/speed.md, "A fused C kernel for the
    # hash encoding") where a C compiler is present, and on CUDA with a Triton kernel
    # (csa_core/nerf/hash_triton.py) where Triton is, else in PyTorch; ``torch``: always PyTorch.
    implementation: Literal["auto", "torch"] = "auto"

    def __post_init__(self) -> None:
        if self.implementation not in ("auto", "torch"):
            raise ValueError(
                f"encoding.implementation must be 'auto' or 'torch', got {self.implementation!r}"
            )


@dataclass
class FieldConfig:
    """Density, colour and semantic heads on top of the hash encoding."""

    encoding: HashEncodingConfig = _field(default_factory=HashEncodingConfig)
    hidden_dim: int = 64  # docs/method.md "Reference numbers": all MLPs 64 wide
    density_hidden_layers: int = (
        1  # docs/method.md "Reference numbers": density MLP, 1 hidden layer
    )
    geo_features: int = (
        15  # docs/method.md "Reference numbers": 15 geometry features beside the density
    )
    color_hidden_layers: int = 2  # docs/method.md "Reference numbers": colour MLP 2-3 layers of 64
    semantic_hidden_layers: int = (
        2  # docs/method.md "Reference numbers": semantic MLP 2 layers of 64
    )
    # Ours: the semantic head also reads its own feature table, laid out like the first
    # ``semantic_grid_levels`` levels of the hash grid and interpolated with the same corners.
    # Only the semantic loss trains it, so geometry still gets no semantic gradient; the detached
    # 15 geometry features alone could not fit even clean labels in our tests. 0 = paper (geometry
    # features only).
    semantic_grid_levels: int = 12
    # Ours: the semantic head reads the geometry features detached as well, so the semantic
    # loss never reaches geometry (a test pins it). False = the official head: the features
    # carry the semantic gradient into the density MLP and the hash table; in both, the
    # rendering weights are detached for the semantic channel (docs/presets.md "The paper preset").
    semantic_detach_geometry: bool = True
    sh_degree: int = 4  # spherical harmonics of the view direction (16 coefficients)
    # Ours: "bfloat16" runs the MLPs under bf16 autocast on CUDA (the paper's implementation
    # trains its MLPs in fp16; bf16 needs no loss scaling); densities, colours and class
    # distributions are composited in float32. CPU tensors always run in float32.
    mlp_dtype: Literal["float32", "bfloat16"] = "float32"

    def __post_init__(self) -> None:
        if self.mlp_dtype not in ("float32", "bfloat16"):
            raise ValueError(
                f"field.mlp_dtype must be 'float32' or 'bfloat16', got {self.mlp_dtype!r}"
            )

    num_classes: int = NUM_CLASSES  # NYU40 ids 1..40 -> channels 0..39


@dataclass
class SamplerConfig:
    """Where samples go along each ray, in training and in rendering.

    ``reference``: stratified uniform samples, then importance samples from their weights
    (paper: 256 + 256). ``depth``: depth-guided (training only; rays without a measurement
    fall back to stratified samples). ``occupancy``: ray marching that skips empty cells of an
    occupancy grid (rendering, and training rays without depth). ``render_depth_guided``:
    views that have measured depth (the training views' pseudo-labels) render with
    ``render_band_samples`` samples in the depth band only. Their rays without a measurement
    (sensor holes) get a depth estimate instead when ``render_hole_estimate`` is on (from the
    first occupied cell of the occupancy grid, a density-only march in steps of
    ``render_estimate_step`` cells to opacity 1/2: ``samplers.GridSurfaceEstimate``) and render
    in the band around it, ``render_estimate_band_scale`` times as wide; rays it finds no
    surface for, all of them when it is off, and views without depth use the ``render``
    sampler, unless ``render_novel_estimate`` treats each of their rays as a hole too.
    Rendering only: training samples never change.
    """

    train: Literal["reference", "depth", "occupancy"] = "reference"
    render: Literal["reference", "occupancy"] = "reference"
    render_depth_guided: bool = False  # paper: every view renders with the ``render`` sampler
    render_band_samples: int = 8  # depth-guided rendering: samples in the band of each ray
    # Ours: depth-guided rendering estimates the surface of rays in depth holes instead of
    # marching them (benchmarks/results/speed.md, "Depth holes and unseen surfaces"); False = march.
    render_hole_estimate: bool = True
    render_estimate_step: float = 0.5  # hole estimate: march step, in occupancy cells
    render_estimate_band_scale: float = 2.0  # hole estimate: band width against a measurement's
    # Ours, off by default: a view without any depth (novel views, replay) renders every ray
    # as a hole, in the band around its estimated surface (needs ``render_depth_guided``);
    # False = every ray of such a view marches the ``render`` sampler.
    render_novel_estimate: bool = False
    # Ours: colour (and depth) of a view with depth from the band too, normalised by the band's
    # opacity (the colour of the surface the band holds); rays whose band opacity is below
    # ``render_band_min_opacity`` (a partly fitted field, a floater in front) march the whole
    # ray. False = every ray's colour and depth from the ``render`` sampler (as the paper).
    render_band_color: bool = False
    render_band_min_opacity: float = 0.5
    # Ours: the class distribution of a ray with measured depth weights its samples by a
    # Gaussian around that depth as well, of standard deviation ``render_band_label_sigma``
    # times the band's half-width (labels only; colour, depth and opacity keep the plain
    # weights). 0 = the plain weights, as the paper.
    render_band_label_sigma: float = 0.0
    # Ours: the class distribution of a ray with measured depth mixes in the semantic head's
    # distribution at the measured surface point with this weight (0 = the band's composite
    # alone, as the paper; 1 = the surface point alone).
    render_surface_label_weight: float = 0.0
    # Ours, off by default (None): the class distribution of a ray with measured depth reads
    # only its band samples at most this many metres behind the measured depth (a surface's
    # inside, which no view sees, is left out; colour, depth and opacity keep every sample).
    render_band_label_behind: float | None = None
    uniform_samples: int = 256  # docs/method.md "Reference numbers": 256 uniform samples per ray
    importance_samples: int = (
        256  # docs/method.md "Reference numbers": 256 importance samples per ray
    )
    near: float = 0.05  # metres in front of the camera where rays start
    depth_band: float = (
        0.10  # depth-guided: half-width (metres) of the band around the measured depth
    )
    depth_band_fraction: float = (
        0.02  # ... widened by this fraction of the depth (sensor noise grows with range)
    )
    band_samples: int = 8  # depth-guided: samples inside the band
    spread_samples: int = 8  # depth-guided: stratified samples over the rest of the ray
    occupancy_resolution: int = 64  # occupancy grid cells per axis
    occupancy_threshold: float = 0.01  # a cell is occupied if its density * step exceeds this
    march_steps: int = 512  # marching step = box diagonal / march_steps
    occupancy_update_every: int = 16  # training steps between grid updates
    max_render_samples: int = 96  # occupancy marching: at most this many samples kept per ray
    # The rendering march (``render="occupancy"``; training marches keep ``march_steps`` and
    # are not pruned): step = box diagonal / ``render_march_steps`` (None: ``march_steps``);
    # a ray stops once its transmittance is below ``render_early_stop``, and samples of weight
    # below ``render_min_weight`` are dropped.
    render_march_steps: int | None = None
    render_early_stop: float = 1e-3
    render_min_weight: float = 1e-4

    def band_half_width(self, depth: Tensor) -> Tensor:
        """Half-width (metres along the ray) of the band around measured ``depth``:
        ``depth_band`` widened by ``depth_band_fraction`` of the depth."""
        return self.depth_band + self.depth_band_fraction * depth

    def __post_init__(self) -> None:
        if self.render_march_steps is not None and self.render_march_steps < 1:
            raise ValueError(
                "sampler.render_march_steps must be at least 1 (or none), got "
                f"{self.render_march_steps}"
            )
        if self.render_band_label_sigma < 0:
            raise ValueError(
                "sampler.render_band_label_sigma must be >= 0 (0 = off), got "
                f"{self.render_band_label_sigma}"
            )
        if self.render_band_label_behind is not None and not self.render_band_label_behind >= 0:
            raise ValueError(
                "sampler.render_band_label_behind must be >= 0 metres (or none), got "
                f"{self.render_band_label_behind}"
            )
        if not 0 <= self.render_surface_label_weight <= 1:
            raise ValueError(
                "sampler.render_surface_label_weight must be in [0, 1], got "
                f"{self.render_surface_label_weight}"
            )
        for name in ("render_early_stop", "render_min_weight"):
            if not 0 <= getattr(self, name) < 1:
                raise ValueError(f"sampler.{name} must be in [0, 1), got {getattr(self, name)}")


SEMANTIC_FORMS: tuple[str, ...] = ("paper", "semantic_nerf")


@dataclass
class LossConfig:
    """Loss weights, docs/method.md "Fuse in 3D"."""

    color: float = 1.0  # L2 on colour
    depth: float = 0.1  # w_d: L1 on depth where the sensor measured it
    semantic: float = 0.04  # w_s: NLL of the normalised rendered class distribution (paper Eq. 3-4)
    # Which semantic loss: "paper" (Eq. 3-4: per-sample softmax composited and normalised,
    # then NLL) or "semantic_nerf" (Semantic-NeRF's original: logits composited with the
    # weights, then softmax cross-entropy; its labels are then the composited logits' argmax).
    # The weights stay detached either way (docs/method.md "Fuse in 3D").
    semantic_form: Literal["paper", "semantic_nerf"] = "paper"
    free_space: float = (
        0.0  # ours (not in the paper): rendering weight in front of the measured surface
    )
    free_space_warmup: float = (
        0.2  # fraction of the steps before the free-space loss starts (ramped in over as many)
    )
    # Ours (1 = off): the free-space term's weight on rays whose pixel borders a nearer
    # surface, a measured depth in its 3x3 neighbourhood more than the band's half-width in
    # front of its own. Those rays pass just beside an edge of that surface, so the term
    # carves the side of whatever stands in front of the wall they measured: the thin parts
    # of furniture (a lamp's pole, a chair's spindles) most of all.
    free_space_edge: float = 1.0
    # Ours (0 = paper): each ray's semantic loss weighs (d / z)^p, z its measured depth (at
    # least 0.3 m; rays without depth weigh 1) and d the training views' median measured
    # depth: with p > 0 views that see a surface from close by get more say in its fused
    # label; with p < 0 far views do (p = -2 weighs each ray by the area its pixel covers, so
    # a view's say in a surface's label no longer grows with how close it stands). In no
    # preset: its measured effect is in docs/deviations.md, the row on the views' depth.
    semantic_depth_power: float = 0.0
    # Ours (0 = paper): in the semantic-head steps, this weight times the NLL of each ray's
    # label under the semantic head evaluated at the ray's measured surface point, beside the
    # composited term (rays without depth have none).
    semantic_surface: float = 0.0
    # Ours: the surface term weighs each ray by one less its band's opacity (detached), so it
    # trains the head where the composited term cannot (a band without weight: a thin part the
    # field renders faintly) and leaves the rest to the composited term.
    semantic_surface_faint_only: bool = False
    # Ours (0 = off): in the semantic-head steps, this weight times each ray's cross-entropy of
    # its label under every band sample's own class distribution, averaged with the samples'
    # normalised rendering weights. The composited terms let the head hold one class at the
    # front of a surface's density and another behind it, so that rays crossing it at
    # different angles render different classes: it learns which views said what, where the
    # voxel map keeps the majority (benchmarks/results/fusion.md "Labels that depend on the
    # view").
    semantic_band_consistency: float = 0.0

    def __post_init__(self) -> None:
        if not 0 <= self.free_space_edge <= 1:
            raise ValueError(f"loss.free_space_edge must be in [0, 1], got {self.free_space_edge}")
        if not isinstance(self.semantic_surface_faint_only, bool):
            raise ValueError(
                "loss.semantic_surface_faint_only must be true or false, "
                f"got {self.semantic_surface_faint_only!r}"
            )
        if self.semantic_form not in SEMANTIC_FORMS:
            raise ValueError(
                f"loss.semantic_form must be one of {', '.join(SEMANTIC_FORMS)}, "
                f"got {self.semantic_form!r}"
            )


@dataclass
class OptimConfig:
    """Adam and the ray batch."""

    # ~5 min at 0.06 s/step on an RTX 3090 (reported cost, docs/method.md "Reference numbers")
    steps: int = 5000
    rays_per_step: int = 4096  # docs/method.md "Reference numbers": 4096 rays per step
    lr: float = 1e-2  # docs/method.md "Reference numbers": Adam lr 1e-2
    betas: tuple[float, float] = (0.9, 0.99)  # docs/method.md "Reference numbers"
    eps: float = 1e-15  # docs/method.md "Reference numbers"
    final_lr_fraction: float = 0.1  # exponential decay to this fraction of lr at the last step
    weight_decay_mlp: float = 1e-6  # small L2 on MLP weights (Instant-NGP)
    # Ours (0 = paper): after the joint fit, steps on the semantic head alone (geometry frozen,
    # samples placed the way labels are rendered), ``semantic_rays_per_step`` rays each,
    # starting at ``lr * semantic_lr_fraction`` (and decaying to
    # ``semantic_final_lr_fraction`` of it). A semantic step costs a fraction of a full one,
    # so the labels of every pixel are seen several times (benchmarks/results/speed.md, "Label
    # fusion speed and quality").
    semantic_steps: int = 0
    semantic_rays_per_step: int = 4096
    semantic_lr_fraction: float = 1.0
    # Ours (1.0 = a constant rate): the semantic-head steps' rate decays exponentially to this
    # fraction of their first one at the last step. Adam moves a hash entry by about its rate
    # whenever a ray reaches it, so at a constant rate a rarely reached entry holds its last
    # few rays' labels rather than all of them.
    semantic_final_lr_fraction: float = 1.0
    # Ours (True = paper): whether the fit's steps train the semantic head too. False leaves
    # the head at its initialisation until the semantic steps above, which then learn the
    # labels through the finished geometry's rendering weights instead of the forming ones
    # (and the fit's steps skip the semantic MLP). Needs ``semantic_steps > 0`` when labels
    # are fitted.
    semantics_in_fit: bool = True
    # Where a step's rays come from: "all" (ours) draws pixels from every training view at
    # once; "per_view" draws the whole batch from one view, the views in a fresh random
    # order each epoch (the official code's batches; the ``paper`` adaptation preset);
    # "class_balanced" (ours, experimental) draws from every view, rare labels more often,
    # each ray's losses weighted back by its draw probability (``RayBank.balanced_ids``).
    ray_batches: Literal["all", "per_view", "class_balanced"] = "all"
    # How the semantic-head steps (``semantic_steps`` above, and joint training's rounds)
    # draw their rays: None follows ``ray_batches`` (label-stratified when it is
    # "class_balanced", else uniformly from every view); "all" or "class_balanced" sets them
    # apart from the fit's, e.g. uniform geometry steps with label-stratified semantic ones.
    semantic_ray_batches: Literal["all", "class_balanced"] | None = None


def scaled_semantic_steps(optim: OptimConfig, steps: int | None) -> int:
    """The semantic-head steps after a fit of ``steps`` steps: ``optim.semantic_steps`` when
    ``steps`` is None or the config's own count, else scaled with the fit's length (rounded
    up), so a shortened fit (``--steps``) keeps its share of semantic steps. The one rule for
    ``fit_semantic_nerf(steps=...)`` and ``csa nerf fit --steps``."""
    if steps is None or optim.semantic_steps <= 0:
        return optim.semantic_steps
    return math.ceil(optim.semantic_steps * int(steps) / max(1, optim.steps))


@dataclass
class NerfConfig:
    """Everything that defines a fit; stored in every checkpoint."""

    preset: str = "reference"
    field: FieldConfig = _field(default_factory=FieldConfig)
    sampler: SamplerConfig = _field(default_factory=SamplerConfig)
    loss: LossConfig = _field(default_factory=LossConfig)
    optim: OptimConfig = _field(default_factory=OptimConfig)
    storage_dtype: Literal["float32", "float16"] = "float32"  # checkpoint tensors
    # Ours (NeRF-W / nerfacto idea, not in the paper): "affine" = a per-training-frame colour
    # gain and bias that absorbs auto exposure and white balance (appearance.py).
    appearance: Literal["none", "affine"] = "none"
    render_chunk: int = 8192  # rays per chunk when rendering
    # Ours: rendered labels are 0 (unknown, as the map answers) where the surface point lies
    # outside every training camera's image or no surface is rendered (render.py). Off: the
    # NeRF's class everywhere (the paper).
    render_unseen_unknown: bool = False
    # Ours: cells for the unseen test (visibility.py): the box cut into this many cells per
    # axis, marked by the fit where a training view's depth measured a surface (and one cell
    # around); 0 = none (the default), the test then uses the training cameras' frusta. 128
    # in ``fast`` (256 KB per checkpoint): benchmarks/results/fusion.md "Unseen surfaces:
    # cells the training depth measured".
    observed_resolution: int = 0
    # Where the hash grid sits (csa_core/nerf/normalization.py). "box" (ours): the scene's
    # box, camera centres and measured depth padded by 10%. "cube" (the paper, the `paper`
    # adaptation preset): the official code's fixed cube, the poses centred on the point the
    # cameras look at and scaled so that they average ``cube_camera_distance`` units from it,
    # the grid spanning [-cube_bound, cube_bound]^3 of those units (docs/presets.md
    # "The paper preset").
    normalization: Literal["box", "cube"] = "box"
    cube_bound: float = 4.0
    cube_camera_distance: float = 1.32
    seed: int = 0

    def __post_init__(self) -> None:
        if self.normalization not in ("box", "cube"):
            raise ValueError(f"normalization must be 'box' or 'cube', got {self.normalization!r}")
        for name in ("cube_bound", "cube_camera_distance"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and 0 < value < math.inf):
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
        if not (isinstance(self.observed_resolution, int) and 0 <= self.observed_resolution <= 512):
            raise ValueError(
                "observed_resolution must be an integer in [0, 512], got "
                f"{self.observed_resolution!r}"
            )

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> NerfConfig:
        d = copy.deepcopy(d)
        enc = HashEncodingConfig(**d["field"].pop("encoding"))
        optim = d.pop("optim")
        optim["betas"] = tuple(optim["betas"])
        return cls(
            preset=d["preset"],
            field=FieldConfig(encoding=enc, **d["field"]),
            sampler=SamplerConfig(**d["sampler"]),
            loss=LossConfig(**d["loss"]),
            optim=OptimConfig(**optim),
            storage_dtype=d["storage_dtype"],
            appearance=d.get("appearance", "none"),
            render_chunk=d["render_chunk"],
            render_unseen_unknown=d.get("render_unseen_unknown", False),
            # Checkpoints written before the cells existed have none.
            observed_resolution=d.get("observed_resolution", 0),
            # Checkpoints written before the fixed cube existed used the scene's box.
            normalization=d.get("normalization", "box"),
            cube_bound=d.get("cube_bound", 4.0),
            cube_camera_distance=d.get("cube_camera_distance", 1.32),
            seed=d["seed"],
        )


def _reference() -> NerfConfig:
    return NerfConfig(preset="reference")


def _fast() -> NerfConfig:
    """CPU-friendly: 2^15 table (fp16 checkpoint with the semantic table ~3.5 MB), depth-guided
    training samples with a free-space loss, occupancy-grid rendering, fewer rays per step.

    For label fusion: label-balanced ray draws (rare classes get their geometry and labels
    fitted within the budget) and then 300 semantic-head steps of 8192 rays from a tenth of the
    rate decaying to 5% of it (about two thirds of a pass over every training pixel's label at
    200 views of 160x120, on the finished geometry), with Semantic-NeRF's semantic loss
    (composited logits). Measured against the voxel map on every synthetic family, clean and
    hard, and the real 7-Scenes kitchen:
    benchmarks/results/fusion.md "The `fast` preset for label fusion". The adaptation budgets
    (``csa_core.adapt.config``) set their own draws and semantic steps."""
    return NerfConfig(
        preset="fast",
        # A finest level of 512 cells, not 1024, and the semantic table on all 16 levels, not
        # 12: in a 2^15 table the finest levels of a furnished room collide so often that chairs
        # and lamps were lost (benchmarks/results/fusion.md "Thin furniture: a coarser finest
        # level").
        field=FieldConfig(
            encoding=HashEncodingConfig(log2_table_size=15, finest_resolution=512),
            semantic_grid_levels=16,
        ),
        sampler=SamplerConfig(
            train="depth",
            render="occupancy",
            render_depth_guided=True,
            render_band_color=True,
            # 6, not 8: labels within 0.2 mIoU, renders in 65-80% of the time; the semantic
            # steps keep the fit's 8 (benchmarks/results/speed.md, "Fewer band samples and one
            # corner layout").
            render_band_samples=6,
            # Labels of a view with depth from the band no further than 5 cm behind the
            # measured surface, a quarter of them from the semantic head at that surface point:
            # the head held classes behind surfaces that only some views' rays reach
            # (benchmarks/results/fusion.md "Labels that depend on the view").
            render_band_label_behind=0.05,
            render_surface_label_weight=0.25,
            # Views without depth march twice the grid's step, stop at transmittance 1/100 and
            # drop samples of weight below 1/1000: within 0.1 mIoU and 0.1 dB of the march at
            # the grid's step, in under half its time, 0.64-0.74 s per novel view on three
            # rooms (benchmarks/results/speed.md, "A cheaper march for novel views").
            render_march_steps=256,
            render_early_stop=1e-2,
            render_min_weight=1e-3,
            uniform_samples=64,
            importance_samples=64,
        ),
        optim=OptimConfig(
            steps=1500,
            rays_per_step=1024,
            ray_batches="class_balanced",
            semantic_steps=300,
            semantic_rays_per_step=8192,
            semantic_lr_fraction=0.1,
            # Decaying to 5% of their rate, and Semantic-NeRF's loss below: the flat panels
            # of a wall (windows, mirrors) and thin furniture kept on every family
            # (benchmarks/results/fusion.md "Semantic-NeRF's loss and a decaying rate").
            semantic_final_lr_fraction=0.05,
        ),
        loss=LossConfig(free_space=1.0, semantic_surface=1.0, semantic_form="semantic_nerf"),
        storage_dtype="float16",
        # Labels 0, unknown, where a view's measured surface lies in no cell a training view
        # measured, as the map abstains there: on walks whose last views look at surfaces
        # the first ones never measured, the field's guesses there were false positives
        # (benchmarks/results/fusion.md "Unseen surfaces: cells the training depth measured").
        render_unseen_unknown=True,
        observed_resolution=128,
    )


PRESETS = {"reference": _reference, "fast": _fast}


def preset(name: str) -> NerfConfig:
    """A fresh config of the preset ``name`` (``reference`` or ``fast``)."""
    try:
        return PRESETS[name]()
    except KeyError:
        raise ValueError(
            f"unknown NeRF preset {name!r} (choose from {', '.join(PRESETS)})"
        ) from None


def build_config(name: str, overrides: Iterable[str] = (), flag: str = "--set") -> NerfConfig:
    """The NeRF config of preset ``name`` with ``overrides``, ``section.name=value`` items
    (``optim.steps=300``, ``field.encoding.log2_table_size=14``), applied in order through
    the one override path (:func:`csa_core.overrides.apply_overrides`; an error names ``flag``
    and the item).

    Every NeRF config made from a preset name and changes to it is made here: ``csa nerf fit``
    (its flags as items, then ``--set``), the adaptation budgets
    (``csa_core.adapt.config.nerf_config``: the budget's schedule, then its items)."""
    return apply_overrides(preset(name), overrides, flag=flag)
