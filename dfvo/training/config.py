"""Typed configuration of ``train.py`` / ``dfvo-train``: the schema every YAML file of ``dfvo/conf/train/`` fills.

The dataclasses hold every default once; ``model/*.yaml`` name their LightningModule (``_target_``) and hold only
what differs from the schema of their task, ``trainer/*.yaml`` only what differs from :class:`TrainerConfig`.
``register_configs()`` stores the schemas in Hydra's ConfigStore (``train_schema`` for the root,
``model/schema/{depth,flow}`` and ``trainer/schema`` for the groups); it runs on import of :mod:`dfvo.cli.train`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING

from dfvo.training.augment import DepthAugmentConfig

__all__ = ["DepthModelConfig", "FlowLossConfig", "FlowModelConfig", "TrainerConfig", "TrainConfig",
           "register_configs"]


@dataclass
class DepthModelConfig:
    """Self-supervised depth (and pose) training (:class:`dfvo.training.depth_module.DepthPoseModule`).

    Attributes:
        name: the model's name (``depth_stereo``, ``depth_mono``, ``depth_mono_sc``; stored in checkpoints).
        stereo: use the stereo partner (metric depth from the calibrated baseline). temporal: use frames i-1, i+1
            through the pose network.
        alpha: SSIM weight of the photometric error. w_smooth: λ_ds of the edge-aware smoothness.
        w_consistency: λ_dc of the inverse-depth consistency (paper "Mono-SC": 5).
        automask: monodepth2's identity reprojection mask.
        min_depth, max_depth: depth range (metres). init_depth: initial depth of the disparity heads (metres).
        lr: Adam's rate; x0.1 for the last ``1 - lr_drop_fraction`` of the steps (paper: 15 of 20 epochs).
        log_images_every: steps between TensorBoard images.
        monitor, monitor_mode: the metric of the ``best`` checkpoint (metric depth: ``val/abs_rel``; monocular
            up-to-scale depth: the median-scaled ``val/abs_rel_med``).
        augment: flips and colour jitter (null: none).
        init_from: start from these weights (DepthNet ``.safetensors``/``.pt``, or a depth ``.ckpt``; not a resume).
    """

    _target_: str = "dfvo.training.depth_module.DepthPoseModule"
    task: str = "depth"
    name: str = "depth_stereo"
    stereo: bool = True
    temporal: bool = True
    alpha: float = 0.85
    w_smooth: float = 1e-3
    w_consistency: float = 0.0
    automask: bool = True
    min_depth: float = 0.1
    max_depth: float = 100.0
    init_depth: float | None = 10.0
    lr: float = 1e-4
    lr_drop_fraction: float = 0.75
    log_images_every: int = 200
    monitor: str = "val/abs_rel"
    monitor_mode: str = "min"
    augment: DepthAugmentConfig | None = field(default_factory=DepthAugmentConfig)
    init_from: str | None = None
    initialised_from: str | None = None


@dataclass
class FlowLossConfig:
    """Self-supervised flow loss: ``alpha`` SSIM weight, ``w_smooth`` λ_fs, ``w_consistency`` λ_fc, ``occlusion``
    (mask the photometric and consistency terms with the forward-backward occlusion mask)."""

    alpha: float = 0.85
    w_smooth: float = 0.1
    w_consistency: float = 5e-3
    occlusion: bool = True


@dataclass
class FlowModelConfig:
    """Optical flow training (:class:`dfvo.training.flow_module.FlowModule`).

    Attributes:
        name: the model's name (``flow_supervised``, ``flow_self``; stored in checkpoints).
        mode: ``supervised`` (multi-scale EPE on true flow) or ``self`` (photometric + smoothness + consistency).
        variant: FlowNet variant (``default``, ``small``, ``tiny``).
        lr, lr_milestones, lr_gamma: Adam, multiplied by ``lr_gamma`` at each milestone epoch.
        init_from: start from these weights (a FlowModule ``.ckpt`` or a FlowNet ``.safetensors``/``.pt``).
        log_images_every: steps between TensorBoard images. monitor, monitor_mode: metric of the ``best`` checkpoint.
    """

    _target_: str = "dfvo.training.flow_module.FlowModule"
    task: str = "flow"
    name: str = "flow_supervised"
    mode: str = "supervised"
    variant: str = "small"
    lr: float = 1e-4
    lr_milestones: list[int] = field(default_factory=lambda: [15])
    lr_gamma: float = 0.1
    init_from: str | None = None
    initialised_from: str | None = None
    log_images_every: int = 200
    monitor: str | None = "val/epe"
    monitor_mode: str = "min"
    loss: FlowLossConfig = field(default_factory=FlowLossConfig)


@dataclass
class TrainerConfig:
    """Lightning ``Trainer`` settings (``trainer=default``; ``trainer=ddp`` and ``trainer=smoke`` change a few)."""

    accelerator: str = "auto"
    devices: Any = "auto"
    strategy: str = "auto"
    num_nodes: int = 1
    max_epochs: int = 20
    max_steps: int = -1
    log_every_n_steps: int = 10
    check_val_every_n_epoch: int = 1
    limit_train_batches: Any = None
    limit_val_batches: Any = None
    num_sanity_val_steps: int = 0
    precision: str = "32-true"
    deterministic: bool = False
    gradient_clip_val: float | None = None
    enable_progress_bar: bool = True
    progress_refresh: int = 10
    logger: bool = True
    channels_last: bool = False


@dataclass
class TrainConfig:
    """Root of ``train.py``'s configuration: ``model`` (depth or flow schema), ``data`` (the training data),
    ``trainer``; ``name`` the run folder ``runs_dir/name``, ``seed``, ``ckpt_path`` (resume exactly), ``threads``
    (torch threads; 0: torch's default)."""

    model: Any = MISSING
    data: Any = MISSING
    trainer: TrainerConfig = field(default_factory=TrainerConfig)
    name: str = MISSING
    runs_dir: str = "runs"
    seed: int = 0
    ckpt_path: str | None = None
    threads: int = 0


def register_configs() -> None:
    """Store the schemas in Hydra's ConfigStore (idempotent)."""
    cs = ConfigStore.instance()
    cs.store(name="train_schema", node=TrainConfig)
    cs.store(group="model/schema", name="depth", node=DepthModelConfig)
    cs.store(group="model/schema", name="flow", node=FlowModelConfig)
    cs.store(group="trainer/schema", name="trainer", node=TrainerConfig)
