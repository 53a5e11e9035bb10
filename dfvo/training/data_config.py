"""Typed configuration of the training data (``data=KIND`` of ``dfvo/conf/train/data/``): one schema per kind.

Each ``data/KIND.yaml`` is ``defaults: [schema/KIND@_here_, _self_]`` plus what differs; the schemas here hold every
field and default (registered by :func:`dfvo.training.config.register_configs`). Dataset roots are never derived from
the repository layout: ``data.root=`` or the kind's environment variable (:attr:`TrainDataConfig.ROOT_ENV`, e.g.
``DFVO_KITTI_RAW_ROOT``), resolved by :func:`data_root` when the data is built.

The inference data schemas (:mod:`dfvo.inference.config`: the one sequence ``infer.py`` tracks) are the other family
of ``data`` nodes; both are chosen by ``data=KIND`` and discriminated by the field ``kind``, and the training classes
are named ``*TrainDataConfig`` (registered under ``data/train_schema``) so the two never share a name.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from enum import StrEnum
from typing import ClassVar

from omegaconf import MISSING

from dfvo.data.calibration import KITTI_CAMERA_HEIGHT
from dfvo.data.held_out import HELD_OUT_DRIVES
from dfvo.validation import positive

__all__ = ["CropMode", "TrainDataConfig", "WorldsTrainDataConfig", "SyntheticTrainDataConfig",
           "KittiRawTrainDataConfig", "KittiOdomTrainDataConfig", "KittiRawSyntheticTrainDataConfig",
           "FlowMixTrainDataConfig",
           "FlowPairTrainDataConfig", "FlyingChairsTrainDataConfig", "FlyingThingsTrainDataConfig",
           "SintelTrainDataConfig", "KittiFlowTrainDataConfig", "TRAIN_DATA_SCHEMAS", "data_root"]


class CropMode(StrEnum):
    """Training crop of the flow datasets (validation is always centred)."""

    random = "random"
    center = "center"


@dataclass
class TrainDataConfig:
    """Fields of every training dataset.

    Attributes:
        kind: the dataset kind (a key of :data:`TRAIN_DATA_SCHEMAS`; set by its schema).
        height, width: working size the frames are resized to (flow pair datasets: the crop).
        batch_size: samples per batch (per process under DDP; on a GPU raise it, e.g. ``data.batch_size=16``).
        num_workers: DataLoader worker processes. seed: shuffling (and augmentation) seed.
        max_train_samples: train on the first N samples only (null: all).
        val_seeds, val_num_frames, val_every: validation on synthetic worlds (true depth and flow; every
            ``val_every``-th sample); ``val_seeds: []``: no synthetic validation.
    """

    ROOT_ENV: ClassVar[str | None] = None  # environment variable giving the root once for all commands

    kind: str = MISSING
    height: int | None = 192
    width: int | None = 640
    batch_size: int = 4
    num_workers: int = 0
    seed: int = 0
    max_train_samples: int | None = None
    val_seeds: list[int] = field(default_factory=lambda: [1000])
    val_num_frames: int = 12
    val_every: int = 1

    def __post_init__(self) -> None:
        expected = next((k for k, v in TRAIN_DATA_SCHEMAS.items() if v is type(self)), None)
        if expected is not None and self.kind != expected:
            raise ValueError(f"data.kind={self.kind!r}; the {type(self).__name__} schema is data={expected}")
        positive("data", height=self.height, width=self.width, batch_size=self.batch_size,
                  val_every=self.val_every, max_train_samples=self.max_train_samples)
        if self.num_workers < 0:
            raise ValueError(f"data.num_workers={self.num_workers}; expected >= 0")
        skips = getattr(self, "frame_skips", None)
        if skips is not None and (not skips or min(skips) < 1):
            raise ValueError(f"data.frame_skips={list(skips)}; expected a non-empty list of gaps >= 1 (e.g. [1, 2, 3])")


@dataclass
class WorldsTrainDataConfig(TrainDataConfig):
    """Synthetic training worlds (:mod:`dfvo.synthetic`): ``seeds`` (one world each, below 1000: seeds >= 1000
    are held-out evaluation worlds), ``num_frames`` each, ``scenario`` (names; seed s gets ``scenario[s % len]``),
    ``speed``/``turn_rate`` (null: the scenario's; ``[v]`` or a range ``[lo, hi]`` drawn per world), ``device``
    (``cuda``: render on the GPU, with ``num_workers: 0``), ``frame_skips`` (depth: snippets (k-s, k, k+s); flow:
    pairs (k, k+s), every s of the list), ``keep_frames`` (depth snippets: every frame rendered once and kept in
    memory, ~``worlds x num_frames x 7 x height x width x 4`` bytes per loading process, instead of rendered again
    for each snippet and epoch: the same samples; false for worlds that do not fit in memory), ``shadows`` (the
    training worlds' objects cast shadows under their sun: shadowed roads and facades of the true depth; the
    validation worlds stay without, comparable across settings)."""

    seeds: list[int] = field(default_factory=lambda: [0, 1, 2, 3])
    num_frames: int = 50
    scenario: list[str] = field(default_factory=lambda: ["drive"])
    speed: list[float] | None = None
    turn_rate: list[float] | None = None
    device: str = "cpu"
    frame_skips: list[int] = field(default_factory=lambda: [1])
    keep_frames: bool = True
    shadows: bool = False


@dataclass
class SyntheticTrainDataConfig(WorldsTrainDataConfig):
    """``data=synthetic``: the synthetic driving world (exact depth, flow and poses)."""

    kind: str = "synthetic"


@dataclass
class KittiRawTrainDataConfig(TrainDataConfig):
    """``data=kitti_raw``: KITTI raw drives ``ROOT/DATE/DATE_drive_XXXX_sync`` (colour stereo) as snippets
    (i-s, i, i+s) for every s of ``frame_skips``; ``drives`` null: every drive under the root. Validation on the
    synthetic worlds (true depth). ``frame_cache_dir``: the frames decoded at the working size once, into
    memory-mapped files there (:mod:`dfvo.data.frame_cache`; ``data/kitti_raw.yaml``: ``RUNS/frame_cache``); null:
    every frame decoded when read. ``held_out_drives``: drives left out when ``drives`` is null (default: the Eigen
    split's 28 test drives and drive 0005, :data:`dfvo.data.held_out.HELD_OUT_DRIVES`; a run that names one in
    ``drives`` trains on it and says so). ``depth_hints``: add each target frame's stereo-matcher depth
    (``depth_hint``, :mod:`dfvo.data.stereo_hints`; computed once into ``frame_cache_dir``) for
    ``model.w_depth_hints``. ``camera_height``: the cameras' height above the road in metres (KITTI's car:
    1.65), carried by every sample as ``camera_height`` for ``model.w_camera_height``; null: none."""

    ROOT_ENV: ClassVar[str | None] = "DFVO_KITTI_RAW_ROOT"

    kind: str = "kitti_raw"
    root: str | None = None
    drives: list[str] | None = None
    frame_skips: list[int] = field(default_factory=lambda: [1])
    frame_cache_dir: str | None = None
    held_out_drives: list[str] = field(default_factory=lambda: list(HELD_OUT_DRIVES))
    depth_hints: bool = False
    camera_height: float | None = KITTI_CAMERA_HEIGHT


@dataclass
class KittiOdomTrainDataConfig(TrainDataConfig):
    """``data=kitti_odom``: KITTI odometry ``ROOT/sequences/SEQ`` as snippets (i-s, i, i+s) (+ stereo when the right
    images exist)."""

    ROOT_ENV: ClassVar[str | None] = "DFVO_KITTI_ODOM_ROOT"

    kind: str = "kitti_odom"
    root: str | None = None
    sequences: list[str] = field(default_factory=lambda: ["06"])
    frame_skips: list[int] = field(default_factory=lambda: [1])


@dataclass
class KittiRawSyntheticTrainDataConfig(WorldsTrainDataConfig):
    """``data=kitti_raw_synthetic``: KITTI raw drives and synthetic worlds in one training set (``frame_skips``
    applies to both; ``frame_cache_dir``, ``camera_height`` and ``depth_hints`` as ``data=kitti_raw``, the height and
    the hints for the KITTI samples alone: the worlds' samples have their exact depth, and no hint, 0, in a mixed
    batch)."""

    ROOT_ENV: ClassVar[str | None] = "DFVO_KITTI_RAW_ROOT"

    kind: str = "kitti_raw_synthetic"
    root: str | None = None
    drives: list[str] | None = None
    frame_cache_dir: str | None = None
    held_out_drives: list[str] = field(default_factory=lambda: list(HELD_OUT_DRIVES))
    camera_height: float | None = KITTI_CAMERA_HEIGHT
    depth_hints: bool = False


def _training_seeds() -> list[int]:
    return list(range(24))


def _all_scenarios() -> list[str]:
    return ["drive", "city", "straight", "highway"]


@dataclass
class FlowMixTrainDataConfig(TrainDataConfig):
    """``data=flow_mix``: the step batches of step-scheduled flow training (``model=flow_mix``; the data module
    :class:`dfvo.training.flow_data.FlowMixDataModule`, the render cache :mod:`dfvo.training.flow_renders`).

    Each training step is one batch drawn at random (with replacement, from a generator seeded by ``seed``, the step
    and the DDP rank, so a resumed run draws the same): ``batch_size`` supervised pairs of the synthetic training
    worlds when the step's phase has ``synthetic``, and ``kitti_batch_size`` KITTI raw pairs when it has ``kitti``.

    Attributes:
        height, width: the network's input size (96x320 for the shipped networks); frames are rendered and decoded at
            the working size ``render_scale`` times larger (640x192) and resized the way inference resizes.
        seeds, num_frames, scenario, speed, frame_skips: the synthetic training worlds (one per seed, below 1000;
            seed s gets ``scenario[s % len]``; ``speed`` m/frame, ``[v]`` or a range ``[lo, hi]`` drawn per world,
            null: the scenario's; a car's speed: the hand-held scenarios always move at their own pace), pairs
            (k, k+s) for every s of ``frame_skips`` (also the KITTI pairs' gaps).
        max_flow: drop synthetic pairs whose largest true flow exceeds this many working-size pixels (null: keep all).
        render_scale: working size / network size. sensor_variation: exposure changes and sensor noise per world.
        device: where the worlds render (``cuda``: on the GPU). cache_dir: the render cache folder (null: render at
            every start, keep nothing).
        root, drives: KITTI raw (``ROOT/DATE/DATE_drive_XXXX_sync``, or one DATE folder; ``drives`` null: all but
            ``held_out_drives``, as ``data=kitti_raw``), needed when a phase has ``kitti``; ``root`` null: the
            environment variable ``DFVO_KITTI_RAW_ROOT``.
        kitti_batch_size: KITTI pairs per step in phases with ``kitti``.
        max_train_samples: use only the first N synthetic pairs (rendering stops at the world that completes them).
        val_seeds, val_scenarios, val_num_frames, val_every: the held-out evaluation: per scenario, the pairs (k, k+1),
            k = 0, val_every, ... of the worlds ``val_seeds`` at the working size, through the inference resizing.
    """

    ROOT_ENV: ClassVar[str | None] = "DFVO_KITTI_RAW_ROOT"

    kind: str = "flow_mix"
    height: int | None = 96
    width: int | None = 320
    seeds: list[int] = field(default_factory=_training_seeds)
    num_frames: int = 40
    scenario: list[str] = field(default_factory=_all_scenarios)
    speed: list[float] | None = field(default_factory=lambda: [0.3, 3.0])
    frame_skips: list[int] = field(default_factory=lambda: [1, 2, 3])
    max_flow: float | None = 160.0
    render_scale: int = 2
    sensor_variation: bool = True
    device: str = "cpu"
    cache_dir: str | None = None
    root: str | None = None
    drives: list[str] | None = None
    held_out_drives: list[str] = field(default_factory=lambda: list(HELD_OUT_DRIVES))
    kitti_batch_size: int = 2
    val_seeds: list[int] = field(default_factory=lambda: [1002, 1003])
    val_scenarios: list[str] = field(default_factory=_all_scenarios)
    val_every: int = 2

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.height is None or self.width is None:
            raise ValueError("data=flow_mix needs data.height and data.width (the network's input size)")
        positive("data", render_scale=self.render_scale, kitti_batch_size=self.kitti_batch_size,
                  max_flow=self.max_flow)
        if self.num_frames < 2 or max(self.frame_skips) >= self.num_frames:
            raise ValueError(f"data.num_frames={self.num_frames} with data.frame_skips={list(self.frame_skips)}; "
                             "expected more frames than the largest gap")
        if not self.scenario:
            raise ValueError("data.scenario=[]; expected at least one scenario")
        if self.speed is not None and len(self.speed) not in (1, 2):
            raise ValueError(f"data.speed={list(self.speed)}; expected null, [v] or [lo, hi] (m/frame)")


@dataclass
class FlowPairTrainDataConfig(TrainDataConfig):
    """Frame pairs with true flow (:mod:`dfvo.data.flow_datasets`): ``height``/``width`` the crop (both null: no
    crop), ``resize`` ``[h, w]`` before cropping (flow vectors scaled; null: native size), ``crop`` for training,
    ``train_split``, ``val_split`` (the dataset's own validation pairs, centre crop; null: the synthetic worlds of
    ``val_seeds``)."""

    root: str | None = None
    resize: list[int] | None = None
    crop: CropMode = CropMode.random
    train_split: str = "train"
    val_split: str | None = None


@dataclass
class FlyingChairsTrainDataConfig(FlowPairTrainDataConfig):
    """``data=flyingchairs``: ``ROOT/data/NNNNN_img1.ppm, _img2.ppm, _flow.flo`` and ``FlyingChairs_train_val.txt``
    (ROOT = FlyingChairs_release). Forward flow only. FlowNet's 320x448 crops of the 384x512 images."""

    ROOT_ENV: ClassVar[str | None] = "DFVO_FLYINGCHAIRS_ROOT"

    kind: str = "flyingchairs"
    height: int | None = 320
    width: int | None = 448
    val_split: str | None = "val"
    val_seeds: list[int] = field(default_factory=list)


@dataclass
class FlyingThingsTrainDataConfig(FlowPairTrainDataConfig):
    """``data=flyingthings``: FlyingThings3D ``frames_cleanpass|finalpass`` and ``optical_flow`` (forward and
    backward flow); ``dstype`` clean | final, ``cameras`` [left] / [right] / both, ``reverse`` also the reversed
    pairs. Crops of the 540x960 frames; TEST pairs as validation."""

    ROOT_ENV: ClassVar[str | None] = "DFVO_FLYINGTHINGS_ROOT"

    kind: str = "flyingthings"
    dstype: str = "clean"
    cameras: list[str] = field(default_factory=lambda: ["left"])
    reverse: bool = False
    height: int | None = 384
    width: int | None = 768
    val_split: str | None = "test"
    val_seeds: list[int] = field(default_factory=list)


@dataclass
class SintelTrainDataConfig(FlowPairTrainDataConfig):
    """``data=sintel``: MPI-Sintel ``training/clean|final/SCENE`` with ``training/flow``; ``scenes`` to train on
    (null: all), ``val_scenes`` with ``val_split: val``. Forward flow only; crops of the 436x1024 frames."""

    ROOT_ENV: ClassVar[str | None] = "DFVO_SINTEL_ROOT"

    kind: str = "sintel"
    dstype: str = "clean"
    scenes: list[str] | None = None
    val_scenes: list[str] | None = None
    height: int | None = 384
    width: int | None = 768


@dataclass
class KittiFlowTrainDataConfig(FlowPairTrainDataConfig):
    """``data=kitti_flow``: KITTI flow 2015 / 2012 training pairs (``ROOT`` = ``data_scene_flow/training``), sparse
    true flow (``mask``: occ = all pixels with ground truth, noc = non-occluded), resized to the working size."""

    ROOT_ENV: ClassVar[str | None] = "DFVO_KITTI_FLOW_ROOT"

    kind: str = "kitti_flow"
    version: int = 2015
    mask: str = "occ"
    resize: list[int] | None = field(default_factory=lambda: [192, 640])


TRAIN_DATA_SCHEMAS: dict[str, type[TrainDataConfig]] = {
    "synthetic": SyntheticTrainDataConfig,
    "kitti_raw": KittiRawTrainDataConfig,
    "kitti_odom": KittiOdomTrainDataConfig,
    "kitti_raw_synthetic": KittiRawSyntheticTrainDataConfig,
    "flow_mix": FlowMixTrainDataConfig,
    "flyingchairs": FlyingChairsTrainDataConfig,
    "flyingthings": FlyingThingsTrainDataConfig,
    "sintel": SintelTrainDataConfig,
    "kitti_flow": KittiFlowTrainDataConfig,
}



def data_root(data: TrainDataConfig) -> str:
    """``data.root``, else the kind's environment variable; one line saying how to set it when neither is set."""
    root = getattr(data, "root", None)
    if root:
        return str(root)
    env = data.ROOT_ENV
    value = os.environ.get(env, "") if env else ""
    if not value:
        how = f"set the environment variable {env}=ROOT once or pass data.root=ROOT" if env else "pass data.root=ROOT"
        raise ValueError(f"data={data.kind} needs the dataset folder: {how}")
    return value
