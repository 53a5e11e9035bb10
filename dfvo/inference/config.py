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

__all__ = ["ALIGN_MODES", "PoseFormat", "ImgResConfig", "DataConfig", "SyntheticDataConfig", "KittiOdomDataConfig",
           "KittiRawDataConfig", "FolderDataConfig", "EurocDataConfig", "TumDataConfig", "VideoDataConfig",
           "DATA_SCHEMAS", "TensorboardConfig", "ViewerConfig", "InferConfig", "register_configs", "typed"]


ALIGN_MODES = ("6dof", "7dof", "scale")  # 6dof: metric depth; 7dof: monocular, up to scale; scale: scale only


class PoseFormat(StrEnum):
    """Trajectory file written by a run: ``kitti`` (12 numbers a line) or ``tum`` (timestamp, position, quaternion)."""

    kitti = "kitti"
    tum = "tum"


@dataclass
class ImgResConfig:
    """Working size the frames are resized to (intrinsics follow exactly).

    ``width`` alone keeps the frames' aspect ratio (the height follows, both rounded to multiples of 32, the
    networks' stride: KITTI 1241x376 → 640x192, EuRoC 752x480 → 640x416); ``scale`` alone scales both sides;
    ``height`` and ``width`` together force that size (an aspect change is reported); all null: native size.
    ``img_res=low`` gives ``width: 640`` through the resolver ``dfvo.width_unless_scaled``, so ``img_res.scale=0.5``
    alone replaces that default width; a ``width`` given on the command line with ``scale`` is a contradiction.
    """

    height: int | None = None
    width: int | None = 640
    scale: float | None = None


@dataclass
class DataConfig:
    """Fields every dataset kind has: ``seq`` (sequence name), frames ``[start, end)`` every ``step``-th, and ground
    truth for data that has none of its own: ``gt`` (a trajectory file), ``gt_format`` (``auto``, ``kitti``,
    ``tum``, ``euroc``), ``times`` (a file of frame timestamps in seconds, one per line, to associate a timestamped
    ``gt`` with the frames). ``camera_height``: the camera's height above the road in metres (KITTI 1.65), null:
    unknown; when set and ``tracker.scale.camera_height`` is null the tracker uses it (the camera-height scale,
    :mod:`dfvo.tracking.scale_fusion`): ``data.camera_height=null`` turns it off for a dataset that sets it."""

    kind: str = MISSING
    seq: str | None = None
    start: int | None = None
    end: int | None = None
    step: int | None = None
    camera_height: float | None = None


@dataclass
class SyntheticDataConfig(DataConfig):
    """The built-in synthetic world (:class:`dfvo.data.synthetic.SyntheticWorld`); ``seq`` is the scenario (drive,
    city, straight, highway, still, rotation, planar, moving_car); ``speed`` (metres per frame, a value or a
    ``[low, high]`` range drawn per world; null: the scenario's default) and ``turn_rate`` (degrees per frame, the
    same) reshape the street scenarios. Seeds >= 1000 are never used for training (held-out worlds)."""

    kind: str = "synthetic"
    seq: str | None = "drive"
    seed: int = 0
    num_frames: int = 30
    exposure_change: bool = False
    noise_std: float = 0.0
    speed: Any = None
    turn_rate: Any = None


@dataclass
class KittiOdomDataConfig(DataConfig):
    """KITTI odometry: ``root/sequences/SEQ/`` (image_2, else image_0; calib.txt), ground truth
    ``root/poses/SEQ.txt`` when present. ``root`` null: the environment variable ``DFVO_KITTI_ODOM_ROOT``."""

    kind: str = "kitti_odom"
    root: str | None = None
    camera: str = "auto"
    camera_height: float | None = 1.65  # the KITTI cars' camera above the road


@dataclass
class KittiRawDataConfig(DataConfig):
    """KITTI raw: ``root/DATE/DATE_drive_XXXX_sync/image_02/data``; ``seq`` the drive name; OXTS ground truth when
    present. ``root`` null: the environment variable ``DFVO_KITTI_RAW_ROOT``."""

    kind: str = "kitti_raw"
    root: str | None = None
    camera_height: float | None = 1.65  # the KITTI cars' camera above the road


@dataclass
class CameraDataConfig(DataConfig):
    """Pinhole intrinsics ``fx, fy, cx, cy`` in pixels of the stored frames and optional OpenCV radial-tangential
    distortion ``dist`` = ``[k1, k2, p1, p2(, k3)]`` (or 8 rational coefficients), for data that does not carry its
    own calibration."""

    fx: float | None = None
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    dist: list[float] | None = None


@dataclass
class OwnVideoDataConfig(CameraDataConfig):
    """Own frames or video, with optional ground truth ``gt`` (a trajectory file in ``gt_format``: auto, kitti, tum,
    euroc), associated with the frames by index, by 13-number frame index, or by nearest timestamp within
    ``gt_tolerance`` seconds (frame times from ``times``: a file, one line per frame, or the video container)."""

    gt: str | None = None
    gt_format: str = "auto"
    times: str | None = None
    gt_tolerance: float = 0.02


@dataclass
class FolderDataConfig(OwnVideoDataConfig):
    """Your own frames: ``root`` a folder of PNG/JPEG images (natural filename order)."""

    kind: str = "folder"
    root: str | None = None


@dataclass
class VideoDataConfig(OwnVideoDataConfig):
    """A video file ``path`` (decoded as a stream with PyAV: ``pip install "dfvo[video]"``); timestamps from the
    container."""

    kind: str = "video"
    path: str | None = None


@dataclass
class EurocDataConfig(DataConfig):
    """EuRoC MAV: ``root`` the sequence folder (or its ``mav0/``); intrinsics, distortion and the body→camera
    extrinsic ``T_BS`` from ``CAMERA/sensor.yaml``, timestamps from ``CAMERA/data.csv``, ground truth from
    ``state_groundtruth_estimate0/data.csv`` associated by nearest timestamp (``gt_tolerance`` seconds) and moved to
    the camera frame; ``unmatched``: ``trim`` (drop frames outside the ground truth), ``nan``, ``none``."""

    kind: str = "euroc"
    root: str | None = None
    camera: str = "cam0"
    undistort: bool = True
    gt_tolerance: float = 0.01
    unmatched: str = "trim"


@dataclass
class TumDataConfig(CameraDataConfig):
    """TUM RGB-D: ``root`` the sequence folder (``rgb.txt``, ``groundtruth.txt``); intrinsics given, or the published
    freiburg1/2/3 ones chosen from the folder name (``camera=auto``) or ``camera=fr1|fr2|fr3``."""

    kind: str = "tum"
    root: str | None = None
    camera: str = "auto"
    undistort: bool = True
    gt_tolerance: float = 0.02
    unmatched: str = "trim"


DATA_SCHEMAS: dict[str, type[DataConfig]] = {
    "synthetic": SyntheticDataConfig,
    "kitti_odom": KittiOdomDataConfig,
    "kitti_raw": KittiRawDataConfig,
    "folder": FolderDataConfig,
    "euroc": EurocDataConfig,
    "tum": TumDataConfig,
    "video": VideoDataConfig,
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
    align: str = "6dof"
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

    def __post_init__(self) -> None:
        if self.align not in ALIGN_MODES:
            raise ValueError(f"align={self.align!r}; expected one of {ALIGN_MODES} (6dof for metric depth, 7dof for "
                             "monocular depth)")
        if int(self.batch_size) < 1:
            raise ValueError(f"batch_size={self.batch_size}; expected a positive number of frame pairs")
        height = self.data.get("camera_height") if isinstance(self.data, DictConfig) else \
            getattr(self.data, "camera_height", None)
        from dfvo.inference.frames import selects_kitti_odometry

        kind = self.data.get("kind") if isinstance(self.data, DictConfig) else getattr(self.data, "kind", None)
        if selects_kitti_odometry(kind, self.seq):
            height = KittiOdomDataConfig.camera_height  # `seq=NN` alone runs KITTI odometry (frames.resolve_data)
        if height is not None and self.tracker.scale.camera_height is None and \
                self.tracker.scale.camera_height_from_data:  # the dataset's camera height
            if not float(height) > 0:
                raise ValueError(f"data.camera_height={height}; expected a height in metres > 0, or null (unknown)")
            self.tracker.scale.camera_height = float(height)


WIDTH_UNLESS_SCALED = "dfvo.width_unless_scaled"


def _width_unless_scaled(width: int | None, scale: float | None) -> int | None:
    """A group's default working width, dropped when ``img_res.scale`` is given (``scale=`` alone wins)."""
    return None if scale is not None else width


def register_configs() -> None:
    """Store the schemas in Hydra's ConfigStore and the resolver the ``img_res`` groups use (idempotent)."""
    OmegaConf.register_new_resolver(WIDTH_UNLESS_SCALED, _width_unless_scaled, replace=True)
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
