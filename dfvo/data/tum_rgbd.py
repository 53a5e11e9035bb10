"""TUM RGB-D sequences: the colour frames, the Kinect calibration, and the motion-capture ground truth.

Layout (``root`` is e.g. ``rgbd_dataset_freiburg1_xyz/``)::

    rgb.txt            "timestamp filename" per frame (``# ...`` comment lines), e.g. "1305031102.175304 rgb/1305...png"
    rgb/*.png          640x480 colour frames
    groundtruth.txt    (optional) "timestamp tx ty tz qx qy qz qw", the pose of the colour camera's optical centre

Convention:
    - ``groundtruth.txt`` already gives the colour camera: poses are ``T_w_cam`` in the motion-capture world
      (no extrinsic needed). A frame takes the pose nearest in time within ``gt_tolerance`` (default 0.02 s, the
      TUM benchmark tools' ``max_difference``; :func:`dfvo.data.timed_poses.associate_frames`); frames without one
      follow the ``unmatched`` policy of :mod:`dfvo.data.timed_poses` (default ``"trim"``).
    - Intrinsics: given (``fx, fy, cx, cy`` and optional ``dist`` in pixels of the stored frames), or the
      published calibration of the colour camera of the sensor named in the folder (``freiburg1|2|3``) or by
      ``camera=fr1|fr2|fr3``, table :data:`TUM_CAMERAS` (from the TUM RGB-D benchmark's camera-calibration
      page). fr1 and fr2 frames are stored distorted (5 OpenCV coefficients ``d0..d4 = k1 k2 p1 p2 k3``) and are
      undistorted at native size; fr3 frames are stored undistorted.
    - Timestamps are the seconds of ``rgb.txt`` (float64).
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np
import torch

from dfvo.data.image_folder import FramePrep
from dfvo.data.image_io import DatasetError, DatasetNotFoundError, image_size, require_dir
from dfvo.data.intrinsics_check import check_intrinsics
from dfvo.data.sequence import FrameSequence
from dfvo.data.timed_poses import associate_frames, attach_ground_truth, parse_floats, read_ground_truth, read_rows
from dfvo.data.transforms import check_working_size
from dfvo.geometry.camera import intrinsics_matrix
from dfvo.io.trajectory import read_tum

__all__ = ["TUM_CAMERAS", "TumRgbdSequence", "open_tum", "tum_camera_from_name", "read_tum_groundtruth"]

log = logging.getLogger("dfvo.data")

# Colour camera of each Kinect (fx, fy, cx, cy, [d0..d4]) in pixels of the 640x480 frames, as published by the
# TUM RGB-D benchmark ("File Formats" -> "Intrinsic Camera Calibration of the Kinect").
TUM_CAMERAS: dict[str, tuple[float, float, float, float, list[float]]] = {
    "fr1": (517.3, 516.5, 318.6, 255.3, [0.2624, -0.9531, -0.0054, 0.0026, 1.1633]),
    "fr2": (520.9, 521.0, 325.1, 249.7, [0.2312, -0.7849, -0.0033, -0.0001, 0.9172]),
    "fr3": (535.4, 539.2, 320.1, 247.6, [0.0, 0.0, 0.0, 0.0, 0.0]),
}


def tum_camera_from_name(name: str) -> str | None:
    """``"fr1"``/``"fr2"``/``"fr3"`` from a folder name like ``rgbd_dataset_freiburg1_xyz`` (None if absent)."""
    m = re.search(r"freiburg([123])(?!\d)", name) or re.search(r"(?<![a-z0-9])fr([123])(?!\d)", name.lower())
    return f"fr{m.group(1)}" if m else None


def read_frame_list(root: Path) -> tuple[np.ndarray, list[Path]]:
    """``(timestamps (N,) float64 s, files)`` of ``root/rgb.txt``, checking every listed file exists."""
    path = root / "rgb.txt"
    rows = read_rows(path, "TUM frame list", 2)
    stamps = np.array([parse_floats(f[:1], path, n, "TUM frame list")[0] for n, f in rows])
    files = [root / f[1] for _, f in rows]
    missing = [p for p in files if not p.is_file()]
    if missing:
        raise DatasetNotFoundError(f"TUM frame list {path} names {len(missing)} missing files, first {missing[0]}")
    if np.any(np.diff(stamps) <= 0):
        k = int(np.argmax(np.diff(stamps) <= 0)) + 1
        raise DatasetError(f"TUM frame list {path}: timestamps not increasing at data line {k + 1} ({stamps[k]})")
    return stamps, files


def read_tum_groundtruth(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """``(timestamps (M,) s, T_w_cam (M,4,4))`` of a TUM ``groundtruth.txt`` (``t tx ty tz qx qy qz qw``), read by
    :func:`dfvo.io.trajectory.read_tum` (sorted by time).

    Raises:
        DatasetNotFoundError: the file does not exist. DatasetError: a malformed line (file and line named).
    """
    return read_ground_truth(path, read_tum, "TUM ground truth")


class TumRgbdSequence:
    """Colour frames of a TUM RGB-D sequence at the working size, with camera ground truth when available.

    Args:
        root: the sequence folder (holding ``rgb.txt``).
        fx, fy, cx, cy: intrinsics in pixels of the stored frames (all four, or none for the published ones).
        dist: distortion of given intrinsics (OpenCV order); ignored for the published ones.
        camera: ``"auto"`` (from the folder name) or ``"fr1"``, ``"fr2"``, ``"fr3"`` when no intrinsics are given.
        height, width: working size (both or neither; None: native 640x480).
        frames: range of ``rgb.txt`` rows to use (applied before the ground-truth policy).
        undistort: undo the distortion (True) or use the frames as stored.
        gt_tolerance: seconds; unmatched: ``"trim"``, ``"nan"`` or ``"none"``.

    Attributes:
        name, files, frame_ids, timestamps (s), K (3,3) float32 at the working size, poses or None,
        camera (the calibration used, e.g. ``"fr1"`` or ``"given"``), report (one line).
    """

    def __init__(self, root: str | Path, fx: float | None = None, fy: float | None = None, cx: float | None = None,
                 cy: float | None = None, dist: list[float] | None = None, camera: str = "auto",
                 height: int | None = None, width: int | None = None, frames: slice = slice(None),
                 undistort: bool = True, gt_tolerance: float = 0.02, unmatched: str = "trim") -> None:
        root = require_dir(root, "TUM RGB-D sequence")
        self.name = root.name
        stamps, files = read_frame_list(root)
        sel = np.arange(len(files))[frames]
        if len(sel) < 2:
            raise DatasetError(f"TUM {self.name}: frames {frames} select {len(sel)} frames; expected at least 2")
        self.native_size = image_size(files[sel[0]])
        given = [v is not None for v in (fx, fy, cx, cy)]
        if any(given) and not all(given):
            raise ValueError("data=tum: give all of data.fx, data.fy, data.cx, data.cy, or none of them (then the "
                             "published calibration of the folder's freiburg1/2/3 camera is used)")
        if all(given):
            self.camera, names, source = "given", ("data.fx", "data.fy", "data.cx", "data.cy"), None
        else:
            key = tum_camera_from_name(root.name) if camera == "auto" else camera
            if key not in TUM_CAMERAS:
                raise ValueError(f"data=tum: cannot tell the camera from {camera!r} / the folder name {root.name!r}; "
                                 f"give data.camera=fr1|fr2|fr3 or data.fx, data.fy, data.cx, data.cy")
            fx, fy, cx, cy, dist = TUM_CAMERAS[key]
            self.camera, names, source = key, ("fx", "fy", "cx", "cy"), f"the published {key} calibration"
        fx, fy, cx, cy, dist = check_intrinsics(fx, fy, cx, cy, self.native_size[1], self.native_size[0], dist,
                                                names=names, source=source)
        working = check_working_size(height, width, f"TUM {self.name}")
        K = intrinsics_matrix(fx, fy, cx, cy, dtype=torch.float64)[0]
        self.prep = FramePrep(K, self.native_size, working, dist if undistort else None)
        self.K = self.prep.K
        self.poses: np.ndarray | None = None
        keep = np.arange(len(sel))
        gt_path = root / "groundtruth.txt"
        if unmatched != "none" and gt_path.is_file():
            gt_t, gt_poses = read_tum_groundtruth(gt_path)
            match = associate_frames(stamps[sel], gt_t, gt_tolerance)
            keep, self.poses, self.report = attach_ground_truth(stamps[sel], match, gt_poses, unmatched,
                                                                f"TUM {self.name}", gt_tolerance)
        else:
            why = "not used (unmatched=none)" if unmatched == "none" else f"absent ({gt_path} does not exist)"
            self.report = f"TUM {self.name}: {len(sel)} frames, ground truth {why}"
        self.report += f"; intrinsics: {self.camera}"
        if len(keep) < 2:
            raise DatasetError(f"{self.report}; fewer than 2 frames left")
        self.frame_ids = sel[keep]
        self.files = [files[i] for i in self.frame_ids]
        self.timestamps = stamps[self.frame_ids]
        log.info(self.report)

    def __len__(self) -> int:
        return len(self.files)

    def image(self, index: int) -> torch.Tensor:
        """(3,H,W) float [0,1] frame ``index`` (undistorted, at the working size)."""
        return self.prep.read(self.files[index])


def open_tum(root: str | Path, *, fx: float | None = None, fy: float | None = None, cx: float | None = None,
             cy: float | None = None, dist: list[float] | None = None, camera: str = "auto",
             height: int | None = None, width: int | None = None, start: int | None = None, end: int | None = None,
             step: int | None = None, undistort: bool = True, gt_tolerance: float = 0.02,
             unmatched: str = "trim") -> FrameSequence:
    """A TUM RGB-D sequence as a :class:`~dfvo.inference.frames.FrameSequence` (see :class:`TumRgbdSequence`).

    ``start, end, step`` index the rows of ``rgb.txt`` (Python slice semantics).
    """
    seq = TumRgbdSequence(root, fx, fy, cx, cy, dist, camera, height, width, slice(start, end, step), undistort,
                          gt_tolerance, unmatched)
    return FrameSequence(seq.name, len(seq), seq.K.clone(), seq.image, seq.poses, None, seq.timestamps)
