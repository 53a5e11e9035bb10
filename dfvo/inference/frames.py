"""The frames an inference run reads: one sequence of any supported dataset behind one small interface.

Convention:
    ``FrameSequence.image(i)`` is (3,H,W) float in [0,1] at the working resolution, ``K`` (3,3) in its pixels,
    ``poses`` (N,4,4) float64 ``T_w_c`` of the left camera when ground truth exists (else None), ``world`` the
    :class:`~dfvo.data.synthetic.SyntheticWorld` for ``data=synthetic`` (oracle sources need it), ``timestamps``
    (N,) float64 seconds of each frame when the dataset has them (else None).
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = ["FrameSequence", "build_sequence", "resolve_data", "DATA_ROOT_ENV"]

# dataset kind -> environment variable that gives its root once for all commands
DATA_ROOT_ENV = {"kitti_odom": "DFVO_KITTI_ODOM_ROOT", "kitti_raw": "DFVO_KITTI_RAW_ROOT"}
KITTI_ODOM_SEQ = re.compile(r"^\d{1,2}$")


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


def _size(img_res: Any) -> tuple[int | None, int | None]:
    h, w = img_res.height, img_res.width
    if (h is None) != (w is None):
        raise ValueError(f"img_res: give both height and width or neither, got height={h}, width={w}")
    return h, w


def resolve_data(data: Any, seq: str | int | None) -> tuple[Any, str | None]:
    """The dataset config and sequence name a run uses.

    ``seq`` overrides ``data.seq``. A KITTI odometry sequence number (``seq=10``) with the default synthetic data
    selects KITTI odometry (the synthetic world's sequences are scenario names), with its root from
    ``DFVO_KITTI_ODOM_ROOT``. A missing ``data.root`` is taken from the kind's environment variable
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
    from dfvo.inference.config import KittiOdomDataConfig

    name = None if seq is None else str(seq)
    if data.kind == "synthetic" and name is not None and KITTI_ODOM_SEQ.match(name):
        data = KittiOdomDataConfig(start=data.start, end=data.end)
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


def build_sequence(data: Any, seq: str | int | None, img_res: Any) -> FrameSequence:
    """Open the sequence described by a typed data config (:data:`dfvo.inference.config.DATA_SCHEMAS`).

    Args:
        data: the ``data`` node (typed), ``seq`` the command line's sequence (see :func:`resolve_data`),
            ``img_res`` the working size (``height``/``width``, both None: native size).

    Raises:
        ValueError: unknown ``data.kind``, missing root, bad sizes; dataset errors name the path.
    """
    from dfvo.inference.config import DATA_SCHEMAS

    if data.kind not in DATA_SCHEMAS:
        raise ValueError(f"data.kind={data.kind!r}; expected one of {tuple(DATA_SCHEMAS)}")
    data, name = resolve_data(data, seq)
    h, w = _size(img_res)
    sel = slice(data.start, data.end)
    if data.kind == "synthetic":
        return _synthetic(data, name, h, w, sel)
    if data.kind == "kitti_odom":
        from dfvo.data.kitti_odometry import KittiOdometry
        if name is None:
            raise ValueError("data=kitti_odom needs seq=NN (e.g. seq=06)")
        ds = KittiOdometry(data.root, name, height=h, width=w, camera=data.camera, frames=sel, stereo=False)
        return FrameSequence(ds.sequence, len(ds), ds.intrinsics.float(), lambda i: ds[i]["image"], ds.poses,
                             timestamps=ds.timestamps)
    if data.kind == "kitti_raw":
        return _kitti_raw(data.root, name, h, w, sel)
    return _folder(data, name, h, w, sel)


def _folder(data: Any, name: str | None, h: int | None, w: int | None, sel: slice) -> FrameSequence:
    from dfvo.data.image_folder import ImageFolder
    for key in ("fx", "fy", "cx", "cy"):
        if getattr(data, key) is None:
            raise ValueError(f"data=folder needs data.{key}= (intrinsics in pixels of the stored images)")
    ds = ImageFolder(data.root, data.fx, data.fy, data.cx, data.cy, dist=data.dist, height=h, width=w)
    ids = list(range(len(ds)))[sel]
    return FrameSequence(name or Path(data.root).name, len(ids), ds.intrinsics.float(), lambda i: ds[ids[i]]["image"])


def _synthetic(data: Any, scenario: str | None, h: int | None, w: int | None, sel: slice) -> FrameSequence:
    from dfvo.data.synthetic import KITTI_HW, SyntheticWorld
    scenario = scenario or "drive"
    h, w = (h, w) if h is not None else KITTI_HW
    world = SyntheticWorld(seed=data.seed, num_frames=data.num_frames, height=h, width=w,
                           exposure_change=data.exposure_change, noise_std=data.noise_std, scenario=scenario)
    ids = list(range(len(world)))[sel]
    if len(ids) < 2:
        raise ValueError(f"data=synthetic: frames {sel.start}..{sel.stop} select {len(ids)} frames; expected at "
                         "least 2")
    poses = world.poses().numpy()[ids]
    name = f"synthetic_{scenario}_s{world.seed}"
    return FrameSequence(name, len(ids), world.intrinsics().float(), lambda i: world.image(ids[i]), poses,
                         _OffsetWorld(world, ids[0]))


class _OffsetWorld:
    """A synthetic world seen from frame ``offset`` on (oracle sources index the sequence, not the world)."""

    def __init__(self, world: Any, offset: int) -> None:
        self.world, self.offset = world, offset

    def flow(self, i: int, j: int) -> tuple[torch.Tensor, torch.Tensor]:
        return self.world.flow(i + self.offset, j + self.offset)

    def depth(self, i: int) -> torch.Tensor:
        return self.world.depth(i + self.offset)


def _kitti_raw(root: str, seq: str | None, h: int | None, w: int | None, sel: slice) -> FrameSequence:
    from dfvo.data.kitti_raw import KittiRawSnippets
    drives = [seq] if seq is not None else None
    ds = KittiRawSnippets(root, h, w, drives=drives, stereo=True, temporal=False)
    if len(ds.drives) != 1:
        names = [d.dir.name for d in ds.drives]
        raise ValueError(f"data=kitti_raw under {root}: {names} drives found; choose one with seq=DRIVE")
    drive = ds.drives[0]
    ids = list(range(len(drive.left)))[sel]
    poses = drive.poses[ids] if drive.poses is not None else None
    return FrameSequence(drive.dir.name, len(ids), drive.K.float(), lambda i: drive.load(drive.left[ids[i]]), poses)
