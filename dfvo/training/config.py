"""Typed configuration of ``train.py`` / ``dfvo-train``: the schema every YAML file of ``dfvo/conf/train/`` fills.

The dataclasses hold every default once. ``model/*.yaml`` name their schema (``schema/depth`` or ``schema/flow``, whose
``_target_`` is the LightningModule) and hold only what differs from it; ``trainer/*.yaml`` only what differs from
:class:`TrainerConfig`; ``data/*.yaml`` only what differs from their kind's schema (:data:`TRAIN_DATA_SCHEMAS`). Hydra
checks overrides against the schema, so a typo (``model.w_smoth=1``) or a wrong type fails before anything runs;
the ``__post_init__`` checks run when a node becomes its dataclass (:func:`typed`), before any data or network
is built. ``python train.py --cfg job`` prints the composed configuration with every default.

``register_configs()`` stores the schemas in Hydra's ConfigStore (``train_schema`` for the root, ``model/schema/KIND``,
``data/train_schema/KIND`` and ``trainer/schema/trainer`` for the groups; not ``data/schema``, where the inference
schemas are: both can be registered in one process); it runs on import of this module.

The data schemas (one per kind, and :func:`data_root`: ``data.root=`` or the kind's environment variable, never a
path derived from the repository layout) live in :mod:`dfvo.training.data_config` and are re-exported here.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig, OmegaConf

from dfvo.training.augment import DepthAugmentConfig
from dfvo.training.data_config import (
    TRAIN_DATA_SCHEMAS,
    CropMode,
    FlowMixTrainDataConfig,
    FlowPairTrainDataConfig,
    FlyingChairsTrainDataConfig,
    FlyingThingsTrainDataConfig,
    KittiFlowTrainDataConfig,
    KittiOdomTrainDataConfig,
    KittiRawSyntheticTrainDataConfig,
    KittiRawTrainDataConfig,
    SintelTrainDataConfig,
    SyntheticTrainDataConfig,
    TrainDataConfig,
    WorldsTrainDataConfig,
    data_root,
)
from dfvo.training.flow_augment import FlowAugmentConfig
from dfvo.validation import choice, choices, positive, typed

__all__ = ["MonitorMode", "FlowMode", "CropMode", "Precision", "MatmulPrecision", "check_distillation",
           "DepthModelConfig", "FlowLossConfig", "FlowPhase", "FlowModelConfig", "MODEL_SCHEMAS", "TrainDataConfig",
           "WorldsTrainDataConfig", "SyntheticTrainDataConfig", "KittiRawTrainDataConfig", "KittiOdomTrainDataConfig",
           "KittiRawSyntheticTrainDataConfig", "FlowMixTrainDataConfig", "FlowPairTrainDataConfig",
           "FlyingChairsTrainDataConfig", "FlyingThingsTrainDataConfig", "SintelTrainDataConfig",
           "KittiFlowTrainDataConfig", "TRAIN_DATA_SCHEMAS", "PRECISIONS", "TrainerConfig", "TrainConfig",
           "register_configs", "typed", "model_config", "data_config", "data_root"]


class MonitorMode(StrEnum):
    """Whether the monitored metric of the ``best`` checkpoint is better when lower or higher."""

    min = "min"
    max = "max"


class FlowMode(StrEnum):
    """``supervised``: multi-scale EPE on true flow; ``self``: photometric + smoothness + fb consistency; ``mixed``:
    step-scheduled phases of supervised synthetic pairs and/or self-supervised KITTI raw pairs (``data=flow_mix``,
    :attr:`FlowModelConfig.phases`)."""

    supervised = "supervised"
    self = "self"
    mixed = "mixed"


# ----------------------------------------------------------------------------------------------------- models
def check_distillation(teacher: str | None, w_distill: float, network: str) -> None:
    """``model.teacher`` and ``model.w_distill`` of a ``network`` (``depth``, ``flow``) model go together: a positive
    weight needs a teacher, a teacher a positive weight; one line naming both otherwise."""
    if w_distill > 0 and not teacher:
        raise ValueError(f"model.w_distill={w_distill} needs model.teacher (a trained {network} network's weights "
                         "file to distil from)")
    if teacher and not w_distill > 0:
        raise ValueError(f"model.teacher={teacher} has no effect with model.w_distill={w_distill}; "
                         "expected a positive weight (or no teacher)")


@dataclass
class DepthModelConfig:
    """Self-supervised depth (and pose) training (:class:`dfvo.training.depth_module.DepthPoseModule`).

    Attributes:
        _target_: the LightningModule built from this node (it receives the whole training config).
        task: ``depth`` (with ``name``, the identity ``task:name`` written into checkpoints and checked on resume).
        name: the model's name (``depth_stereo``, ``depth_mono``, ``depth_mono_sc``; set by ``model/NAME.yaml``).
        stereo: use the stereo partner (metric depth from the calibrated baseline). temporal: use frames i-s, i+s
            through the pose network.
        alpha: SSIM weight of the photometric error. w_smooth: λ_ds of the edge-aware smoothness.
        w_consistency: λ_dc of the inverse-depth consistency (paper "Mono-SC": 5).
        w_depth_supervised: weight of the log-depth L1 against true depth where the batch has it (synthetic
            samples; 0: the paper's self-supervised loss alone).
        w_depth_hints: weight of the depth-hint loss (Watson et al. 2019): at every scale, ``log(1 + |D - H|)``
            where the batch's stereo-matcher depth ``H`` (``data.depth_hints=true``) reprojects the stereo partner
            with a lower photometric error than the network's depth ``D`` does any source view (0: off).
        depth_hints_from_row: the hints teach only the image rows at or below this fraction of the height (0: every
            row; 0.667: the lower third, mostly road); above it they are dropped before any loss (with
            ``distill_where_no_target`` the teacher takes those pixels).
        w_camera_height: weight of the camera-height loss (:mod:`dfvo.losses.road_height`): at every scale, the
            log-depth L1 of the road pixels against the plane at the sample's known ``camera_height`` (the data's
            ``data.camera_height``: real KITTI samples), the plane's tilt and pixels from the network's own depth
            (the tracker's road band, ``tracker.road_plane`` defaults) (0: off).
        freeze_bn: keep the depth and pose networks' batch-norm layers in inference mode while training (their
            running statistics stay those of ``init_from``; their scales and shifts still learn): a fine-tune on
            small batches that mix real and synthetic images otherwise normalises each batch by its own mix, and the
            network it exports (running statistics) is not the one the losses trained.
        automask: monodepth2's identity reprojection mask.
        min_depth, max_depth: depth range (metres). init_depth: initial depth of the disparity heads (metres; null:
            sigmoid 0.5); 10 m gives the stereo term a gradient from step 0.
        lr: Adam's rate; x0.1 for the last ``1 - lr_drop_fraction`` of the steps (paper: 15 of 20 epochs; > 1: never).
        log_images_every: steps between TensorBoard images (0: never).
        monitor, monitor_mode: the metric of the ``best`` checkpoint (metric depth: ``val/abs_rel``; monocular
            up-to-scale depth: the median-scaled ``val/abs_rel_med``); null: no best checkpoint.
        augment: monodepth2's flips and colour jitter (null: none).
        init_from: start from these weights (DepthNet ``.safetensors``/``.pt``, or a depth ``.ckpt``; not a resume).
        initialised_from: where a checkpoint's weights started from (written by training, see
            :mod:`dfvo.training.hparams`).
        width_multiplier: the depth network's channel multiplier (``DepthNet(width=...)``; 1: the monodepth2 network,
            0.5: a cheaper one with about a quarter of its multiply-adds; at most 4); exports record it.
        teacher: a trained depth network's weights file (any width): distillation. It sees each sample's image before
            ``augment.shadow_prob``'s shadows (so the student learns to ignore them) and before
            ``augment.paste_prob``'s objects (it teaches the scene around them; their own pixels, whose depth is
            known, are left out), in inference mode, and is not part of the checkpoints.
        w_distill: weight of the distillation loss: at every scale, the log-depth L1 of the scale's depth against
            the teacher's (0: off; > 0 needs ``teacher``).
        distill_where_no_target: the teacher only at the pixels that have no other depth target: not where the
            batch's ``depth`` (the worlds' exact depth, pasted objects) or ``depth_hint`` (the stereo matcher's,
            ``data.depth_hints``) is > 0 (false: every pixel but the pasted objects').
        distill_scale_from_hints: the teacher's depth of each image times the median of stereo hint ÷ teacher over
            the pixels it teaches that have a hint (``depth_hints_from_row`` does not limit these), so the teacher
            gives the scene's shape and the stereo matcher its metric scale (an image with fewer than
            ``dfvo.training.depth_module.MIN_SCALE_PIXELS`` such pixels keeps the teacher's scale). Needs
            ``data.depth_hints``.
    """

    _target_: str = "dfvo.training.depth_module.DepthPoseModule"
    task: str = "depth"
    name: str = MISSING
    stereo: bool = True
    temporal: bool = True
    alpha: float = 0.85
    w_smooth: float = 1e-3
    w_consistency: float = 0.0
    w_depth_supervised: float = 0.0
    w_depth_hints: float = 0.0
    depth_hints_from_row: float = 0.0
    w_camera_height: float = 0.0
    freeze_bn: bool = False
    automask: bool = True
    min_depth: float = 0.1
    max_depth: float = 100.0
    init_depth: float | None = 10.0
    lr: float = 1e-4
    lr_drop_fraction: float = 0.75
    log_images_every: int = 200
    monitor: str | None = "val/abs_rel"
    monitor_mode: MonitorMode = MonitorMode.min
    augment: DepthAugmentConfig | None = field(default_factory=DepthAugmentConfig)
    init_from: str | None = None
    initialised_from: str | None = None
    width_multiplier: float = 1.0
    teacher: str | None = None
    w_distill: float = 0.0
    distill_where_no_target: bool = False
    distill_scale_from_hints: bool = False

    def __post_init__(self) -> None:
        if self.task != "depth":
            raise ValueError(f"model.task={self.task!r}; the depth schema (model/schema/depth) trains task 'depth'")
        if not (self.stereo or self.temporal):
            raise ValueError("model: at least one of model.stereo / model.temporal must be true")
        for key in ("w_smooth", "w_consistency", "w_depth_supervised", "w_depth_hints", "w_camera_height",
                    "w_distill"):
            if getattr(self, key) < 0:
                raise ValueError(f"model.{key}={getattr(self, key)}; expected >= 0")
        if self.w_depth_hints > 0 and not self.stereo:
            raise ValueError("model.w_depth_hints > 0 needs model.stereo = true (hints reproject the stereo partner)")
        if not 0.0 <= self.depth_hints_from_row < 1.0:
            raise ValueError(f"model.depth_hints_from_row={self.depth_hints_from_row}; expected a fraction of the "
                             "image height in [0, 1) (0: hints on every row)")
        if self.w_consistency > 0 and not self.temporal:
            raise ValueError("model.w_consistency > 0 needs model.temporal = true (consistency across frames)")
        check_distillation(self.teacher, self.w_distill, "depth")
        if self.distill_scale_from_hints and self.w_distill <= 0:
            raise ValueError("model.distill_scale_from_hints=true scales the teacher's depth: it needs model.teacher "
                             "and model.w_distill > 0")
        if not 0 < self.width_multiplier <= 4:
            raise ValueError(f"model.width_multiplier={self.width_multiplier}; expected a channel multiplier in "
                             "(0, 4] (1: the monodepth2 network; the image width is data.width)")
        positive("model", min_depth=self.min_depth, lr=self.lr, lr_drop_fraction=self.lr_drop_fraction,
                  init_depth=self.init_depth)
        if self.max_depth <= self.min_depth:
            raise ValueError(f"model.max_depth={self.max_depth}; expected > model.min_depth={self.min_depth}")


@dataclass
class FlowLossConfig:
    """Self-supervised flow loss: ``alpha`` SSIM weight (alpha*(1-SSIM)/2 + (1-alpha)*|I-I'|), ``w_smooth`` λ_fs
    (edge-aware smoothness of the flow), ``w_consistency`` λ_fc (forward-backward consistency), ``occlusion`` (mask
    the photometric and consistency terms with the forward-backward occlusion mask)."""

    alpha: float = 0.85
    w_smooth: float = 0.1
    w_consistency: float = 5e-3
    occlusion: bool = True


@dataclass
class FlowPhase:
    """One phase of a step-scheduled flow run (``model=flow_mix``, :attr:`FlowModelConfig.phases`).

    Attributes:
        name: the phase's name (logged). steps: optimiser steps of the phase.
        lr: Adam's rate in the phase (x ``model.lr_gamma`` for its last ``1 - model.lr_drop_fraction``).
        synthetic: each step holds ``data.batch_size`` supervised synthetic pairs (multi-scale EPE, both directions).
        kitti: each step holds ``data.kitti_batch_size`` self-supervised KITTI raw pairs (photometric + smoothness +
            forward-backward consistency, weight ``model.self_weight``).
    """

    name: str = "phase"
    steps: int = MISSING
    lr: float = 1e-4
    synthetic: bool = True
    kitti: bool = False

    def __post_init__(self) -> None:
        if self.steps < 1:
            raise ValueError(f"model.phases: phase {self.name!r} has steps={self.steps}; expected >= 1")
        positive(f"model.phases[{self.name}]", lr=self.lr)
        if not (self.synthetic or self.kitti):
            raise ValueError(f"model.phases: phase {self.name!r} trains on nothing; set synthetic and/or kitti true")


@dataclass
class FlowModelConfig:
    """Optical flow training (:class:`dfvo.training.flow_module.FlowModule`).

    Attributes:
        _target_, task (``flow``), name (``flow_supervised``, ``flow_self``): as :class:`DepthModelConfig`.
        mode: see :class:`FlowMode` (supervised: multi-scale EPE on visible pixels, each scale / 2^scale).
        variant: FlowNet variant (``default``, ``small``, ``tiny``; :class:`dfvo.models.flow_net.FlowNetConfig`).
        lr, lr_milestones, lr_gamma: Adam (paper: 1e-4 for 15 epochs, then 1e-5), multiplied by ``lr_gamma`` at each
            milestone epoch.
        init_from: start from these weights (a FlowModule ``.ckpt`` or a FlowNet ``.safetensors``/``.pt``).
        log_images_every: steps between TensorBoard images (flow colours, fb inconsistency, visibility).
        monitor, monitor_mode: metric of the ``best`` checkpoint (``val/epe``: validation data with true flow; mode
            ``mixed``: the mean over the held-out scenarios of the AEPE over visible pixels at the working size).
        loss: the self-supervised loss (modes ``self`` and ``mixed``).
        phases: mode ``mixed``: the run as a list of :class:`FlowPhase` (steps, rate, what a step's batch holds);
            the run is their steps, one epoch. lr_drop_fraction: mode ``mixed``: each phase's rate is multiplied by
            ``lr_gamma`` from this fraction of its steps on (1: never).
        self_weight: mode ``mixed``: weight of the self-supervised loss added to the supervised one.
        grad_clip_norm: clip the gradient's global 2-norm to this before each step (null: no clipping; a
            ``trainer.gradient_clip_val`` applies when this is null).
        augment: mode ``mixed``: flips, greyscale and jitter (:class:`dfvo.training.flow_augment.FlowAugmentConfig`;
            null: none).
        teacher: mode ``mixed``: a trained flow network's weights file (any variant, e.g. the shipped
            ``checkpoints/flow.safetensors``): distillation. On each step's KITTI (self-supervised) pairs, as the
            student sees them (augmented), its forward and backward flows supervise the student's by the
            multi-scale EPE over all pixels, weight ``w_distill``: the teacher's behaviour on real footage carried into
            a smaller variant (``variant: tiny``), while the synthetic pairs keep their true flow.
        w_distill: weight of the distillation loss (0: off; > 0 needs ``teacher``).
    """

    _target_: str = "dfvo.training.flow_module.FlowModule"
    task: str = "flow"
    name: str = MISSING
    mode: FlowMode = FlowMode.supervised
    variant: str = "small"
    lr: float = 1e-4
    lr_milestones: list[int] = field(default_factory=lambda: [15])
    lr_gamma: float = 0.1
    init_from: str | None = None
    initialised_from: str | None = None
    log_images_every: int = 200
    monitor: str | None = "val/epe"
    monitor_mode: MonitorMode = MonitorMode.min
    loss: FlowLossConfig = field(default_factory=FlowLossConfig)
    phases: list[FlowPhase] = field(default_factory=list)
    lr_drop_fraction: float = 0.75
    self_weight: float = 1.0
    grad_clip_norm: float | None = None
    augment: FlowAugmentConfig | None = None
    teacher: str | None = None
    w_distill: float = 0.0

    def __post_init__(self) -> None:
        from dfvo.models.flow_net import FlowNetConfig  # deferred: torch; composing a config needs none

        if self.task != "flow":
            raise ValueError(f"model.task={self.task!r}; the flow schema (model/schema/flow) trains task 'flow'")
        try:
            FlowNetConfig.variant(self.variant)
        except ValueError as err:
            raise ValueError(f"model.variant={self.variant!r}: {err}") from None
        positive("model", lr=self.lr, lr_gamma=self.lr_gamma, lr_drop_fraction=self.lr_drop_fraction,
                  grad_clip_norm=self.grad_clip_norm)
        if self.lr_drop_fraction > 1:
            raise ValueError(f"model.lr_drop_fraction={self.lr_drop_fraction}; expected a fraction in (0, 1]")
        if self.self_weight < 0:
            raise ValueError(f"model.self_weight={self.self_weight}; expected >= 0")
        if (self.mode == FlowMode.mixed) != bool(self.phases):
            raise ValueError("model.phases: mode 'mixed' (model=flow_mix) trains by phases and needs at least one; "
                             f"mode {self.mode.value!r} has none (got {len(self.phases)})")
        if self.w_distill < 0:
            raise ValueError(f"model.w_distill={self.w_distill}; expected >= 0")
        check_distillation(self.teacher, self.w_distill, "flow")
        if self.teacher and not (self.mode == FlowMode.mixed and any(p.kitti for p in self.phases)):
            raise ValueError(f"model.teacher={self.teacher}: the teacher supervises the KITTI pairs of mode 'mixed' "
                             "(model=flow_mix with a phase of kitti: true); this run has none")


MODEL_SCHEMAS: dict[str, type] = {"depth": DepthModelConfig, "flow": FlowModelConfig}


# ---------------------------------------------------------------------------------------------------- trainer
class Precision(StrEnum):
    """``trainer.precision``: ``auto`` (bf16 mixed precision where the device computes in bf16, else fp32:
    :mod:`dfvo.training.precision`) or one of Lightning's values (the field holds the value: ``32-true``...)."""

    auto = "auto"
    fp32 = "32-true"
    bf16_mixed = "bf16-mixed"
    fp16_mixed = "16-mixed"
    bf16 = "bf16-true"
    fp16 = "16-true"
    fp64 = "64-true"


PRECISIONS = tuple(choices(Precision))


class MatmulPrecision(StrEnum):
    """``torch.set_float32_matmul_precision`` values (``trainer.float32_matmul_precision``)."""

    highest = "highest"
    high = "high"
    medium = "medium"


@dataclass
class TrainerConfig:
    """Lightning ``Trainer`` settings and the run's checkpoint outputs.

    ``trainer=default`` is this schema; ``trainer=smoke`` (a few steps), ``trainer=gpu`` (one GPU, bf16) and
    ``trainer=ddp`` change a few fields.

    Attributes:
        accelerator: ``auto`` (CUDA when visible, else CPU), ``cpu``, ``gpu``. devices: ``auto``, a count or a list.
        strategy: ``auto`` or ``ddp`` (one process per device; CPU: ``devices=N`` processes with gloo).
        max_epochs (paper: 20, lr drop after 15), max_steps (-1: no limit), limit_train_batches, limit_val_batches
            (null: all; an int: batches, a float: fraction), check_val_every_n_epoch, num_sanity_val_steps,
            log_every_n_steps, deterministic, gradient_clip_val: as Lightning's Trainer.
        precision: one of :data:`PRECISIONS`: ``auto`` (default) is ``bf16-mixed`` where the CPU or GPU has bf16
            arithmetic and ``32-true`` elsewhere (:func:`dfvo.training.precision.resolve_precision`, logged);
            ``32-true`` forces float32 (the reference), ``bf16-mixed`` bf16 autocast.
        channels_last: convolutional networks and image batches in NHWC memory layout (pays on GPUs with mixed
            precision; measure before using it on a CPU).
        keep_freed_memory: glibc's malloc keeps large freed blocks for the next step instead of returning them to the
            system (:mod:`dfvo.training.allocator`; fewer page faults, ~x1.1 steps an hour on a CPU; no-op elsewhere).
        benchmark: cuDNN autotuning for fixed input sizes (null: Lightning's default).
        float32_matmul_precision: ``torch.set_float32_matmul_precision`` (``high``: TF32 on Ampere and newer GPUs;
            null: leave torch's default).
        val_check_interval: validate every this many training steps (an int) or fraction of an epoch (a float;
            null: once per epoch), as Lightning's Trainer.
        validate_at_stop: a run stopped by ``max_steps`` validates its last step (so the monitored metric exists
            for the ``best`` checkpoint and the final metrics), also when the stop falls mid-epoch.
        checkpoint_every_n_steps: rewrite ``checkpoints/last.ckpt`` every this many steps (and at the end of the run;
            null: at every epoch end and validation).
        keep_best: also keep ``best-*.ckpt``, the checkpoint of the best ``model.monitor`` value (a full copy;
            ``trainer=smoke`` keeps only ``last.ckpt``, what resuming needs).
        export_weights: write ``RUN/weights.safetensors`` (fp16, the network inference loads, with its metadata)
            whenever ``checkpoints/last.ckpt`` is written.
        keep_weights_every_n_steps: also keep ``RUN/weights_step{N}.safetensors`` every this many steps (null: none):
            a long run's intermediate networks, to compare afterwards.
        ema_decay: export the exponential moving average of the network's weights (decay per step, e.g. 0.999)
            instead of the raw weights (null: off); the average is kept in the checkpoint
            (:mod:`dfvo.training.weight_average`).
        print_every_n_steps: one console (log) line with the step, rate, speed and logged training metrics every
            this many steps, and one per validation (0: none; for runs without a progress bar, e.g. in the
            background).
        enable_progress_bar, progress_refresh: the progress bar. logger: TensorBoard under ``RUN/tb``.
    """

    accelerator: str = "auto"
    devices: Any = "auto"
    strategy: str = "auto"
    num_nodes: int = 1
    max_epochs: int = 20
    max_steps: int = -1
    log_every_n_steps: int = 10
    check_val_every_n_epoch: int = 1
    val_check_interval: int | float | None = None
    limit_train_batches: int | float | None = None
    limit_val_batches: int | float | None = None
    num_sanity_val_steps: int = 0
    precision: str = "auto"
    deterministic: bool = False
    gradient_clip_val: float | None = None
    channels_last: bool = False
    keep_freed_memory: bool = True
    benchmark: bool | None = None
    float32_matmul_precision: str | None = None
    validate_at_stop: bool = True
    checkpoint_every_n_steps: int | None = None
    keep_best: bool = True
    export_weights: bool = True
    keep_weights_every_n_steps: int | None = None
    ema_decay: float | None = None
    print_every_n_steps: int = 0
    enable_progress_bar: bool = True
    progress_refresh: int = 10
    logger: bool = True

    def __post_init__(self) -> None:
        choice(Precision, self.precision, "trainer.precision")
        if self.float32_matmul_precision is not None:
            choice(MatmulPrecision, self.float32_matmul_precision, "trainer.float32_matmul_precision (or null)")
        if self.max_steps < -1 or self.max_steps == 0:
            raise ValueError(f"trainer.max_steps={self.max_steps}; expected -1 (no limit) or a positive count")
        positive("trainer", checkpoint_every_n_steps=self.checkpoint_every_n_steps,
                  val_check_interval=self.val_check_interval,
                  keep_weights_every_n_steps=self.keep_weights_every_n_steps)
        if self.ema_decay is not None and not 0.0 < self.ema_decay < 1.0:
            raise ValueError(f"trainer.ema_decay={self.ema_decay}; expected a decay in (0, 1), e.g. 0.999, or null")
        if self.ema_decay is not None and self.precision in (Precision.bf16, Precision.fp16):
            raise ValueError(f"trainer.ema_decay={self.ema_decay} with trainer.precision={self.precision}: a moving "
                             "average of half-precision weights stops moving (each step's change is below their "
                             "resolution); use a mixed precision (bf16-mixed, 16-mixed) or 32-true")
        if self.print_every_n_steps < 0:
            raise ValueError(f"trainer.print_every_n_steps={self.print_every_n_steps}; expected >= 0 (0: none)")


# ------------------------------------------------------------------------------------------------------- root
@dataclass
class TrainConfig:
    """Root of ``train.py``'s configuration.

    Attributes:
        model: depth or flow schema (``model=NAME``). data: one of :data:`TRAIN_DATA_SCHEMAS` (``data=KIND``).
        trainer: :class:`TrainerConfig` (``trainer=default|smoke|gpu|ddp``).
        name: the run folder ``runs_dir/name`` (default ``<model>_<data>``).
        runs_dir: where runs are written (default ``$DFVO_RUNS_DIR``, else ``runs`` in the working folder; long runs
            that must outlive a session: a folder outside the work tree, e.g. ``~/dfvo-runs``; ``~`` is expanded
            here and in the paths built on it through the ``${user_path:...}`` resolver).
        seed: global seed (weights initialisation). ckpt_path: resume exactly from a ``last.ckpt`` of the same model.
        resume: ``auto`` continues the run ``runs_dir/name`` from its newest checkpoint (exactly, as ``ckpt_path``)
            or starts it; ``never`` starts a new run and refuses a folder that already holds one
            (:mod:`dfvo.training.resume`).
        continue_from: a weights export of this depth run (``RUN/weights.safetensors``: its step and epoch in the
            metadata) to continue it from when its checkpoints are lost, e.g. on a new machine: the epochs to go,
            the same rate schedule, the pose network and optimiser anew (:mod:`dfvo.training.continuation`).
        threads: torch threads (0: torch's default). verbose: full tracebacks for expected errors.
    """

    model: Any = MISSING
    data: Any = MISSING
    trainer: TrainerConfig = field(default_factory=TrainerConfig)
    name: str = "${model.name}_${data.kind}"
    runs_dir: str = "${oc.env:DFVO_RUNS_DIR,runs}"
    seed: int = 0
    ckpt_path: str | None = None
    resume: str = "never"
    continue_from: str | None = None
    threads: int = 0
    verbose: bool = False


def user_path(path: str) -> str:
    """The ``${user_path:PATH}`` resolver of the training configs: ``PATH`` with a leading ``~`` expanded."""
    return str(Path(str(path)).expanduser())


def register_configs() -> None:
    """Store the schemas in Hydra's ConfigStore and the ``user_path`` resolver in OmegaConf (idempotent)."""
    if not OmegaConf.has_resolver("user_path"):
        OmegaConf.register_new_resolver("user_path", user_path)
    cs = ConfigStore.instance()
    cs.store(name="train_schema", node=TrainConfig)
    for task, schema in MODEL_SCHEMAS.items():
        cs.store(group="model/schema", name=task, node=schema)
    for kind, schema in TRAIN_DATA_SCHEMAS.items():
        cs.store(group="data/train_schema", name=kind, node=schema)
    cs.store(group="trainer/schema", name="trainer", node=TrainerConfig)


# ------------------------------------------------------------------------------------------------ typed access
def model_config(cfg: DictConfig | dict) -> DepthModelConfig | FlowModelConfig:
    """The typed ``model`` node of a training config (schema chosen by ``model.task``)."""
    node = cfg["model"]
    task = node.get("task") if hasattr(node, "get") else None
    if task not in MODEL_SCHEMAS:
        raise ValueError(f"model.task={task!r}; expected one of {sorted(MODEL_SCHEMAS)} (choose model=NAME)")
    return typed(node, MODEL_SCHEMAS[task], "model")


def data_config(cfg: DictConfig | dict) -> TrainDataConfig:
    """The typed ``data`` node of a training config (schema chosen by ``data.kind``)."""
    node = cfg["data"]
    kind = node.get("kind") if hasattr(node, "get") else None
    if kind not in TRAIN_DATA_SCHEMAS:
        raise ValueError(f"data.kind={kind!r}; expected one of {sorted(TRAIN_DATA_SCHEMAS)} (choose data=KIND)")
    return typed(node, TRAIN_DATA_SCHEMAS[kind], "data")


register_configs()
