"""Typed configuration of ``infer.py`` / ``dfvo-infer``: the schema every YAML file of ``dfvo/conf/infer/`` fills.

The dataclasses here and in :mod:`dfvo.tracking.config`, :mod:`dfvo.sources.config` and
:mod:`dfvo.matching.flow_refinement` hold every default once; the YAML files only choose (``tracker=pnp``,
``data=kitti_odom``) and the command line overrides values. Hydra checks overrides against the schema, so a typo
(``tracker.scale.methd=...``) or a wrong type fails before anything runs.

``register_configs()`` stores the schemas in Hydra's ConfigStore (``infer_schema`` for the root, ``data/schema/KIND``
for each dataset kind); it runs on import of this module, before Hydra composes. The data schemas describe the one
sequence a run tracks and are discriminated by ``kind`` (``data=KIND``), like the training data schemas
(:mod:`dfvo.training.data_config`, classes named ``*TrainDataConfig``). Values are checked with
:mod:`dfvo.validation`, whose :func:`~dfvo.validation.typed` turns a node into its dataclass.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig, OmegaConf

from dfvo.data.calibration import KITTI_CAMERA_HEIGHT
from dfvo.data.kitti_odometry import selects_kitti_odometry
from dfvo.eval.alignment import AlignMode
from dfvo.sources.config import DepthSourceConfig, FlowSourceConfig
from dfvo.tracking.config import ScaleMethod, TrackerConfig, TrackerMode, check_camera_height
from dfvo.training.online_flow import OnlineFlowConfig
from dfvo.validation import check, choice, typed

__all__ = ["PoseFormat", "OverlapMode", "ViewerKind", "ImgResConfig", "DataConfig", "SyntheticDataConfig",
           "KittiOdomDataConfig", "KittiRawDataConfig", "FolderDataConfig", "EurocDataConfig", "TumDataConfig",
           "VideoDataConfig", "RosbagDataConfig", "StreamDataConfig", "DATA_SCHEMAS", "TensorboardConfig",
           "ViewerConfig", "RosbagStorage", "OutputConfig", "InferConfig", "register_configs", "typed",
           "compose_infer_config"]
# typed: dfvo.validation.typed, re-exported (scripts import it from here)


class PoseFormat(StrEnum):
    """Trajectory file written by a run: ``kitti`` (12 numbers a line) or ``tum`` (timestamp, position, quaternion)."""

    kitti = "kitti"
    tum = "tum"


class OverlapMode(StrEnum):
    """What runs beside the networks in the inference loop (``overlap``; :mod:`dfvo.inference.loop`): ``none`` (the
    serial loop), ``load`` (frames decoded in a loader thread), ``full`` (also the refinement and the tracker in a
    tracker thread) or ``auto`` (``full`` with two or more torch threads or on CUDA, else ``load``)."""

    none = "none"
    load = "load"
    full = "full"
    auto = "auto"


class ViewerKind(StrEnum):
    """``rerun`` records the run to ``OUT/run.rrd`` (``viewer.kind``); ``none`` does not."""

    none = "none"
    rerun = "rerun"


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
    """The built-in synthetic world (:class:`dfvo.synthetic.SyntheticWorld`); ``seq`` is the scenario (drive,
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
    camera_height: float | None = KITTI_CAMERA_HEIGHT


@dataclass
class KittiRawDataConfig(DataConfig):
    """KITTI raw: ``root/DATE/DATE_drive_XXXX_sync/image_02/data``; ``seq`` the drive name; OXTS ground truth when
    present. ``root`` null: the environment variable ``DFVO_KITTI_RAW_ROOT``."""

    kind: str = "kitti_raw"
    root: str | None = None
    camera_height: float | None = KITTI_CAMERA_HEIGHT


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
class RosbagDataConfig(OwnVideoDataConfig):
    """A ROS 1 ``.bag`` or a ROS 2 bag (its folder, or one ``.db3`` / ``.mcap`` file) read with the pure-Python
    ``rosbags`` library (``pip install "dfvo[ros]"``; :mod:`dfvo.data.rosbag_input`); frames in header-stamp order,
    timestamps from the header stamps.

    Attributes:
        path: the bag. topic: the image topic (``sensor_msgs/Image`` or ``CompressedImage``; null: the bag's only
            one).
        camera_info_topic: the ``sensor_msgs/CameraInfo`` giving the intrinsics and distortion (null: the one beside
            the image topic, else the bag's only one); ``fx, fy, cx, cy, dist`` given replace its values.
        gt_topic: ground truth in the bag (``geometry_msgs/PoseStamped``, ``nav_msgs/Odometry``,
            ``geometry_msgs/TransformStamped``, ``tf2_msgs/TFMessage``; null: none), associated by nearest stamp
            within ``gt_tolerance`` seconds.
        gt_parent_frame, gt_child_frame: the transform of a TF topic to use (null: the topic's only one);
            ``gt_child_frame`` also names the body whose pose a ``PoseStamped`` gives (null: the camera's).
        gt_camera_transform: the camera's pose in the ground truth's body frame, ``[x, y, z, qx, qy, qz, qw]``
            (metres, ROS order) or 16 numbers (4x4, row by row); null: from the bag's ``/tf_static``.
    """

    kind: str = "rosbag"
    path: str | None = None
    topic: str | None = None
    camera_info_topic: str | None = None
    gt_topic: str | None = None
    gt_parent_frame: str | None = None
    gt_child_frame: str | None = None
    gt_camera_transform: list[float] | None = None

    def __post_init__(self) -> None:
        check(not (self.gt and self.gt_topic), f"data.gt={self.gt} and data.gt_topic={self.gt_topic}: give one "
              "ground truth (a file, or a topic of the bag)")


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


@dataclass
class StreamDataConfig(CameraDataConfig):
    """A live source read as frames arrive (:mod:`dfvo.data.stream`, PyAV: ``pip install "dfvo[video]"``): ``url``
    is a camera device (``/dev/video0``, or ``0`` for it), a network stream (``rtsp://``, ``http://``, ``tcp://``,
    ``udp://``, ``srt://``) or a video file still being written (read on as it grows).

    Attributes:
        url: the source. input_format: PyAV/FFmpeg input format (null: from the url; ``/dev/video*`` uses ``v4l2``).
        options: FFmpeg options for opening it (e.g. ``{rtsp_transport: tcp}``, ``{video_size: 640x480}``).
        realtime: true: when tracking falls behind, keep the latest frame and drop the older ones (counted per frame
            in ``frames.csv`` and in ``summary.json``); false: every frame is tracked (the source waits, or
            buffers).
        timeout_s: opening, and waiting for the next frame, give up after this many seconds (a stalled source ends
            the run with its outputs complete).
        max_frames: stop after this many frames tracked (null: until the source ends).
        size_change: a frame of another size than the first is ``resize``d to it (noted once) or ``refuse``d (the
            run ends there with one line).
    """

    kind: str = "stream"
    seq: str | None = "stream"
    url: str | None = None
    input_format: str | None = None
    options: dict[str, str] = field(default_factory=dict)
    realtime: bool = True
    timeout_s: float = 10.0
    max_frames: int | None = None
    size_change: str = "resize"


DATA_SCHEMAS: dict[str, type[DataConfig]] = {
    "synthetic": SyntheticDataConfig,
    "kitti_odom": KittiOdomDataConfig,
    "kitti_raw": KittiRawDataConfig,
    "folder": FolderDataConfig,
    "euroc": EurocDataConfig,
    "tum": TumDataConfig,
    "video": VideoDataConfig,
    "rosbag": RosbagDataConfig,
    "stream": StreamDataConfig,
}


@dataclass
class TensorboardConfig:
    """``OUT/tensorboard``: per-frame flow, inconsistency, correspondences, depth (every ``every`` frames)."""

    enabled: bool = False
    every: int = 10


@dataclass
class ViewerConfig:
    """``kind: rerun`` writes ``OUT/run.rrd`` as frames are processed (``spawn``: also open the live viewer)."""

    kind: ViewerKind = ViewerKind.none
    spawn: bool = False


class RosbagStorage(StrEnum):
    """Storage of the output bag (``output.rosbag_storage``): ``sqlite3`` (``bag.db3``, what ``ros2 bag`` reads
    without plugins) or ``mcap`` (``bag.mcap``, which Foxglove opens directly)."""

    sqlite3 = "sqlite3"
    mcap = "mcap"


@dataclass
class OutputConfig:
    """Optional outputs of a run besides the trajectory, ``frames.csv`` and the summary.

    Attributes:
        rosbag: write ``OUT/bag/``, a ROS 2 bag (:mod:`dfvo.io.rosbag`, ``pip install "dfvo[ros]"``) with
            ``nav_msgs/msg/Odometry`` (pose, twist, covariances), ``tf2_msgs/msg/TFMessage`` and the ground truth,
            as frames are produced.
        rosbag_storage: the bag's storage (:class:`RosbagStorage`: ``sqlite3`` or ``mcap``).
        ros_world_frame, ros_camera_frame: the frame ids of the messages (the world is the first camera's frame).
    """

    rosbag: bool = False
    rosbag_storage: RosbagStorage = RosbagStorage.sqlite3
    ros_world_frame: str = "odom"
    ros_camera_frame: str = "camera"


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
        align: trajectory alignment for ``metrics.json`` (:class:`dfvo.eval.alignment.AlignMode`: ``6dof`` for
            metric depth, ``7dof`` for monocular depth, ``scale``, ``none``). pose_format: trajectory file format.
        batch_size: frame pairs per network batch. device: ``cpu``, ``cuda``, ``auto`` (CUDA when available).
        overlap: what runs beside the networks (:class:`OverlapMode`; ``load``: frame decoding in a thread, ``full``:
            also the refinement and the tracker, ``none``: serial, ``auto``: ``full`` with two or more torch threads
            or on CUDA, else ``load``); the poses are the same in every mode for the same threads per stage.
        cuda_sync: synchronise CUDA at every stage boundary, so each stage's time in ``summary.json`` is its GPU
            work (it serialises the GPU with the host: measure FPS without it).
        num_threads: torch threads (null: torch's default). progress: progress bar on stderr.
        verbose: full tracebacks for expected errors (bad data, checkpoint, setting).
        warn_fallback_rate: loud warning when more frames than this fell back to constant motion / PnP failed.
        online_finetune: self-supervised flow finetuning on the sequence (network flow only); online: its settings.
        tensorboard, viewer: optional per-frame logging. output: optional outputs (the ROS 2 bag).
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
    overlap: OverlapMode = OverlapMode.auto
    cuda_sync: bool = False
    num_threads: int | None = None
    progress: bool = True
    verbose: bool = False
    warn_fallback_rate: float = 0.2
    online_finetune: bool = False
    online: OnlineFlowConfig = field(default_factory=OnlineFlowConfig)
    tensorboard: TensorboardConfig = field(default_factory=TensorboardConfig)
    viewer: ViewerConfig = field(default_factory=ViewerConfig)
    output: OutputConfig = field(default_factory=OutputConfig)

    def __post_init__(self) -> None:
        choice(AlignMode, self.align, "align")
        check(self.num_threads is None or int(self.num_threads) >= 1,
              f"num_threads={self.num_threads}; expected a positive number of torch threads, or null (torch's default)")
        check(int(self.batch_size) >= 1, f"batch_size={self.batch_size}; expected a positive number of frame pairs")
        every = int(self.depth.every)  # >= 1: DepthSourceConfig's own check
        check(every == 1 or (self.tracker.scale.depth_views == 2 and self.tracker.mode != TrackerMode.pnp),
              f"depth.every={every} needs tracker.scale.depth_views=2 and a tracker with the E-tracker (tracker."
              f"scale.depth_views={self.tracker.scale.depth_views}, tracker.mode={self.tracker.mode}): each pair "
              "then has one frame with depth")
        check(every == 1 or self.tracker.scale.method != ScaleMethod.iterative,
              f"depth.every={every} needs tracker.scale.method=simple (the iterative scale re-selects on the earlier "
              "frame's depth, which every other frame lacks)")
        height = self.data.get("camera_height") if isinstance(self.data, DictConfig) else \
            getattr(self.data, "camera_height", None)
        kind = self.data.get("kind") if isinstance(self.data, DictConfig) else getattr(self.data, "kind", None)
        if selects_kitti_odometry(kind, self.seq) and height is None:
            height = KittiOdomDataConfig.camera_height  # `seq=NN` alone runs KITTI odometry (frames.resolve_data)
        check_camera_height(height, "data.camera_height")
        if height is not None and self.tracker.scale.camera_height is None and \
                self.tracker.scale.camera_height_from_data:  # the dataset's camera height
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


def compose_infer_config(overrides: list[str] | tuple[str, ...] = ()) -> DictConfig:
    """``infer.py``'s configuration composed by Hydra's compose API from the same config tree and defaults
    (``dfvo/conf/infer/infer.yaml``), with command-line style ``overrides`` (``["flow=dis",
    "tracker.scale.camera_height=1.65"]``). Works inside a running Hydra app too (its global state is restored).

    Raises:
        hydra.errors.HydraException / omegaconf errors: an unknown key, group option or a wrong type (as infer.py).
    """
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra
    from hydra.initialize import get_gh_backup, restore_gh_from_backup

    backup = get_gh_backup()
    GlobalHydra.instance().clear()
    try:
        with initialize_config_module(config_module="dfvo.conf.infer", version_base="1.3"):
            return compose(config_name="infer", overrides=list(overrides))
    finally:
        restore_gh_from_backup(backup)


register_configs()
