"""KITTI calibration files: odometry ``calib.txt`` and raw ``calib_cam_to_cam.txt`` / ``calib_*_to_*.txt``.

Convention:
    - Every file is ``key: v1 v2 ...`` per line; lines whose values are not all numbers (``calib_time``) are
      kept out of the numeric dictionary, but remembered: asking for such a key as a matrix names the line.
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
from dfvo.data.intrinsics_check import check_matrix

# the KITTI recording car's cameras above the road, metres (Geiger et al. 2013's setup; odometry and raw alike)
KITTI_CAMERA_HEIGHT = 1.65


class CalibValues(dict):
    """``{key: float64 vector}`` of a calibration file, remembering each key's line and the non-numeric lines.

    Attributes:
        path: the file. lines: ``{key: line number}`` of the numeric entries.
        non_numeric: ``{key: (line number, text after the colon)}`` of lines whose values are not all numbers.
    """

    def __init__(self, path: Path) -> None:
        super().__init__()
        self.path = path
        self.lines: dict[str, int] = {}
        self.non_numeric: dict[str, tuple[int, str]] = {}


def read_calib_file(path: str | Path) -> CalibValues:
    """Parse a KITTI calibration file into ``{key: float64 vector}`` (non-numeric lines kept aside).

    Raises:
        DatasetNotFoundError: the file does not exist.
        DatasetError: the file holds no ``key: numbers`` line.
    """
    path = require_file(path, "calibration")
    values = CalibValues(path)
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        key, sep, rest = line.partition(":")
        if not sep:
            continue
        key = key.strip()
        try:
            values[key] = np.array([float(tok) for tok in rest.split()], dtype=np.float64)
            values.lines[key] = lineno
        except ValueError:
            values.non_numeric[key] = (lineno, rest.strip())  # e.g. "calib_time: 09-Jan-2012 13:57:47"
    if not values:
        raise DatasetError(f"calibration file {path} has no 'KEY: numbers' lines")
    return values


def get_matrix(calib: dict[str, np.ndarray], key: str, shape: tuple[int, int], path: str | Path) -> np.ndarray:
    """Entry ``key`` of a parsed calibration reshaped to ``shape``, with an error naming the file (and line)."""
    n = shape[0] * shape[1]
    if key not in calib:
        bad = getattr(calib, "non_numeric", {}).get(key)
        if bad is not None:
            lineno, text = bad
            raise DatasetError(f"calibration file {path} line {lineno}: '{key}:' is not {n} numbers "
                               f"({shape[0]}x{shape[1]} matrix): {text[:60]!r}")
        raise DatasetError(f"calibration file {path} has no '{key}:' line (expected a {shape[0]}x{shape[1]} "
                           f"matrix; found keys {sorted(calib)})")
    vec = calib[key]
    if vec.size != n:
        lineno = getattr(calib, "lines", {}).get(key)
        at = f" line {lineno}" if lineno is not None else ""
        raise DatasetError(f"calibration file {path}{at}: '{key}:' has {vec.size} numbers, expected "
                           f"{n} ({shape[0]}x{shape[1]})")
    return vec.reshape(shape)


def intrinsics_from_projection(P: np.ndarray) -> np.ndarray:
    """(3,3) intrinsics ``K`` of a rectified (3,4) projection matrix ``P = K [I | t]``."""
    K = P[:3, :3].copy()
    K[2] = (0.0, 0.0, 1.0)
    return K


def checked_intrinsics(path: str | Path, key: str, image_hw: tuple[int, int],
                       calib: dict[str, np.ndarray] | None = None) -> np.ndarray:
    """(3,3) float64 intrinsics of the projection matrix ``key`` of a calibration file, checked against the images
    they describe (``image_hw`` = (height, width) of the stored frames) by :mod:`dfvo.data.intrinsics_check`, the
    checks every reader applies (``data=folder`` too).

    Raises:
        IntrinsicsError: ``fx``, ``fy``, ``cx`` or ``cy`` not finite, not positive, outside the image, or an
            implausible field of view; the message names the file, the line and the value.
        DatasetError: the line is missing or malformed (see :func:`get_matrix`).
    """
    calib = read_calib_file(path) if calib is None else calib
    K = intrinsics_from_projection(get_matrix(calib, key, (3, 4), path))
    lineno = getattr(calib, "lines", {}).get(key)
    at = f" line {lineno}" if lineno is not None else ""
    check_matrix(K, int(image_hw[1]), int(image_hw[0]), source=f"calibration file {path}{at} ('{key}:')")
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
