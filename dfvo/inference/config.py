"""Typed configuration of ``infer.py`` / ``dfvo-infer``: the schema every YAML file of ``dfvo/conf/infer/`` fills.

The dataclasses here and in :mod:`dfvo.tracking.config`, :mod:`dfvo.sources.config` and
:mod:`dfvo.matching.flow_refinement` hold every default once; the YAML files only choose (``tracker=pnp``,
``data=kitti_odom``) and the command line overrides values. Hydra checks overrides against the schema, so a typo
(``tracker.scale.methd=...``) or a wrong type fails before anything runs.

``register_configs()`` stores the schemas in Hydra's ConfigStore (``infer_schema`` for the root, ``data/schema/KIND``
for each dataset kind); it runs on import of this module, before Hydra composes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig, OmegaConf

from dfvo.sources.config import DepthSourceConfig, FlowSourceConfig
from dfvo.tracking.config import TrackerConfig
from dfvo.training.online_flow import OnlineFlowConfig

__all__ = ["AlignMode", "PoseFormat", "ImgResConfig", "SyntheticDataConfig", "KittiOdomDataConfig",
           "KittiRawDataConfig", "FolderDataConfig", "DATA_SCHEMAS", "TensorboardConfig", "ViewerConfig",
           "InferConfig", "register_configs", "typed"]


class AlignMode(StrEnum):
    """Alignment of the prediction to the ground truth before metrics: ``6dof`` (metric depth), ``7dof``
    (monocular, up to scale), ``scale`` (scale only)."""

    six_dof = "6dof"
    seven_dof = "7dof"
    scale = "scale"


class PoseFormat(StrEnum):
    """Trajectory file written by a run: ``kitti`` (12 numbers a line) or ``tum`` (timestamp, position, quaternion)."""

    kitti = "kitti"
    tum = "tum"


@dataclass
class ImgResConfig:
    """Working size the frames are resized to (intrinsics follow); both None: the data's native size."""

    height: int | None = 192
    width: int | None = 640


@dataclass
class DataConfig:
    """Fields every dataset kind has: ``seq`` (sequence name), frame range ``[start, end)``."""

    kind: str = MISSING
    seq: str | None = None
    start: int | None = None
    end: int | None = None


@dataclass
class SyntheticDataConfig(DataConfig):
    """The built-in synthetic world (:class:`dfvo.data.synthetic.SyntheticWorld`); ``seq`` is the scenario."""

    kind: str = "synthetic"
    seq: str | None = "drive"
    seed: int = 0
    num_frames: int = 30
    exposure_change: bool = False
    noise_std: float = 0.0


@dataclass
class KittiOdomDataConfig(DataConfig):
    """KITTI odometry: ``root/sequences/SEQ/`` (image_2, else image_0; calib.txt), ground truth
    ``root/poses/SEQ.txt`` when present. ``root`` null: the environment variable ``DFVO_KITTI_ODOM_ROOT``."""

    kind: str = "kitti_odom"
    root: str | None = None
    camera: str = "auto"


@dataclass
class KittiRawDataConfig(DataConfig):
    """KITTI raw: ``root/DATE/DATE_drive_XXXX_sync/image_02/data``; ``seq`` the drive name; OXTS ground truth when
    present. ``root`` null: the environment variable ``DFVO_KITTI_RAW_ROOT``."""

    kind: str = "kitti_raw"
    root: str | None = None


@dataclass
class FolderDataConfig(DataConfig):
    """Your own frames: a folder of PNG/JPEG images, pinhole intrinsics in pixels of the stored images, optional
    OpenCV radial-tangential distortion ``[k1, k2, p1, p2(, k3)]``."""

    kind: str = "folder"
    root: str | None = None
    fx: float | None = None
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    dist: list[float] | None = None


DATA_SCHEMAS: dict[str, type[DataConfig]] = {
    "synthetic": SyntheticDataConfig,
    "kitti_odom": KittiOdomDataConfig,
    "kitti_raw": KittiRawDataConfig,
    "folder": FolderDataConfig,
}


@dataclass
class TensorboardConfig:
    """``OUT/tensorboard``: per-frame flow, inconsistency, correspondences, depth (every ``every`` frames)."""

    enabled: bool = False
    every: int = 10


@dataclass
class ViewerConfig:
    """``kind: rerun`` writes ``OUT/run.rrd`` as frames are processed (``spawn``: also open the live viewer)."""

    kind: str = "none"
    spawn: bool = False


@dataclass
class InferConfig:
    """Root of ``infer.py``'s configuration.

    Attributes:
        data: the dataset (one of :data:`DATA_SCHEMAS`, chosen with ``data=KIND``).
        img_res: working size. flow, depth: the sources. tracker: the odometry loop.
        seq: sequence (KITTI ``06``, a raw drive, a synthetic scenario); null: ``data.seq``. A KITTI odometry
            number (``seq=10``) with the default data runs KITTI odometry from ``DFVO_KITTI_ODOM_ROOT``.
        out_dir: output folder (default ``outputs/infer/<time>``; with ``-m`` each job writes a subfolder named by
            its overrides).
        align: trajectory alignment for ``metrics.json``. pose_format: trajectory file format.
        batch_size: frame pairs per network batch. device: ``cpu``, ``cuda``, ``auto`` (CUDA when available).
        num_threads: torch threads (null: torch's default). progress: progress bar on stderr.
        verbose: full tracebacks for expected errors (bad data, checkpoint, setting).
        warn_fallback_rate: loud warning when more frames than this fell back to constant motion / PnP failed.
        online_finetune: self-supervised flow finetuning on the sequence (network flow only); online: its settings.
        tensorboard, viewer: optional per-frame logging.
    """

    data: Any = MISSING
    img_res: ImgResConfig = field(default_factory=ImgResConfig)
    flow: FlowSourceConfig = field(default_factory=FlowSourceConfig)
    depth: DepthSourceConfig = field(default_factory=DepthSourceConfig)
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    seq: str | None = None
    out_dir: str | None = None
    align: AlignMode = AlignMode.six_dof
    pose_format: PoseFormat = PoseFormat.kitti
    batch_size: int = 4
    device: str = "cpu"
    num_threads: int | None = None
    progress: bool = True
    verbose: bool = False
    warn_fallback_rate: float = 0.2
    online_finetune: bool = False
    online: OnlineFlowConfig = field(default_factory=OnlineFlowConfig)
    tensorboard: TensorboardConfig = field(default_factory=TensorboardConfig)
    viewer: ViewerConfig = field(default_factory=ViewerConfig)


def register_configs() -> None:
    """Store the schemas in Hydra's ConfigStore (idempotent)."""
    cs = ConfigStore.instance()
    cs.store(name="infer_schema", node=InferConfig)
    for kind, schema in DATA_SCHEMAS.items():
        cs.store(group="data/schema", name=kind, node=schema)


def typed(node: DictConfig | Any, schema: type | None = None) -> Any:
    """A config node as its dataclass instance (validated by the dataclass' ``__post_init__``); ``schema`` merges an
    untyped node (e.g. a ``data`` node built in Python) into that dataclass first."""
    if schema is not None and OmegaConf.get_type(node) is not schema:
        node = OmegaConf.merge(OmegaConf.structured(schema), node)
    return OmegaConf.to_object(node)


register_configs()
