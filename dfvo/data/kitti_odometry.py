"""KITTI Odometry sequences exactly as KITTI lays them out.

Layout::

    ROOT/sequences/SS/image_2/NNNNNN.png   left colour   (image_3: right colour)
    ROOT/sequences/SS/image_0/NNNNNN.png   left gray     (image_1: right gray), used when image_2 is absent
    ROOT/sequences/SS/calib.txt            lines P0..P3 (3x4); only those of the cameras used are needed
    ROOT/sequences/SS/times.txt            one timestamp (s) per frame, optional
    ROOT/poses/SS.txt                      one row-major 3x4 T_w_c of the left camera per frame, optional
                                           (12 numbers a line, or 13 with a leading frame index)

Convention:
    - Samples follow :mod:`dfvo.data` keys: ``image`` (3,H,W) in [0,1] (gray replicated), ``K`` (3,3) at the
      working resolution, ``index``, ``pose`` (4,4) T_w_c when ground truth exists, ``image_right`` and
      ``T_right_left`` (4,4) for stereo, ``timestamp`` (s) when ``times.txt`` exists.
    - ``K`` is ``P_left[:3,:3]``; the baseline ``b = -(P_right[0,3] - P_left[0,3]) / fx`` (≈0.54 m).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from dfvo.data.calibration import (
    checked_intrinsics,
    read_odometry_projections,
    stereo_baseline,
    stereo_transform,
)
from dfvo.data.image_io import DatasetError, image_size, list_images, read_image, require_dir
from dfvo.data.transforms import check_working_size, resize_with_intrinsics
from dfvo.io.trajectory import read_kitti_poses, read_times

CAMERAS = {"color": ("image_2", "image_3", 2, 3), "gray": ("image_0", "image_1", 0, 1)}
KITTI_ODOM_SEQ = re.compile(r"^\d{1,2}$")  # a KITTI odometry sequence name: 00..21 (one digit accepted)


def selects_kitti_odometry(kind: str | None, seq: str | int | None) -> bool:
    """Whether ``seq`` alone turns the default synthetic data of a run into KITTI odometry (``seq=10``: a sequence
    number, where the synthetic world's sequences are scenario names); the one home of this rule for the data
    resolution (:func:`dfvo.inference.frames.resolve_data`) and the camera-height default
    (:class:`dfvo.inference.config.InferConfig`)."""
    return kind == "synthetic" and seq is not None and bool(KITTI_ODOM_SEQ.match(str(seq)))


def read_times_file(path: str | Path) -> np.ndarray:
    """A KITTI ``times.txt`` (one timestamp in seconds a line) as (N,) float64, read by
    :func:`dfvo.io.trajectory.read_times`; a malformed line is a :class:`DatasetError` naming file and line."""
    try:
        return read_times(path)
    except ValueError as err:
        raise DatasetError(f"times file: {err}") from err


class KittiOdometry(Dataset):
    """One KITTI Odometry sequence as a map-style dataset of frames.

    Args:
        root: dataset root holding ``sequences/`` (and ``poses/`` when ground truth exists).
        sequence: sequence name, e.g. ``"06"`` (an integer-like ``"6"`` becomes ``"06"``).
        height: working height (None: native resolution); give both height and width or neither.
        width: working width.
        camera: ``"auto"`` (image_2 when present, else image_0), ``"color"`` or ``"gray"``.
        frames: optional slice of the sequence's frames (e.g. ``slice(0, 100)``); poses and times follow it.
        stereo: include the right image; ``None`` means when the right folder exists.
        temporal: training snippets: sample ``k`` is frame ``k+1`` of the selection with ``image_prev`` /
            ``image_next`` (and ``pose_prev`` / ``pose_next`` when known); the dataset has two samples fewer.

    Raises:
        DatasetNotFoundError: missing sequence / image folder / calib.txt.
        DatasetError: no images, calib.txt lacking the needed ``P`` line, image and pose (or times, or left and
            right image) counts that differ.
    """

    def __init__(self, root: str | Path, sequence: str, height: int | None = None, width: int | None = None,
                 camera: str = "auto", frames: slice | None = None, stereo: bool | None = None,
                 temporal: bool = False) -> None:
        self.root = Path(root)
        self.sequence = str(sequence).zfill(2) if str(sequence).isdigit() else str(sequence)
        seq_dir = require_dir(self.root / "sequences" / self.sequence, f"KITTI odometry sequence {self.sequence}")
        self.sequence_dir = seq_dir
        if camera == "auto":
            camera = "color" if (seq_dir / "image_2").is_dir() else "gray"
        if camera not in CAMERAS:
            raise ValueError(f"camera must be 'auto', 'color' or 'gray', got {camera!r}")
        self.camera = camera
        left_name, right_name, left_id, right_id = CAMERAS[camera]
        all_left = list_images(seq_dir / left_name, f"KITTI odometry left camera ({left_name})")
        n_all = len(all_left)
        if stereo is None:
            stereo = (seq_dir / right_name).is_dir()
        self.stereo = bool(stereo)
        all_right = None
        if self.stereo:
            all_right = list_images(seq_dir / right_name, f"KITTI odometry right camera ({right_name})")
            if len(all_right) != n_all:
                raise DatasetError(f"{seq_dir}: {left_name} has {n_all} images but {right_name} has "
                                   f"{len(all_right)}; expected equal counts (pass stereo=False to ignore)")

        cams = (left_id, right_id) if self.stereo else (left_id,)
        proj = read_odometry_projections(seq_dir / "calib.txt", cams)
        self.native_size = image_size(all_left[0])
        K_native = torch.as_tensor(checked_intrinsics(seq_dir / "calib.txt", f"P{left_id}", self.native_size),
                                   dtype=torch.float32)  # before the baseline divides by fx
        self.baseline = stereo_baseline(proj[left_id], proj[right_id]) if self.stereo else None

        poses = None
        pose_path = self.root / "poses" / f"{self.sequence}.txt"
        if pose_path.is_file():
            try:
                poses = read_kitti_poses(pose_path)
            except ValueError as err:  # the one KITTI pose reader (dfvo.io.trajectory), as a dataset error
                raise DatasetError(str(err)) from err
            if len(poses) != n_all:
                raise DatasetError(f"pose file {pose_path} has {len(poses)} poses but {seq_dir / left_name} has "
                                   f"{n_all} images; expected one pose per image")
        times = None
        times_path = seq_dir / "times.txt"
        if times_path.is_file():
            times = read_times_file(times_path)
            if len(times) != n_all:
                raise DatasetError(f"times file {times_path} has {len(times)} entries but {seq_dir / left_name} "
                                   f"has {n_all} images; expected one timestamp per image")

        sel = frames if frames is not None else slice(None)
        self.frame_ids = list(range(n_all))[sel]
        if not self.frame_ids:
            raise DatasetError(f"{seq_dir}: frames={frames} selects no frame of the {n_all} available")
        self.left_files = [all_left[i] for i in self.frame_ids]
        self.right_files = [all_right[i] for i in self.frame_ids] if all_right is not None else None
        self.poses: np.ndarray | None = poses[self.frame_ids] if poses is not None else None
        self.timestamps: np.ndarray | None = times[self.frame_ids] if times is not None else None

        working = check_working_size(height, width, f"KittiOdometry({seq_dir})")
        self.image_size: tuple[int, int] = working if working is not None else self.native_size
        _, self.intrinsics = resize_with_intrinsics(torch.zeros(1, *self.native_size), K_native, *self.image_size)
        self.T_right_left = stereo_transform(self.baseline) if self.baseline is not None else None
        self.temporal = temporal
        if temporal and len(self.left_files) < 3:
            raise DatasetError(f"{seq_dir}: temporal snippets need at least 3 frames, the selection has "
                               f"{len(self.left_files)}")

    def __len__(self) -> int:
        return len(self.left_files) - (2 if self.temporal else 0)

    def _load(self, path: Path) -> torch.Tensor:
        return read_image(path, size=self.image_size, expected_size=self.native_size)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        if not -len(self) <= index < len(self):
            raise IndexError(f"frame {index} out of range for {len(self)} frames")
        index = index % len(self) + (1 if self.temporal else 0)
        sample: dict[str, torch.Tensor] = {
            "image": self._load(self.left_files[index]),
            "K": self.intrinsics.clone(),
            "index": torch.tensor(self.frame_ids[index]),
        }
        if self.poses is not None:
            sample["pose"] = torch.as_tensor(self.poses[index], dtype=torch.float32)
            if self.temporal:
                sample["pose_prev"] = torch.as_tensor(self.poses[index - 1], dtype=torch.float32)
                sample["pose_next"] = torch.as_tensor(self.poses[index + 1], dtype=torch.float32)
        if self.temporal:
            sample["image_prev"] = self._load(self.left_files[index - 1])
            sample["image_next"] = self._load(self.left_files[index + 1])
        if self.right_files is not None and self.T_right_left is not None:
            sample["image_right"] = self._load(self.right_files[index])
            sample["T_right_left"] = self.T_right_left.clone()
        if self.timestamps is not None:
            sample["timestamp"] = torch.tensor(self.timestamps[index], dtype=torch.float64)
        return sample
