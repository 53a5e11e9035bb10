"""The frames an inference run reads: one sequence of any supported dataset behind one small interface.

Convention:
    ``FrameSequence.image(i)`` is (3,H,W) float in [0,1] at the working resolution, ``K`` (3,3) in its pixels,
    ``poses`` (N,4,4) float64 ``T_w_c`` of the left camera when ground truth exists (else None), ``world`` the
    :class:`~dfvo.data.synthetic.SyntheticWorld` for ``data=synthetic`` (oracle sources need it), ``timestamps``
    (N,) float64 seconds of each frame when the dataset has them (else None).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = ["FrameSequence", "build_sequence", "DATA_KINDS"]

DATA_KINDS = ("synthetic", "kitti_odom", "kitti_raw", "folder")


@dataclass
class FrameSequence:
    """One sequence ready for inference (see module docstring)."""

    name: str
    length: int
    K: torch.Tensor
    load: Callable[[int], torch.Tensor]
    poses: np.ndarray | None = None
    world: Any = None
    timestamps: np.ndarray | None = None

    def image(self, index: int) -> torch.Tensor:
        """(3,H,W) frame ``index``."""
        return self.load(index)


def _frames_slice(data: Any) -> slice:
    start, end = data.get("start"), data.get("end")
    return slice(start, end)


def _size(img_res: Any) -> tuple[int | None, int | None]:
    h, w = img_res.get("height"), img_res.get("width")
    if (h is None) != (w is None):
        raise ValueError(f"img_res: give both height and width or neither, got height={h}, width={w}")
    return h, w


def build_sequence(data: Any, seq: str | int | None, img_res: Any) -> FrameSequence:
    """Open sequence ``seq`` of the dataset described by the ``data`` config group.

    Args:
        data: ``kind`` in :data:`DATA_KINDS` plus its fields (``root``, synthetic ``seed``/``num_frames``/...,
            folder intrinsics, optional ``start``/``end`` frame range).
        seq: sequence name (KITTI odometry ``"06"``, a raw drive name, a synthetic scenario); None: the
            dataset's default ``data.seq``.
        img_res: ``height``/``width`` working size (both None: native size).

    Raises:
        ValueError: unknown ``data.kind``, missing ``data.root``, bad sizes; dataset errors name the path.
    """
    kind = data.get("kind")
    if kind not in DATA_KINDS:
        raise ValueError(f"data.kind={kind!r}; expected one of {DATA_KINDS} (conf/dataset/*.yaml)")
    seq = data.get("seq") if seq is None else seq
    h, w = _size(img_res)
    sel = _frames_slice(data)
    if kind == "synthetic":
        return _synthetic(data, seq, h, w, sel)
    root = data.get("root")
    if not root:
        raise ValueError(f"data={kind} needs data.root=PATH (the dataset folder)")
    if kind == "kitti_odom":
        from dfvo.data.kitti_odometry import KittiOdometry
        if seq is None:
            raise ValueError("data=kitti_odom needs seq=NN (e.g. seq=06)")
        ds = KittiOdometry(root, str(seq), height=h, width=w, camera=data.get("camera", "auto"), frames=sel,
                           stereo=False)
        return FrameSequence(ds.sequence, len(ds), ds.intrinsics.float(), lambda i: ds[i]["image"], ds.poses)
    if kind == "kitti_raw":
        return _kitti_raw(root, seq, h, w, sel)
    from dfvo.data.image_folder import ImageFolder
    for key in ("fx", "fy", "cx", "cy"):
        if data.get(key) is None:
            raise ValueError(f"data=folder needs data.{key}= (intrinsics in pixels of the stored images)")
    ds = ImageFolder(root, data.fx, data.fy, data.cx, data.cy, dist=data.get("dist"), height=h, width=w)
    ids = list(range(len(ds)))[sel]
    name = str(seq) if seq is not None else Path(root).name
    return FrameSequence(name, len(ids), ds.intrinsics.float(), lambda i: ds[ids[i]]["image"])


def _synthetic(data: Any, seq: Any, h: int | None, w: int | None, sel: slice) -> FrameSequence:
    from dfvo.data.synthetic import KITTI_HW, SyntheticWorld
    scenario = str(seq) if seq is not None else "drive"
    h, w = (h, w) if h is not None else KITTI_HW
    world = SyntheticWorld(seed=int(data.get("seed", 0)), num_frames=int(data.get("num_frames", 100)), height=h,
                           width=w, exposure_change=bool(data.get("exposure_change", False)),
                           noise_std=float(data.get("noise_std", 0.0)), scenario=scenario)
    ids = list(range(len(world)))[sel]
    if len(ids) < 2:
        raise ValueError(f"data=synthetic: frames {sel} select {len(ids)} frames; expected at least 2")
    if ids != list(range(ids[0], ids[0] + len(ids))):
        raise ValueError("data=synthetic: the frame range must be contiguous (no step)")
    poses = world.poses().numpy()[ids]
    seq_view = _OffsetWorld(world, ids[0])
    name = f"synthetic_{scenario}_s{world.seed}"
    return FrameSequence(name, len(ids), world.intrinsics().float(), lambda i: world.image(ids[i]), poses, seq_view)


class _OffsetWorld:
    """A synthetic world seen from frame ``offset`` on (oracle sources index the sequence, not the world)."""

    def __init__(self, world: Any, offset: int) -> None:
        self.world, self.offset = world, offset

    def flow(self, i: int, j: int) -> tuple[torch.Tensor, torch.Tensor]:
        return self.world.flow(i + self.offset, j + self.offset)

    def depth(self, i: int) -> torch.Tensor:
        return self.world.depth(i + self.offset)


def _kitti_raw(root: str, seq: Any, h: int | None, w: int | None, sel: slice) -> FrameSequence:
    from dfvo.data.kitti_raw import KittiRawSnippets
    drives = [str(seq)] if seq is not None else None
    ds = KittiRawSnippets(root, h, w, drives=drives, stereo=True, temporal=False)
    if len(ds.drives) != 1:
        names = [d.dir.name for d in ds.drives]
        raise ValueError(f"data=kitti_raw under {root}: {names} drives found; choose one with seq=DRIVE")
    drive = ds.drives[0]
    ids = list(range(len(drive.left)))[sel]
    poses = drive.poses[ids] if drive.poses is not None else None
    return FrameSequence(drive.dir.name, len(ids), drive.K.float(), lambda i: drive.load(drive.left[ids[i]]), poses)
