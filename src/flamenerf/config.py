"""Typed configuration and the named presets.

Every preset is the same model code with different values: `flame-in-nerf` holds the
paper's numbers, `nerfies` drops the expression input, `no-prior` feeds the expression to
every sample point, and `fast` keeps the paper's conditioning, prior and regularisation
but swaps the costly parts for ones that train in minutes on a CPU (see docs/presets.md).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import types
import typing
from dataclasses import dataclass
from dataclasses import field as _field
from typing import Any, Literal

from flamenerf.errors import UserError

ExpressionMode = Literal["masked", "none", "everywhere"]


@dataclass
class WarpConfig:
    """Nerfies SE(3) deformation field D(x; ω)."""

    enabled: bool = True
    """Use a deformation field at all (off = static NeRF, for debugging)."""
    code_dim: int = 128
    """Per-frame deformation code ω_i dimension (paper: 128)."""
    width: int = 128
    depth: int = 6
    skips: tuple[int, ...] = (4,)
    num_freqs: int = 8
    """Positional-encoding frequencies of x, annealed coarse-to-fine."""
    anneal_fraction: float = 1 / 3
    """The c2f window opens every frequency band after this fraction of the run (the paper:
    50k of 150k steps), so `--steps` shortens or lengthens it with the run."""
    init_scale: float = 1e-4
    """Output layers start near zero so the warp starts as the identity (as in Nerfies)."""
    expression_input: bool = False
    """Also condition the warp on the masked expression 𝕀β (next to ω): the face's motion
    becomes a smooth function of β that a commanded β reproduces. Off in the paper."""
    head_only: bool | None = None
    """Where the model follows a moving head (datasets with head poses): the deformation
    acts only in the head's region, fading out over `band` beyond the head's ellipsoid, so
    the background is static in the world and registers without a per-frame code; False:
    everywhere, as without head poses (the per-frame codes then also move the room, and
    a re-animation with frame 0's code sees it moved as in frame 0). None: settled to True
    when a run starts; runs from before this option load as they trained (everywhere)."""
    still_head_only: bool = False
    """Datasets without head poses (the built-in scene without --head-motion): the
    deformation acts only in the head's region too (the ellipsoid of `head_only`, fading
    out over `band`), so the room's samples skip it (on in `fast`). Off: everywhere, as in
    the paper. A dataset with head poses trained with `model.head.follow` off keeps the
    warp everywhere (its head moves through the world)."""
    band: float | None = None
    """With `head_only`: the width of the deformation's fade beyond the head's ellipsoid, as
    a fraction of its radius. Narrower than the head's band, it keeps per-frame codes off
    the hair and shoulders that the head's motion blends. None: settled to 0.15 when a run
    starts; a run from before this option loads with the head's band, as it trained."""

    def settle(self) -> None:
        """The defaults a new run trains with (None stays None in a loaded old run's config,
        meaning what it trained with: see `head_only` and `band`)."""
        if self.head_only is None:
            self.head_only = True
        if self.band is None:
            self.band = 0.15


@dataclass
class FieldConfig:
    """Canonical radiance field F(γ(D(x)), γ(d), φ, 𝕀(x)β)."""

    kind: Literal["mlp", "hash"] = "mlp"
    """`mlp`: the paper's 8x256 NeRF MLP; `hash`: a multiresolution hash grid + tiny MLPs."""
    width: int = 256
    depth: int = 8
    skips: tuple[int, ...] = (4,)
    pos_freqs: int = 10
    dir_freqs: int = 4
    view_dependent: bool = True
    """Whether colour sees the viewing direction γ(d) (the paper: yes)."""
    appearance_dim: int = 8
    """Per-frame appearance code φ_i dimension (paper: 8)."""
    # hash grid only
    hash_levels: int = 16
    hash_features: int = 2
    hash_log2_size: int = 17
    hash_base_res: int = 16
    hash_max_res: int = 1024
    """Finest resolution of the hash grid over the scene box; 0: one cell per training pixel
    at the face (settled per dataset and training size when a run is built:
    `data.scene.face_pixel_resolution`)."""
    head_width: int = 64
    geo_features: int = 15
    expr_rank: int = 0
    """hash only: > 0 adds expression features to the canonical field, Σ_r (Aβ)_r G_r(x'):
    a hash grid G of `expr_rank` feature sets mixed by a learned projection A of 𝕀β (a
    blendshape basis of feature fields). β = 0 adds exactly nothing, so the prior holds."""
    expr_direct: bool = True
    """hash only: β also enters the density head directly (the paper's conditioning). With
    `expr_rank` > 0, False leaves only the spatially local pathway Σ_r (Aβ)_r G_r(x'), so β
    cannot act as one face-wide code."""
    expr_levels: int = 8
    expr_base_res: int = 16
    """Coarsest resolution of the expression grid: a coarse level is one feature for the
    whole face, through which β can act as a face-wide code (a tint) rather than a local
    change."""
    expr_features: int = 2
    expr_log2_size: int = 16
    expr_max_res: int = 512
    detail_levels: int = 0
    """hash only: > 0 adds that many finer levels above `hash_max_res`, up to
    `detail_max_res`, evaluated only in the head's region (data/head_pose.head_region, the
    canonical frame's ellipsoid around the reference face mesh, fading to 0 over
    `detail_band`): the face gets finer cells, the room keeps the grid's (docs/presets.md
    item 7)."""
    detail_max_res: int = 0
    """Finest resolution of the detail levels over the scene box (as `hash_max_res`); 0: two
    cells per training pixel at the face (settled per dataset and training size)."""
    detail_log2_size: int = 19
    detail_band: float = 0.2


@dataclass
class SamplerConfig:
    kind: Literal["hierarchical", "proposal"] = "hierarchical"
    """`hierarchical`: coarse + fine networks (NeRF); `proposal`: a tiny density-only hash
    field proposes where the main field samples (mip-NeRF 360)."""
    num_coarse: int = 64
    num_fine: int = 64
    fine_reuses_coarse: bool = True
    """The fine network also re-evaluates the coarse samples (NeRF's 64+64=128)."""
    num_proposal: int = 64
    """proposal: uniform samples of the proposal field per ray."""
    num_main: int = 24
    """proposal: samples of the main field per ray, drawn from the proposal's weights."""
    refine_main: int = 128
    """proposal, outside training: a ray that its `num_main` samples leave unfinished
    (accumulated opacity below 1 − `refine_below`) while the proposal's weights say it ends
    (`unfinished`) is rendered again with this many samples from the same proposal weights;
    0: never. The proposal learns only where training rays went, so at a new camera it can
    leave out a surface that the main field holds: on the built-in scene a crack of wall
    beside the cheek, which the main field fills when sampled more densely. Chosen on the
    built-in scene's four `fast` seeds (re-animation face +0.04 to +0.25 dB, the Nerfies
    variant's within 0.03; the margin between them over +3 dB on every seed), reported on
    a second scene (+0.36); a 256 px frame at the re-animation's cameras a few per cent
    longer on a CPU (docs/decisions/second-pass-unfinished-rays.md). The reference
    forward draws the second pass's proposal samples afresh: the same weights without
    jitter (eval, render), new ones in the held-out fit's jittered batches."""
    refine_below: float = 0.05
    proposal_levels: int = 6
    proposal_log2_size: int = 15
    proposal_max_res: int = 256
    proposal_width: int = 16

    def unfinished(self, acc, proposal_acc):
        """The rays that the second pass (`refine_main`) renders again: those that the
        proposal's weights say end (its opacity proposal_acc (R,) at least 1 −
        `refine_below`) and that the main samples leave unfinished (acc (R,) below it).
        Rays the proposal sees through too (open scenes, an untrained model) keep their
        one pass. -> their indices (n,) long."""
        end = 1.0 - self.refine_below
        return ((acc < end) & (proposal_acc >= end)).nonzero()[:, 0]


@dataclass
class MeshGuideConfig:
    """Mesh-guided deformation (as in RigNeRF): points near the face are carried from the
    mesh of the ray's expression 𝕀β to the neutral mesh before the learned warp, so the
    face's motion is a function of β that any commanded β reproduces. The mesh of a β comes
    from a per-subject linear model fitted on the training frames' tracked meshes."""

    enabled: bool | None = False
    """None: on where the face parts are known (`face_parts` with ARKit names on a mesh
    whose eyes and mouth are known: tracked clips, the built-in scene), off elsewhere;
    settled per dataset when a run is built. On the shared expressions clip it raised the
    controls' mean re-tracked gain with companions from 0.30 to 0.41 (two trainings each)
    at no cost in PSNR. On the built-in scene, once its β -> mesh fit had face parts
    (2026-11-26), it made the jaw follow (sweep gain 0.17-0.24 -> 0.27-0.32, ground truth
    0.30; a real person driving it: jawOpen correlation 0.26 -> 0.75-0.91) at 0.4-0.8 dB of
    re-animation face PSNR and ~15 % more training time (three seeds;
    docs/decisions/mesh-guide.md)."""
    falloff: float = 0.15
    """Distance (fraction of the neutral mesh's bounding-box diagonal) over which the motion
    fades out away from the mesh."""
    neighbours: int = 4
    max_residual: float | None = None
    """Vertices that the β -> mesh model misses by more than this (RMS over the training
    frames' tracked meshes, world units: metres on tracked clips and the built-in scene) do
    not guide; None: all do. `fast` uses 0.0015: on the built-in scene three lip-line
    vertices are missed by 4.5 mm (its lips slide into the open mouth, not linear in β) and
    carried the canonical mouth to the wrong place; leaving them out raised re-animation face
    PSNR on all four seeds (+0.26 to +0.69 dB) with the jaw still following a real driver
    (jawOpen correlation 0.83-0.89). On the expressions clip it leaves out 29 outline and
    forehead vertices that the tracker places unsteadily (1.5-2.3 mm; controls passing
    11 / 12 -> 12 / 13 of 27, PSNR within noise, seeds 0 / 1), on the orbit clip none
    (docs/decisions/mesh-guide.md)."""
    ridge: float = 1e-3
    """Ridge of the β -> mesh least-squares fit (relative to the mean squared control)."""
    face_parts: bool = True
    """Fit the β -> mesh model with each ARKit-named control limited to its part of the
    face (brows, eyes, mid face, lower face) where the mesh's eyes and mouth are known
    (MediaPipe's meshes, the built-in scene's): a tracker's scores co-vary, and a free fit
    let brow controls open the jaw; on the built-in mesh it gave the lips' non-linear motion
    to the blinks, and a commanded blink opened the mouth (data/face_parts.py). Used by
    every preset that fits the model (per-control prior, mesh guide, driven silhouettes)."""

    generic_shapes: bool = False
    """Eye and brow controls that the training frames leave still (largest value under 0.1:
    a subject who never blinks on camera) take a generic shape in the β -> mesh model (the
    upper lid shut onto the lower one, the brows raised or lowered, in the face's own
    proportions; data/generic_shapes.py) and act through the mesh guide alone, where the
    fitted model gives them nothing and a commanded blink did nothing. Needs the mesh guide
    and the per-control regions. `fast`: on (docs/decisions/generic-shapes.md)."""
    stored: bool = True
    """Use the β -> mesh model a dataset carries (`preprocess --consistent-expressions` fits
    one that reads back through the tracker as each control commanded alone:
    tracking/expression_model.py) where it was fitted with this `ridge` and the face parts;
    False, or a dataset without one: the least-squares fit, made when the run is built."""

    def resolved_enabled(self, face_parts: bool) -> bool:
        return face_parts if self.enabled is None else bool(self.enabled)


RADIUS_PARTS, RADIUS_FREE = 0.1, 0.05
"""The per-control prior's default fade radius with and without the face parts."""


@dataclass
class ExpressionRegionsConfig:
    """Per-control spatial prior: β_k reaches only points near the part of the face mesh
    that control k moves (from the per-subject β -> mesh model fitted on the training
    frames). A refinement of the silhouette prior inside the face: a rarely used control
    (a blink in a few frames) cannot become a face-wide code for those frames."""

    enabled: bool = False
    threshold: float = 0.2
    """A vertex belongs to control k's region when k moves it by more than this fraction of
    k's largest vertex motion."""
    radius: float | None = None
    """Distance (fraction of the neutral mesh's bounding-box diagonal) at which a point's
    share of β_k has faded to 1/e away from the region's vertices. None: `RADIUS_PARTS` where
    the face parts limit the controls (`mesh_guide.face_parts` on MediaPipe meshes, whose
    part-limited regions need the wider fade), else `RADIUS_FREE`; a run's config.json holds
    the value it trained with. Each was measured on one dataset only: 0.1 on the shared
    expressions clip, 0.05 on the built-in scene, where 0.1 lowered the control gain
    (docs/decisions/expression-fields.md)."""

    def resolved_radius(self, face_parts: bool) -> float:
        if self.radius is not None:
            return self.radius
        return RADIUS_PARTS if face_parts else RADIUS_FREE


@dataclass
class HeadConfig:
    """Following a moving head (datasets with per-frame `head_pose`; docs/head_pose.md):
    points in the head's region are taken into the head's canonical frame by the frame's
    rigid pose before the deformation field; the background stays in the world."""

    follow: bool = True
    """Use the dataset's head poses (off: treat the head as part of the static world)."""
    region_scale: float = 1.0
    """Grows the head's ellipsoid (fitted around frame 0's face mesh) about its centre."""
    band: float = 0.6
    """Width of the blend from head motion to the static world, as a fraction of the
    ellipsoid's radius: full head motion inside, none beyond 1 + band (0.6 with the
    deformation's narrower `warp.band`: both real clips re-animate better than with 0.35,
    the built-in scene ~0.2 dB worse; docs/head_pose.md)."""


@dataclass
class ModelConfig:
    expression_mode: ExpressionMode = "masked"
    """`masked`: β only on rays through the face silhouette (the paper's spatial prior);
    `none`: no β input (Nerfies); `everywhere`: β for every point (no-prior ablation)."""
    warp: WarpConfig = _field(default_factory=WarpConfig)
    field: FieldConfig = _field(default_factory=FieldConfig)
    sampler: SamplerConfig = _field(default_factory=SamplerConfig)
    expression_scale: float = 1.0
    """β is multiplied by this before it enters the field (keeps β and PE on one scale)."""
    expression_centre: bool = False
    """β enters the networks as β − β̄, β̄ the training frames' mean (stored with the run):
    the fields without β then hold the average face and β only how a frame differs from it.
    Scores such as MediaPipe's blendshapes are never negative, so with raw β the expression
    pathway can also carry part of the constant face (the reason it was tried; measured:
    docs/presets.md item 5). The masks, meshes and the meaning of every β a user gives stay
    as before."""
    mesh_guide: MeshGuideConfig = _field(default_factory=MeshGuideConfig)
    expression_regions: ExpressionRegionsConfig = _field(
        default_factory=ExpressionRegionsConfig)
    head: HeadConfig = _field(default_factory=HeadConfig)


@dataclass
class TrainConfig:
    steps: int = 150_000
    batch_rays: int = 1024
    """Rays per step, over all processes of a distributed run (docs/distributed.md)."""
    accumulate: int = 1
    """Split each process's share of the step's rays into this many micro-batches, computed
    one after another with their gradients summed (gradient accumulation): the same step in
    less memory. A run on N processes draws exactly the rays of one process with
    `accumulate=N` (training/distributed.py)."""
    lr: float = 1e-3
    lr_final: float = 5e-4
    """Adam's learning rate decays exponentially from `lr` to `lr_final` (paper: 1e-3→5e-4)."""
    lr_warmup: int = 0
    warp_lr_scale: float = 1.0
    """The deformation MLP learns at `lr * warp_lr_scale`: at the hash grid's 1e-2 its
    ReLU units die within a few hundred steps and the warp becomes a constant identity."""
    appearance_lr_scale: float = 1.0
    """The appearance codes φ_i learn at `lr * appearance_lr_scale`: fast, they soak up
    per-frame residuals that the held-out protocol (which uses φ_0) cannot reproduce."""
    deform_code_lr_scale: float = 1.0
    """The deformation codes ω_i learn at `lr * deform_code_lr_scale` (1: with the field;
    a re-animation has only ω_0, so what the other codes learn it cannot show)."""
    face_reg_weight: float = 1.0
    """Weight of ‖D(x_3DMM; ω_i) − x_3DMM‖ (paper's runs: 0.1 to 10)."""
    face_reg_points: int = 1024
    face_ray_fraction: float = 0.0
    """Share of each batch's rays drawn from pixels inside the face silhouettes (0: all
    uniform over the image)."""
    interlevel_weight: float = 1.0
    """Weight of the proposal sampler's interlevel loss."""
    random_background: bool = False
    """Composite each training ray over a random colour instead of black, so that a
    half-transparent room cannot pass for an opaque one in the captured views (it then
    renders as fog from new ones; instant-ngp trains its synthetic scenes so)."""
    face_depth_weight: float = 0.0
    """Weight of the face-depth prior (model/losses.py `face_depth_loss`): on rays
    through the tracked face mesh, rendering weight further than `face_depth_margin` from
    the mesh's surface is penalised (0: off, as in the paper)."""
    face_depth_margin: float = 0.01
    """Scene units (metres in a preprocessed or built-in dataset) around the mesh's surface
    that the face-depth prior leaves free: a tracked mesh is not the exact surface."""
    face_depth_start: float = 0.0
    """Share of the training steps after which the face-depth prior acts (it pulls density
    down along whole rays, which early in training thins the background too)."""
    moving_weight: float = 0.1
    """Weight in the photometric loss of pixels that the dataset marks as background moving
    by itself (`moving_path`: leaves, water, passers-by; 1: as any other pixel, 0: left
    out); such pixels feed no depth prior either. Datasets without the masks train as
    before (docs/decisions/moving-background.md)."""
    bf16: bool = False
    """Train the MLPs' layers in bfloat16 (float32 weights, outputs and everything else: the
    hash grids, compositing, losses) where that pays: a new run on a CPU settles this to
    `model.mlp.bf16_pays()` (native AVX-512 BF16 or AMX, and measured faster than float32
    there) and stores the answer in its config.json, so resuming keeps it; on a GPU it is
    settled to False."""
    checkpoint_every: int = 5000
    keep_checkpoints: int = 2
    log_every: int = 50
    image_every: int = 5000
    downscale: float = 1.0
    """Train at 1/downscale of the dataset resolution."""
    seed: int = 0
    num_threads: int = 0
    """CPU threads for torch (0 = torch's default)."""

    @property
    def render_background(self) -> float:
        """The colour (grey level) behind the scene when rendering: what the rest of a ray
        that leaves the scene unfinished was trained against, on average. Over random
        colours (uniform in [0, 1]) their mean, 0.5, is the squared-error-optimal guess;
        over black, black. At a new camera such rays lie mostly next to the outline of the
        head and body and at the image's border; rendered over black they were dark seams."""
        return 0.5 if self.random_background else 0.0


@dataclass
class Config:
    preset: str = "flame-in-nerf"
    model: ModelConfig = _field(default_factory=ModelConfig)
    train: TrainConfig = _field(default_factory=TrainConfig)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def _paper() -> Config:
    return Config(preset="flame-in-nerf")


def _nerfies() -> Config:
    cfg = _paper()
    cfg.preset = "nerfies"
    cfg.model.expression_mode = "none"
    return cfg


def _no_prior() -> Config:
    cfg = _paper()
    cfg.preset = "no-prior"
    cfg.model.expression_mode = "everywhere"
    return cfg


def _fast() -> Config:
    cfg = Config(preset="fast")
    # without head poses (the built-in scene) the warp too acts in the head's region only:
    # the room's samples skip it, a step is ~28 % shorter on the CPU, and four seeds score
    # as with the warp everywhere (docs/presets.md)
    cfg.model.warp = WarpConfig(code_dim=16, width=64, depth=4, skips=(), num_freqs=6,
                                anneal_fraction=0.5, still_head_only=True)
    # finer cells at the head only: four levels above 512, to two cells per training pixel
    # at the face (settled per dataset, ~1900 at 128 px), evaluated in the head's region
    # (docs/presets.md item 7)
    cfg.model.field = FieldConfig(kind="hash", appearance_dim=8, dir_freqs=4, hash_levels=12,
                                  hash_log2_size=19, hash_max_res=512, detail_levels=4)
    # β acts through local feature fields only, each control near the part of the face mesh
    # it moves: through the density head's input β became a face-wide code of the few
    # frames that show a control (docs/decisions/expression-fields.md)
    cfg.model.field.expr_rank, cfg.model.field.expr_direct = 8, False
    cfg.model.expression_regions.enabled = True
    cfg.model.expression_centre = True
    # the mesh-guided deformation wherever the face parts are known (tracked clips, the
    # built-in scene): the jaw follows β, not only the face's colours
    # (docs/decisions/mesh-guide.md)
    cfg.model.mesh_guide.enabled = None
    # ... less the vertices the linear β -> mesh model cannot follow (the built-in lips)
    cfg.model.mesh_guide.max_residual = 0.0015
    # ... and generic shapes for the eye and brow controls the clip never moves
    # (docs/decisions/generic-shapes.md)
    cfg.model.mesh_guide.generic_shapes = True
    cfg.model.sampler = SamplerConfig(kind="proposal", num_proposal=48, num_main=32,
                                      proposal_levels=5, proposal_max_res=128)
    # the per-frame deformation codes at a tenth of the learning rate: extra steps then
    # sharpen the face a re-animation shows instead of what each frame's codes fit (at full
    # rate a real clip's driven face fell 0.9 dB). 1800 steps of 2048 rays, the rays of 900
    # of 4096 in twice the updates: a sharper face and a blink that starts to form on both
    # built-in scenes measured (the margin over the Nerfies variant rose on the scene it was
    # chosen on, +2.8 to +3.1 dB on four seeds against +2.3 to +2.6, not on a second one);
    # ~8.5 minutes on the 2-core CPU (491-548 s alone; docs/presets.md item 3)
    # the face-depth prior from a fifth of the run on: without it the face trains as a fog
    # centred ~3 cm behind its surface, which new cameras see wrongly (docs/presets.md)
    # rays over a random colour: over black, a half-transparent room with fog in front of it
    # passed for the captured views in some trainings and not for new ones (item 7)
    # 30 % of the rays from the face silhouettes: uniform rays otherwise leave the face's small
    # saturated parts (lips, irises) and the mouth's shapes pale and soft (item 8)
    # the MLPs in bfloat16 on CPUs where that pays (settled per run): a training 11 %
    # shorter on a Zen 4, four seeds scoring as in float32 (docs/presets.md)
    cfg.train = TrainConfig(steps=1800, batch_rays=2048, lr=1e-2, lr_final=1e-3,
                            lr_warmup=50, warp_lr_scale=0.1, appearance_lr_scale=0.01,
                            deform_code_lr_scale=0.1,
                            face_depth_weight=0.01, face_depth_start=0.2,
                            random_background=True, face_ray_fraction=0.3, bf16=True,
                            checkpoint_every=200,
                            image_every=200, log_every=20)
    return cfg


def _fast_gpu() -> Config:
    cfg = _fast()
    cfg.preset = "fast-gpu"
    # on a GPU a `fast` step is bound by kernel launches, not by the rays: on an H100 a
    # step of 16384 rays took 75 ms against 83 ms for 4096. 800 such steps: 31.7 / 32.0 dB
    # held-out at 256 px (seeds 0 / 1, all 30 val frames) in 43 / 46 s before `fast`'s
    # changes of 2026-11-25/26 (docs/bench/gpu_train_fast_gpu.json); with them (mesh guide,
    # slower per-frame codes), on an H200: 30.3 / 29.2 dB in 51 s
    # (docs/bench/gpu_h200_20261126.json); with the guide's vertex cut too, on an H100:
    # 29.5 / 30.5 dB in 60 / 58 s. 32768 rays per step: 1.7x the step time, worse within
    # the minute (docs/bench/gpu_h100_20261126.json)
    cfg.train.steps, cfg.train.batch_rays = 800, 16384
    # measured on GPUs with the warp everywhere (its figures above); selecting the head's
    # samples pays on a CPU and was not timed on a GPU, whose step is launch-bound
    cfg.model.warp.still_head_only = False
    # the per-frame codes at `fast`'s tenth of the rate were where the pre-guide figures'
    # ~2 dB went: at the full rate, trained on this CPU at 256 px (800 steps of 16384 rays),
    # the 6-frame held-out curve reads 31.76 dB at step 800 against 29.95 (seed 0), and the
    # re-animation against ground truth 24.85 / face 29.40 dB against 24.45 / 29.24, the
    # control gain 0.161 against 0.142 (docs/presets.md, "`fast-gpu` on this CPU")
    cfg.train.deform_code_lr_scale = 1.0
    return cfg


def _demo() -> Config:
    cfg = _fast()
    cfg.preset = "demo"
    # `flamenerf demo`: a few CPU minutes at 64 px; c2f over the first 40 % of the run
    cfg.model.warp.anneal_fraction = 0.4
    cfg.train.steps, cfg.train.batch_rays = 300, 2048
    return cfg


PRESETS: dict[str, tuple[str, Any]] = {
    "flame-in-nerf": ("the paper: SE(3) warp 6x128, NeRF 8x256, 64+64 samples, 150k steps",
                      _paper),
    "nerfies": ("Nerfies baseline: as flame-in-nerf without the expression input", _nerfies),
    "no-prior": ("ablation: as flame-in-nerf with β reaching every sample point", _no_prior),
    "fast": ("CPU-friendly: hash-grid field, proposal sampler, small warp", _fast),
    "fast-gpu": ("fast for a GPU: 800 steps of 16384 rays, the per-frame codes at full "
                 "rate (~51 s on an H200)", _fast_gpu),
    "demo": ("`flamenerf demo`'s: fast, 300 steps of 2048 rays", _demo),
}


def preset(name: str) -> Config:
    if name not in PRESETS:
        raise UserError(f"unknown preset {name!r} (choose from {', '.join(PRESETS)})")
    return PRESETS[name][1]()


def override(cfg: Config, values: dict[str, Any]) -> Config:
    """Set dotted fields of `cfg` in place (`{"train.batch_rays": 2048}`); None values are
    skipped, so a command can pass its optional flags as they are. Strings given for
    numeric or boolean fields are converted ("true"/"1"/"yes" for booleans). -> cfg."""
    for key, val in values.items():
        if val is None:
            continue
        obj, parts = cfg, key.split(".")
        try:
            for p in parts[:-1]:
                obj = getattr(obj, p)
            old = getattr(obj, parts[-1])
        except AttributeError:
            raise UserError(f"{key}: no such configuration field") from None
        if isinstance(val, str) and old is None:  # an optional field left to its default
            val = _optional_value(val)
        elif isinstance(val, str) and not isinstance(old, str):
            val = (val.lower() in ("1", "true", "yes") if isinstance(old, bool)
                   else type(old)(float(val)))
        setattr(obj, parts[-1], val)
    return cfg


def _optional_value(val: str) -> float | bool | str | None:
    low = val.lower()
    if low in ("none", "true", "false"):
        return {"none": None, "true": True, "false": False}[low]
    try:
        return float(val)
    except ValueError:
        return val


def parse_overrides(text: str) -> dict[str, str]:
    """`key=value,key=value` (dotted fields, as `override` takes them) -> a dict of strings;
    the benchmarks' variant specs (`name:key=value,...`)."""
    out = {}
    for item in filter(None, (t.strip() for t in text.split(","))):
        key, eq, val = item.partition("=")
        if not eq or not key:
            raise UserError(f"{item!r}: not key=value")
        out[key.strip()] = val.strip()
    return out


def parse_variants(text: str) -> list[tuple[str, dict[str, str]]]:
    """The benchmarks' `--variants`: `name` or `name:key=value,...`, separated by ';' (or by
    ',' when no variant has overrides) -> [(name, overrides)] in order."""
    # "a:x=1,y=2" is one variant with two overrides, not a variant named "y=2"
    specs = text.split(";") if ";" in text or ":" in text else text.split(",")
    out = []
    for spec in filter(None, (s.strip() for s in specs)):
        name, _, sets = spec.partition(":")
        out.append((name.strip(), parse_overrides(sets)))
    return out


def from_dict(d: dict[str, Any], source: str | os.PathLike = "config") -> Config:
    """Inverse of Config.to_dict; unknown keys are ignored so old runs stay loadable. Each
    value is checked against its field's annotation and `check_ranges`: a run's config.json
    is a file people edit and copy, and a wrong value otherwise surfaced as a traceback deep
    in the model (or, for a Literal, silently trained another variant). A one-line
    UserError naming `source` (the file) and the key otherwise."""
    try:
        cfg = _build(Config, d, "")
        _check_ranges(cfg)
    except _BadValue as e:
        raise UserError(f"{source}: {e}") from None
    if cfg.preset not in PRESETS:  # the label reports and resumes carry
        raise UserError(f"{source}: preset {_shown(cfg.preset)} is not one of this "
                        f"flamenerf's ({', '.join(PRESETS)})")
    return cfg


class _BadValue(ValueError):
    """A value of the wrong type or range; the message starts with its key path."""


def _build(cls: type, values: Any, key: str) -> Any:
    if not isinstance(values, dict):
        raise _BadValue(f"{key or 'the configuration'} must be an object, got "
                        f"{_shown(values)}")
    hints = typing.get_type_hints(cls)  # resolves the annotations' strings (__future__)
    kwargs = {f.name: _value(values[f.name], hints[f.name], _key(key, f.name))
              for f in dataclasses.fields(cls) if f.name in values}
    return cls(**kwargs)


def _value(v: Any, hint: Any, key: str) -> Any:
    """`v` as the annotation `hint` takes it (JSON lists become tuples, ints floats), or
    _BadValue."""
    if dataclasses.is_dataclass(hint):
        return _build(hint, v, key)
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if v is None and type(None) in args:
            return None
        for arg in (a for a in args if a is not type(None)):
            try:
                return _value(v, arg, key)
            except _BadValue:
                continue
    elif origin is Literal:
        if isinstance(v, str) and v in args:
            return v
    elif origin in (tuple, list) and isinstance(v, (list, tuple)):
        if origin is list or (len(args) == 2 and args[1] is Ellipsis):
            items = [_value(x, args[0], f"{key}[{i}]") for i, x in enumerate(v)]
        elif len(v) == len(args):
            items = [_value(x, a, f"{key}[{i}]") for i, (x, a) in enumerate(zip(v, args))]
        else:
            items = None
        if items is not None:
            return tuple(items) if origin is tuple else items
    elif hint is Any:
        return v
    elif hint is float and is_number(v):
        return float(v)
    elif hint is int and is_int(v):
        return v
    elif hint in (bool, str) and isinstance(v, hint):
        return v
    raise _BadValue(f"{key} must be {_expected(hint)}, got {_shown(v)}")


def _key(parent: str, name: str) -> str:
    return f"{parent}.{name}" if parent else name


def is_number(v: Any) -> bool:
    """An int or a float as JSON gives them (True is an int to Python, not to JSON)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _expected(hint: Any) -> str:
    """What a value of annotation `hint` is, in words, for an error message."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if dataclasses.is_dataclass(hint):
        return "an object"
    if origin in (typing.Union, types.UnionType):
        return " or ".join("null" if a is type(None) else _expected(a) for a in args)
    if origin is Literal:
        return "one of " + ", ".join(json.dumps(a) for a in args)
    if origin in (tuple, list):
        return f"a list of {_expected(args[0]).split(' ', 1)[-1]}s" if args else "a list"
    return {int: "an int", float: "a number", bool: "true or false",
            str: "a string"}.get(hint, str(hint))


def _shown(v: Any) -> str:
    """`v` as config.json writes it, cut short."""
    s = json.dumps(v, default=repr)
    return s if len(s) <= 40 else s[:37] + "..."


# Ranges that the annotations cannot say. Every number must be finite and non-negative
# (no setting takes a negative one: the seed neither, `train --seed` refuses it); these
# must also be at least 1 (sizes and counts the model or the training divides by or builds
# from: 0 gave a traceback deep inside), positive, or a fraction in [0, 1].
_AT_LEAST_ONE = frozenset({
    "model.warp.width", "model.field.width", "model.field.hash_levels",
    "model.field.hash_features", "model.field.hash_log2_size", "model.field.hash_base_res",
    "model.field.head_width", "model.field.expr_levels", "model.field.expr_base_res",
    "model.field.expr_features", "model.field.expr_log2_size",
    "model.field.detail_log2_size", "model.sampler.num_coarse",
    "model.sampler.num_proposal", "model.sampler.num_main", "model.sampler.proposal_levels",
    "model.sampler.proposal_log2_size", "model.sampler.proposal_max_res",
    "model.sampler.proposal_width", "model.mesh_guide.neighbours", "train.steps",
    "train.batch_rays", "train.accumulate", "train.checkpoint_every", "train.log_every"})
_POSITIVE = frozenset({"model.expression_scale", "model.head.region_scale",
                       "train.downscale"})
_FRACTION = frozenset({"model.sampler.refine_below", "model.expression_regions.threshold",
                       "train.face_ray_fraction", "train.face_depth_start",
                       "train.moving_weight"})


def _check_ranges(obj: Any, key: str = "") -> None:
    """Raise _BadValue for the first number of `obj` (a Config, or one of its parts at
    `key`) outside its range (above)."""
    for f in dataclasses.fields(obj):
        v, k = getattr(obj, f.name), _key(key, f.name)
        if dataclasses.is_dataclass(v):
            _check_ranges(v, k)
            continue
        for x in v if isinstance(v, tuple) else (v,):
            if is_number(x) and _out_of_range(x, k):
                raise _BadValue(f"{k} must be {_range(k)}, got {_shown(x)}")


def _out_of_range(x: float, key: str) -> bool:
    if not math.isfinite(x) or x < 0:
        return True
    return ((key in _AT_LEAST_ONE and x < 1) or (key in _POSITIVE and x <= 0)
            or (key in _FRACTION and x > 1))


def _range(key: str) -> str:
    if key in _AT_LEAST_ONE:
        return "at least 1"
    if key in _POSITIVE:
        return "a positive number"
    return "between 0 and 1" if key in _FRACTION else "a finite number, at least 0"
