"""KITTI calibration files: odometry ``calib.txt`` and raw ``calib_cam_to_cam.txt`` / ``calib_*_to_*.txt``.

Convention:
    - Every file is ``key: v1 v2 ...`` per line; lines whose values are not all numbers (``calib_time``) are
      kept out of the numeric dictionary.
    - A rectified projection matrix is ``P = K [I | t]`` (3,4) where ``t`` moves points of the reference
      (rectified camera 0) frame into this camera. For a rectified stereo pair the baseline in metres is
      ``b = -(P_right[0,3] - P_left[0,3]) / fx`` and ``T_right_left`` is a translation ``(-b, 0, 0)``.
    - Rigid transforms are returned as (4,4) float64 numpy arrays ``T_a_b`` (maps frame-b points into a).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from dfvo.data.image_io import DatasetError, require_file


def read_calib_file(path: str | Path) -> dict[str, np.ndarray]:
    """Parse a KITTI calibration file into ``{key: float64 vector}`` (non-numeric lines skipped).

    Raises:
        DatasetNotFoundError: the file does not exist.
        DatasetError: the file holds no ``key: numbers`` line.
    """
    path = require_file(path, "calibration")
    values: dict[str, np.ndarray] = {}
    for line in path.read_text().splitlines():
        key, sep, rest = line.partition(":")
        if not sep:
            continue
        try:
            values[key.strip()] = np.array([float(tok) for tok in rest.split()], dtype=np.float64)
        except ValueError:
            continue  # e.g. "calib_time: 09-Jan-2012 13:57:47"
    if not values:
        raise DatasetError(f"calibration file {path} has no 'KEY: numbers' lines")
    return values


def get_matrix(calib: dict[str, np.ndarray], key: str, shape: tuple[int, int], path: str | Path) -> np.ndarray:
    """Entry ``key`` of a parsed calibration reshaped to ``shape``, with an error naming the file if absent."""
    if key not in calib:
        raise DatasetError(f"calibration file {path} has no '{key}:' line (expected a {shape[0]}x{shape[1]} "
                           f"matrix; found keys {sorted(calib)})")
    vec = calib[key]
    if vec.size != shape[0] * shape[1]:
        raise DatasetError(f"calibration file {path}: '{key}' has {vec.size} numbers, expected "
                           f"{shape[0] * shape[1]} ({shape[0]}x{shape[1]})")
    return vec.reshape(shape)


def intrinsics_from_projection(P: np.ndarray) -> np.ndarray:
    """(3,3) intrinsics ``K`` of a rectified (3,4) projection matrix ``P = K [I | t]``."""
    K = P[:3, :3].copy()
    K[2] = (0.0, 0.0, 1.0)
    return K


def stereo_baseline(P_left: np.ndarray, P_right: np.ndarray) -> float:
    """Baseline in metres of a rectified pair: ``-(P_right[0,3] - P_left[0,3]) / fx`` (positive for KITTI)."""
    return float(-(P_right[0, 3] - P_left[0, 3]) / P_left[0, 0])


def stereo_transform(baseline: float) -> torch.Tensor:
    """(4,4) float32 ``T_right_left`` of a rectified pair: points move by ``(-baseline, 0, 0)``."""
    T = torch.eye(4)
    T[0, 3] = -baseline
    return T


def read_odometry_projections(path: str | Path, cameras: tuple[int, ...]) -> dict[int, np.ndarray]:
    """The (3,4) matrices ``P{c}`` of a KITTI odometry ``calib.txt`` for the requested camera numbers.

    Raises:
        DatasetError: a requested ``P{c}`` line is missing or malformed (other lines may be absent).
    """
    calib = read_calib_file(path)
    return {c: get_matrix(calib, f"P{c}", (3, 4), path) for c in cameras}


def read_raw_projections(path: str | Path, cameras: tuple[int, ...] = (2, 3)) -> dict[int, np.ndarray]:
    """Rectified projection matrices ``P_rect_0{c}`` (3,4) of a KITTI raw ``calib_cam_to_cam.txt``."""
    calib = read_calib_file(path)
    return {c: get_matrix(calib, f"P_rect_0{c}", (3, 4), path) for c in cameras}


def read_raw_rectification(path: str | Path) -> np.ndarray:
    """``R_rect_00`` of a KITTI raw ``calib_cam_to_cam.txt`` as a (4,4) transform (unrectified→rectified cam0)."""
    calib = read_calib_file(path)
    T = np.eye(4)
    T[:3, :3] = get_matrix(calib, "R_rect_00", (3, 3), path)
    return T


def read_rigid_transform(path: str | Path) -> np.ndarray:
    """(4,4) transform from a KITTI raw ``calib_velo_to_cam.txt`` / ``calib_imu_to_velo.txt`` (``R:`` and ``T:``).

    ``calib_velo_to_cam.txt`` gives ``T_cam0_velo``; ``calib_imu_to_velo.txt`` gives ``T_velo_imu``.
    """
    calib = read_calib_file(path)
    T = np.eye(4)
    T[:3, :3] = get_matrix(calib, "R", (3, 3), path)
    T[:3, 3] = get_matrix(calib, "T", (3, 1), path)[:, 0]
    return T


def camera_from_rectified_cam0(P: np.ndarray) -> np.ndarray:
    """(4,4) ``T_camc_cam0rect``: the translation ``K^-1 P[:,3]`` of a rectified projection ``P = K [I | t]``."""
    T = np.eye(4)
    T[:3, 3] = np.linalg.solve(intrinsics_from_projection(P), P[:, 3])
    return T
