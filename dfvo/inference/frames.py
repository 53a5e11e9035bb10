"""The frames an inference run reads: the ``data`` config opened as a :class:`~dfvo.data.sequence.FrameSequence`
at the working size.

Convention (of the sequence):
    ``FrameSequence.image(i)`` is (3,H,W) float in [0,1] at the working resolution, ``K`` (3,3) in its pixels,
    ``poses`` (N,4,4) float64 ``T_w_c`` of the left camera when ground truth exists (else None), ``world`` the
    :class:`~dfvo.synthetic.SyntheticWorld` for ``data=synthetic`` (oracle sources need it), ``timestamps``
    (N,) float64 seconds of each frame when the dataset has them (else None), ``frame_ids`` (N,) the frames'
    indices in the dataset's own list when a range or step selected them (else None).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dfvo.data.euroc import open_euroc
from dfvo.data.image_folder import ImageFolder
from dfvo.data.kitti_odometry import KittiOdometry, selects_kitti_odometry
from dfvo.data.kitti_raw import open_drives
from dfvo.data.pose_check import checked_poses
from dfvo.data.rosbag_input import open_rosbag
from dfvo.data.sequence import FrameSequence
from dfvo.data.transforms import resize_image
from dfvo.data.tum_rgbd import open_tum
from dfvo.data.video import open_video
from dfvo.data.working_size import aspect_change, working_size
from dfvo.geometry.camera import resize_intrinsics
from dfvo.inference.config import DATA_SCHEMAS, KittiOdomDataConfig
from dfvo.inference.ground_truth import attach_ground_truth
from dfvo.synthetic import KITTI_HW, SyntheticWorld

__all__ = ["FrameSequence", "build_sequence", "resolve_data", "working_hw", "at_working_size", "DATA_ROOT_ENV"]

log = logging.getLogger("dfvo.data")

# dataset kind -> environment variable that gives its root once for all commands
DATA_ROOT_ENV = {"kitti_odom": "DFVO_KITTI_ODOM_ROOT", "kitti_raw": "DFVO_KITTI_RAW_ROOT"}
SYNTHETIC_FRAME_PERIOD_S = 0.1  # the synthetic camera runs at KITTI's 10 Hz
MIN_WORKING_SIDE = 64  # pixels: a working size below this cannot be tracked (6-pixel grid cells, 2x2 network maps)


def resolve_data(data: Any, seq: str | int | None) -> tuple[Any, str | None]:
    """The dataset config and sequence name a run uses.

    ``seq`` overrides ``data.seq``. A KITTI odometry sequence number (``seq=10``) with the default synthetic data
    selects KITTI odometry (the synthetic world's sequences are scenario names), with its root from
    ``DFVO_KITTI_ODOM_ROOT`` and the settings both kinds have (``data.start``, ``end``, ``step``, ``camera_height``)
    as given. A missing ``data.root`` is taken from the kind's environment variable
    (:data:`DATA_ROOT_ENV`).

    Args:
        data: a typed data config (:mod:`dfvo.inference.config`).
        seq: the command line's ``seq`` (None: ``data.seq``).

    Returns:
        (data config, sequence name or None).

    Raises:
        ValueError: a dataset that needs a root has neither ``data.root`` nor its environment variable (one line
            saying how to set it).
    """
    name = None if seq is None else str(seq)
    if selects_kitti_odometry(data.kind, name):
        # every setting the two kinds share that the command line gave (start, end, step, camera_height) carries over
        shared = {f.name for f in dataclasses.fields(KittiOdomDataConfig)} - {"kind", "seq", "root"}
        data = KittiOdomDataConfig(**{k: getattr(data, k) for k in shared
                                      if getattr(data, k, None) is not None})
    name = name if name is not None else data.seq
    if data.kind == "kitti_odom" and name is not None and name.isdigit():
        name = name.zfill(2)
    env = DATA_ROOT_ENV.get(data.kind)
    if getattr(data, "root", "") is None:
        root = os.environ.get(env) if env else None
        if not root:
            how = f"set the environment variable {env}=ROOT once or pass data.root=ROOT" if env else \
                "pass data.root=FOLDER"
            what = f"KITTI odometry sequence {name}" if data.kind == "kitti_odom" and name else f"data={data.kind}"
            raise ValueError(f"{what} needs the dataset folder: {how}")
        data.root = root
    return data, name


def working_hw(img_res: Any, native_hw: tuple[int, int]) -> tuple[int, int]:
    """The working (height, width) that ``img_res`` (see :class:`dfvo.inference.config.ImgResConfig`) gives frames of
    ``native_hw``."""
    hw = _working_hw(img_res, native_hw)
    if min(hw) < MIN_WORKING_SIDE:
        h0, w0 = native_hw
        need = math.ceil(MIN_WORKING_SIDE * w0 / min(h0, w0))
        given = ", ".join(f"img_res.{k}={getattr(img_res, k)}" for k in ("width", "height", "scale")
                          if getattr(img_res, k, None) is not None)
        raise ValueError(f"{given or 'img_res'}: frames of {w0}x{h0} would be tracked at {hw[1]}x{hw[0]}; expected at "
                         f"least {MIN_WORKING_SIDE} pixels on each side (the 10x10 correspondence grid, the networks' "
                         f"32-pixel steps): give img_res.width={need} or more (or a larger img_res.scale)")
    return hw


def _working_hw(img_res: Any, native_hw: tuple[int, int]) -> tuple[int, int]:
    h, w, scale = img_res.height, img_res.width, getattr(img_res, "scale", None)
    if scale is not None:
        if h is not None or w is not None:
            raise ValueError(f"img_res: give scale={scale} alone (height={h}, width={w} must be null)")
        return working_size(native_hw, scale=float(scale))
    if h is not None and w is not None:
        if h <= 0 or w <= 0:
            raise ValueError(f"img_res: height={h}, width={w}; expected positive sizes")
        return int(h), int(w)
    if w is not None:
        return working_size(native_hw, width=int(w))
    if h is not None:
        raise ValueError(f"img_res: height={h} alone; give width= (the height follows the aspect ratio), both, or "
                         "scale=")
    return int(native_hw[0]), int(native_hw[1])


def at_working_size(seq: FrameSequence, hw: tuple[int, int]) -> FrameSequence:
    """``seq`` with its frames resized to ``hw`` (bilinear, :func:`dfvo.data.transforms.resize_with_intrinsics`) and
    its intrinsics following exactly; a change of aspect ratio beyond 2 % is logged once."""
    native = tuple(int(v) for v in seq.image(0).shape[-2:])
    if native == tuple(hw):
        return seq
    change = aspect_change(native, hw)
    if abs(change) > 0.02:
        log.warning("img_res: frames of %dx%d are resized to %dx%d, changing their aspect ratio by %+.0f%% (both "
                    "sides are multiples of 32 for the networks: img_res.width alone keeps the aspect as closely as "
                    "that allows, a larger width closer)", native[1], native[0], hw[1], hw[0], 100 * change)
    load = seq.load
    K = resize_intrinsics(seq.K, native, tuple(hw))
    return replace(seq, K=K, load=lambda i: resize_image(load(i), int(hw[0]), int(hw[1])))


def build_sequence(data: Any, seq: str | int | None, img_res: Any) -> FrameSequence:
    """Open the sequence described by a typed data config (:data:`dfvo.inference.config.DATA_SCHEMAS`) at the working
    size ``img_res``.

    Args:
        data: the ``data`` node (typed), ``seq`` the command line's sequence (see :func:`resolve_data`),
            ``img_res`` the working size (:class:`dfvo.inference.config.ImgResConfig`).

    Raises:
        ValueError: unknown ``data.kind``, missing root, bad sizes; dataset errors name the path.
    """
    if data.kind not in DATA_SCHEMAS:
        raise ValueError(f"data.kind={data.kind!r}; expected one of {tuple(DATA_SCHEMAS)}")
    if data.kind == "stream":
        raise ValueError("data=stream is a live source, read frame by frame (dfvo.inference.live.run_live), not a "
                         "sequence")
    _check_range(data)
    data, name = resolve_data(data, seq)
    if data.kind == "synthetic":  # rendered at the working size directly
        return _synthetic(data, name, working_hw(img_res, KITTI_HW))
    opened = _open_native(data, name)
    opened = replace(opened, poses=checked_poses(opened.poses, _ground_truth_source(data, name)))
    return at_working_size(opened, working_hw(img_res, tuple(opened.image(0).shape[-2:])))


def _ground_truth_source(data: Any, name: str | None) -> str:
    """Where the ground truth of a native dataset comes from, for the warning lines of
    :func:`dfvo.data.pose_check.checked_poses`."""
    if getattr(data, "gt", None):
        return f"data.gt={data.gt}"
    if getattr(data, "gt_topic", None):
        return f"data.gt_topic={data.gt_topic} of {data.path}"
    root = getattr(data, "root", None)  # data=video and data=rosbag have a path instead
    where = {"kitti_odom": f"{root}/poses/{name}.txt", "kitti_raw": f"{root} drive {name} (oxts)",
             "euroc": f"{root} (state_groundtruth_estimate0)", "tum": f"{root}/groundtruth.txt"}
    return where.get(data.kind, f"data={data.kind} ground truth")


def _check_range(data: Any) -> None:
    """``data.step`` must be a positive number of frames (0 or negative would stop or run the footage backwards)."""
    if data.step is not None and int(data.step) < 1:
        raise ValueError(f"data.step={data.step}; expected a positive integer (every step-th frame, 1: every frame; "
                         "the footage is always read forwards)")


def _range(data: Any) -> dict[str, int | None]:
    return {"start": data.start, "end": data.end, "step": data.step}


def _open_native(data: Any, name: str | None) -> FrameSequence:
    sel = slice(data.start, data.end, data.step)
    if data.kind == "kitti_odom":
        if name is None:
            raise ValueError("data=kitti_odom needs seq=NN (e.g. seq=06)")
        ds = KittiOdometry(data.root, name, camera=data.camera, frames=sel, stereo=False)
        return FrameSequence(ds.sequence, len(ds), ds.intrinsics.float(), lambda i: ds[i]["image"], ds.poses,
                             timestamps=ds.timestamps)
    if data.kind == "kitti_raw":
        return _kitti_raw(data.root, name, sel)
    if data.kind == "euroc":
        return open_euroc(data.root, camera=data.camera, undistort=data.undistort, gt_tolerance=data.gt_tolerance,
                          unmatched=data.unmatched, **_range(data))
    if data.kind == "tum":
        return open_tum(data.root, fx=data.fx, fy=data.fy, cx=data.cx, cy=data.cy, dist=data.dist,
                        camera=data.camera, undistort=data.undistort, gt_tolerance=data.gt_tolerance,
                        unmatched=data.unmatched, **_range(data))
    if data.kind == "video":
        _require_intrinsics(data)
        if not data.path:
            raise ValueError("data=video needs data.path=FILE (a video file such as .mp4 or .mkv)")
        opened = open_video(data.path, fx=data.fx, fy=data.fy, cx=data.cx, cy=data.cy, dist=data.dist,
                            **_range(data))
        return _with_ground_truth(opened, data)
    if data.kind == "rosbag":
        if not data.path:
            raise ValueError("data=rosbag needs data.path=BAG (a ROS 1 .bag file, a ROS 2 bag folder, or its "
                             ".db3/.mcap file)")
        opened = open_rosbag(data.path, topic=data.topic, camera_info_topic=data.camera_info_topic, fx=data.fx,
                             fy=data.fy, cx=data.cx, cy=data.cy, dist=data.dist, gt_topic=data.gt_topic,
                             gt_parent_frame=data.gt_parent_frame, gt_child_frame=data.gt_child_frame,
                             gt_camera_transform=data.gt_camera_transform, gt_tolerance=data.gt_tolerance,
                             **_range(data))
        return _with_ground_truth(opened, data)
    return _with_ground_truth(_folder(data, name, sel), data)


def _require_intrinsics(data: Any) -> None:
    for key in ("fx", "fy", "cx", "cy"):
        if getattr(data, key) is None:
            raise ValueError(f"data={data.kind} needs data.{key}= (intrinsics in pixels of the stored frames)")


def _with_ground_truth(seq: FrameSequence, data: Any) -> FrameSequence:
    """``seq`` with the ground truth of ``data.gt`` (own frames and videos), when given."""
    if not getattr(data, "gt", None):
        return seq
    return attach_ground_truth(seq, data)


def _folder(data: Any, name: str | None, sel: slice) -> FrameSequence:
    if not data.root:
        raise ValueError("data=folder needs data.root=FOLDER (a folder of PNG/JPEG frames)")
    _require_intrinsics(data)
    ds = ImageFolder(data.root, data.fx, data.fy, data.cx, data.cy, dist=data.dist)
    ids = list(range(len(ds)))[sel]
    if len(ids) < 2:
        raise ValueError(f"data=folder {data.root}: data.start={data.start}, data.end={data.end} select {len(ids)} of "
                         f"its {len(ds)} frames; expected at least 2 (frames 0..{len(ds) - 1}, end exclusive)")
    seq = FrameSequence(name or Path(data.root).name, len(ids), ds.intrinsics.float(), lambda i: ds[ids[i]]["image"])
    seq.frame_ids = np.asarray(ids)
    return seq


def _synthetic(data: Any, scenario: str | None, hw: tuple[int, int]) -> FrameSequence:
    scenario = scenario or "drive"
    world = SyntheticWorld(seed=data.seed, num_frames=data.num_frames, height=hw[0], width=hw[1],
                           exposure_change=data.exposure_change, noise_std=data.noise_std, scenario=scenario,
                           speed=_range_or_value(data.speed, "data.speed"),
                           turn_rate=_range_or_value(data.turn_rate, "data.turn_rate"))
    ids = list(range(len(world)))[slice(data.start, data.end, data.step)]
    if len(ids) < 2:
        raise ValueError(f"data=synthetic: frames {data.start}..{data.end} select {len(ids)} frames; expected at "
                         "least 2")
    if data.step not in (None, 1):
        raise ValueError(f"data=synthetic: data.step={data.step}; the oracle sources need consecutive frames")
    poses = world.poses().numpy()[ids]
    name = f"synthetic_{scenario}_s{world.seed}"
    times = np.asarray(ids, dtype=np.float64) * SYNTHETIC_FRAME_PERIOD_S
    return FrameSequence(name, len(ids), world.intrinsics().float(), lambda i: world.image(ids[i]), poses,
                         _OffsetWorld(world, ids[0]), timestamps=times)


def _range_or_value(value: Any, setting: str) -> float | tuple[float, float] | None:
    """A setting given as a number or a ``[low, high]`` range, as SyntheticWorld takes it."""
    if value is None or isinstance(value, int | float):
        return value
    values = [float(v) for v in value]
    if len(values) != 2:
        raise ValueError(f"{setting}={list(value)}; expected a number or a [low, high] range")
    return values[0], values[1]


class _OffsetWorld:
    """A synthetic world seen from frame ``offset`` on (oracle sources index the sequence, not the world)."""

    def __init__(self, world: Any, offset: int) -> None:
        self.world, self.offset = world, offset

    def flow(self, i: int, j: int) -> tuple[torch.Tensor, torch.Tensor]:
        return self.world.flow(i + self.offset, j + self.offset)

    def depth(self, i: int) -> torch.Tensor:
        return self.world.depth(i + self.offset)


def _kitti_raw(root: str, seq: str | None, sel: slice) -> FrameSequence:
    drives = [seq] if seq is not None else None
    found = open_drives(root, drives, stereo=False)  # the left camera alone
    if len(found) != 1:
        names = [d.dir.name for d in found]
        raise ValueError(f"data=kitti_raw under {root}: {names} drives found; choose one with seq=DRIVE")
    drive = found[0]
    ids = list(range(len(drive.left)))[sel]
    poses = drive.poses[ids] if drive.poses is not None else None
    stamps = drive.timestamps[ids] if drive.timestamps is not None else None
    return FrameSequence(drive.dir.name, len(ids), drive.K.float(), lambda i: drive.load(drive.left[ids[i]]), poses,
                         timestamps=stamps, frame_ids=np.asarray(ids))
