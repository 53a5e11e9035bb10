"""EuRoC MAV sequences (ASL layout): one camera's frames, its calibration, and the ground truth moved to it.

Layout (``root`` is the sequence folder holding ``mav0/``, or ``mav0/`` itself)::

    mav0/cam0/sensor.yaml                 intrinsics [fu, fv, cu, cv], distortion_model, distortion_coefficients,
                                          resolution [width, height], T_BS (4x4, rows/cols/data)
    mav0/cam0/data.csv                    "#timestamp [ns],filename" one line per frame
    mav0/cam0/data/<ns>.png               8-bit grayscale frames (replicated to 3 channels)
    mav0/state_groundtruth_estimate0/data.csv   (optional) ns timestamp, p_RS_R xyz [m], q_RS w x y z, ...

Convention:
    - ``T_BS`` maps points of the camera (sensor S) into the body frame B: it is ``T_body_cam``. The ground
      truth gives the body (IMU) pose ``T_w_body`` at 200 Hz; a frame takes the pose nearest in time within
      ``gt_tolerance`` seconds (:func:`dfvo.data.timed_poses.associate_frames`; both sides ``ns * 1e-9``) and the
      camera pose is ``T_w_cam = T_w_body @ T_BS``.
      The world frame is the ground truth's own (the first pose is not the identity).
    - Frames without a ground-truth pose follow the ``unmatched`` policy of :mod:`dfvo.data.timed_poses`
      (default ``"trim"``: the frames before the ground truth starts are dropped, and said so). The frame range
      (``frames``/``start, end, step``) indexes ``cam0/data.csv`` and is applied before that.
    - radial-tangential distortion is undone at native size (:class:`dfvo.data.image_folder.FramePrep`); the
      undistorted frames keep ``K``. ``equidistant`` (fisheye) calibrations are refused unless ``undistort=False``.
    - Timestamps are seconds (float64, ``ns * 1e-9``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import yaml

from dfvo.data.image_folder import FramePrep
from dfvo.data.image_io import DatasetError, DatasetNotFoundError, image_size, require_dir, require_file
from dfvo.data.intrinsics_check import check_intrinsics
from dfvo.data.sequence import FrameSequence
from dfvo.data.timed_poses import associate_frames, attach_ground_truth, read_ground_truth, read_rows
from dfvo.data.transforms import check_working_size
from dfvo.io.trajectory import read_euroc

__all__ = ["EurocCamera", "EurocSequence", "open_euroc", "read_sensor_yaml", "read_euroc_groundtruth"]

log = logging.getLogger("dfvo.data")
GT_CSV = Path("state_groundtruth_estimate0") / "data.csv"


@dataclass
class EurocCamera:
    """One camera's ``sensor.yaml``: ``K`` (3,3) float64 in pixels, ``dist``, ``resolution`` (width, height),
    ``T_BS`` (4,4) float64 ``T_body_cam``, ``distortion_model``, ``rate_hz`` (None when absent)."""

    K: np.ndarray
    dist: list[float]
    resolution: tuple[int, int]
    T_BS: np.ndarray
    distortion_model: str
    rate_hz: float | None


def _field(data: dict, key: str, path: Path, count: int | None = None) -> list[float]:
    value = data.get(key)
    if value is None:
        raise DatasetError(f"EuRoC sensor file {path} has no '{key}:' entry")
    try:
        numbers = [float(v) for v in (value if isinstance(value, list) else [value])]
    except (TypeError, ValueError):
        raise DatasetError(f"EuRoC sensor file {path}: '{key}' must be numbers, got {value!r}") from None
    if count is not None and len(numbers) != count:
        raise DatasetError(f"EuRoC sensor file {path}: '{key}' has {len(numbers)} numbers, expected {count}")
    return numbers


def read_sensor_yaml(path: str | Path) -> EurocCamera:
    """Parse a EuRoC camera ``sensor.yaml`` (plain YAML; a leading OpenCV ``%YAML:1.0`` line is tolerated).

    Raises:
        DatasetNotFoundError: the file does not exist.
        DatasetError: not YAML, or a field missing or malformed (the message names the file and the field).
    """
    path = require_file(path, "EuRoC sensor file")
    text = "\n".join(ln for ln in path.read_text().splitlines() if not ln.startswith("%YAML"))
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise DatasetError(f"EuRoC sensor file {path} is not valid YAML ({err})") from None
    if not isinstance(data, dict):
        raise DatasetError(f"EuRoC sensor file {path}: expected 'key: value' entries")
    fu, fv, cu, cv = _field(data, "intrinsics", path, 4)
    width, height = (int(v) for v in _field(data, "resolution", path, 2))
    model = str(data.get("distortion_model", "radial-tangential"))
    dist = _field(data, "distortion_coefficients", path) if data.get("distortion_coefficients") is not None else []
    tbs = data.get("T_BS")
    if not isinstance(tbs, dict):
        raise DatasetError(f"EuRoC sensor file {path} has no 'T_BS:' entry with rows, cols and data")
    T_BS = np.asarray(_field(tbs, "data", path, 16), dtype=np.float64).reshape(4, 4)
    R = T_BS[:3, :3]
    if not np.allclose(T_BS[3], (0, 0, 0, 1)) or np.abs(R.T @ R - np.eye(3)).max() > 1e-3:
        raise DatasetError(f"EuRoC sensor file {path}: T_BS is not a rigid transform (rotation not orthonormal or "
                           f"last row not 0 0 0 1): {T_BS.tolist()}")
    rate = data.get("rate_hz")
    K = np.array([[fu, 0.0, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]])
    return EurocCamera(K, dist, (width, height), T_BS, model, float(rate) if rate is not None else None)


def _ns(field: str, path: Path, lineno: int, what: str) -> int:
    try:
        return int(field) if field.isdigit() else int(round(float(field)))
    except ValueError:
        raise DatasetError(f"{what} {path} line {lineno}: timestamp {field!r} is not a number of nanoseconds") from None


def read_frame_list(cam_dir: Path) -> tuple[np.ndarray, list[Path]]:
    """``(timestamps_ns (N,) int64, files)`` of ``cam_dir/data.csv``, checking every listed file exists."""
    csv = cam_dir / "data.csv"
    rows = read_rows(csv, "EuRoC frame list", 2, sep=",")
    stamps = np.array([_ns(f[0], csv, n, "EuRoC frame list") for n, f in rows], dtype=np.int64)
    files = [cam_dir / "data" / f[1] for _, f in rows]
    missing = [p for p in files if not p.is_file()]
    if missing:
        raise DatasetNotFoundError(f"EuRoC frame list {csv} names {len(missing)} missing files, first {missing[0]}")
    if np.any(np.diff(stamps) <= 0):
        k = int(np.argmax(np.diff(stamps) <= 0)) + 1
        raise DatasetError(f"EuRoC frame list {csv}: timestamps not increasing at data line {k + 1} ({stamps[k]})")
    return stamps, files


def read_euroc_groundtruth(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """``(timestamps (M,) float64 s, T_w_body (M,4,4) float64)`` of ``state_groundtruth_estimate0/data.csv``, read by
    :func:`dfvo.io.trajectory.read_euroc` (timestamp [ns] -> ``ns * 1e-9`` s, p_RS_R x y z [m], q_RS w x y z;
    the further columns are ignored).

    Raises:
        DatasetNotFoundError: the file does not exist. DatasetError: a malformed line (file and line named).
    """
    return read_ground_truth(path, read_euroc, "EuRoC ground truth")


def _find_mav0(root: Path) -> Path:
    root = require_dir(root, "EuRoC sequence")
    if (root / "mav0").is_dir():
        return root / "mav0"
    if root.name == "mav0" or (root / "cam0").is_dir():
        return root
    raise DatasetNotFoundError(f"EuRoC sequence: {root} holds no mav0/ folder (expected ROOT/mav0/cam0/data.csv)")


class EurocSequence:
    """Frames of one EuRoC camera at the working size, with camera ground-truth poses when available.

    Args:
        root: the sequence folder (holding ``mav0/``) or ``mav0/``.
        camera: ``"cam0"`` (left) or ``"cam1"``.
        height, width: working size (both or neither; None: native 752x480).
        frames: range of ``data.csv`` rows to use (applied before the ground-truth policy).
        undistort: undo the radial-tangential distortion (True), or use the frames as stored with ``K``.
        gt_tolerance: largest frame-to-ground-truth time difference in seconds (evo's default 0.01).
        unmatched: ``"trim"``, ``"nan"`` or ``"none"`` (:mod:`dfvo.data.timed_poses`).

    Attributes:
        name, files, frame_ids (rows of ``data.csv`` kept), timestamps_ns (int64), timestamps (s),
        K (3,3) float32 at the working size, poses (N,4,4) float64 ``T_w_cam`` or None, T_BS, report (one line).

    Raises:
        DatasetNotFoundError / DatasetError: missing or malformed files (named); IntrinsicsError: implausible
        intrinsics in ``sensor.yaml``; fewer than two frames left.
    """

    def __init__(self, root: str | Path, camera: str = "cam0", height: int | None = None, width: int | None = None,
                 frames: slice = slice(None), undistort: bool = True, gt_tolerance: float = 0.01,
                 unmatched: str = "trim") -> None:
        mav0 = _find_mav0(Path(root))
        self.name = mav0.parent.name if mav0.name == "mav0" else mav0.name
        cam_dir = require_dir(mav0 / camera, "EuRoC camera")
        yaml_path = cam_dir / "sensor.yaml"
        cam = read_sensor_yaml(yaml_path)
        stamps, files = read_frame_list(cam_dir)
        sel = np.arange(len(files))[frames]
        if len(sel) < 2:
            raise DatasetError(f"EuRoC {self.name}: frames {frames} select {len(sel)} frames; expected at least 2")
        self.native_size = image_size(files[sel[0]])
        if self.native_size != (cam.resolution[1], cam.resolution[0]):
            raise DatasetError(f"EuRoC frame {files[sel[0]]} is {self.native_size[1]}x{self.native_size[0]}, "
                               f"{yaml_path} says resolution {cam.resolution[0]}x{cam.resolution[1]}")
        dist = cam.dist if undistort and any(cam.dist) else None
        if dist is not None and cam.distortion_model != "radial-tangential":
            raise DatasetError(f"EuRoC sensor file {yaml_path}: distortion_model {cam.distortion_model!r} cannot be "
                               "undone here (radial-tangential only); undistort the frames first, or undistort=false")
        fu, fv, cu, cv, dist = check_intrinsics(cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2],
                                                cam.resolution[0], cam.resolution[1], dist,
                                                names=("fu", "fv", "cu", "cv"), dist_name="distortion_coefficients",
                                                source=str(yaml_path))
        working = check_working_size(height, width, f"EuRoC {self.name}")
        self.prep = FramePrep(torch.from_numpy(cam.K), self.native_size, working, dist)
        self.K = self.prep.K
        self.T_BS = cam.T_BS
        self.poses: np.ndarray | None = None
        keep = np.arange(len(sel))
        gt_path = mav0 / GT_CSV
        if unmatched != "none" and gt_path.is_file():
            gt_s, T_w_body = read_euroc_groundtruth(gt_path)
            match = associate_frames(stamps[sel] * 1e-9, gt_s, gt_tolerance)  # the ns -> s of read_euroc
            keep, body, self.report = attach_ground_truth(stamps[sel] * 1e-9, match, T_w_body, unmatched,
                                                          f"EuRoC {self.name}", gt_tolerance)
            self.poses = body @ cam.T_BS  # T_w_cam = T_w_body @ T_body_cam (NaN rows stay NaN)
            self.report += "; poses moved from the body (IMU) frame to the camera with T_BS"
        else:
            why = "not used (unmatched=none)" if unmatched == "none" else f"absent ({gt_path} does not exist)"
            self.report = f"EuRoC {self.name}: {len(sel)} frames, ground truth {why}"
        if len(keep) < 2:
            raise DatasetError(f"{self.report}; fewer than 2 frames left")
        self.frame_ids = sel[keep]
        self.files = [files[i] for i in self.frame_ids]
        self.timestamps_ns = stamps[self.frame_ids]
        self.timestamps = self.timestamps_ns * 1e-9
        log.info(self.report)

    def __len__(self) -> int:
        return len(self.files)

    def image(self, index: int) -> torch.Tensor:
        """(3,H,W) float [0,1] frame ``index`` (undistorted, at the working size)."""
        return self.prep.read(self.files[index])


def open_euroc(root: str | Path, *, camera: str = "cam0", height: int | None = None, width: int | None = None,
               start: int | None = None, end: int | None = None, step: int | None = None, undistort: bool = True,
               gt_tolerance: float = 0.01, unmatched: str = "trim") -> FrameSequence:
    """A EuRoC camera as a :class:`~dfvo.inference.frames.FrameSequence` (see :class:`EurocSequence`).

    ``start, end, step`` index the rows of ``cam0/data.csv`` (Python slice semantics).
    """
    seq = EurocSequence(root, camera, height, width, slice(start, end, step), undistort, gt_tolerance, unmatched)
    return FrameSequence(seq.name, len(seq), seq.K.clone(), seq.image, seq.poses, None, seq.timestamps)
