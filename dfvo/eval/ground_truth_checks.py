"""Checks of a ground-truth trajectory itself: stretches where its rotation was interpolated, not measured.

KITTI's odometry ground truth comes from a GPS/IMU (OXTS RT3003). A real car's frame-to-frame rotation varies from
frame to frame (KITTI 00-10: median change 0.10-0.19 deg between consecutive pairs, on every axis's largest), but
some stretches of the ground truth turn at one constant rate for 10-15 frames, to a thousandth of a degree: the
poses there were interpolated (e.g. the first 12 frames of sequences 00 and 06). A visual odometry that measures the
real rotation differs from such a stretch by the car's real rotation changes, so a rotation RPE there measures the
ground truth, not the estimate. :func:`constant_rate_segments` finds these stretches; ``studies/gt_constant_rate.py``
reports them and a run's RPE inside and outside.

Convention:
    Poses ``T_w_c`` (N,4,4) (camera to world). Pair ``k`` is frames ``(k, k+1)``; its relative rotation
    ``R_k = R_w_k^T R_w_{k+1}`` as a rotation vector in degrees. A segment ``(first, count)`` is the pairs
    ``first .. first + count - 1``.
"""

from __future__ import annotations

import numpy as np

from dfvo.geometry.pose_covariance import so3_log

__all__ = ["pair_rotations_deg", "rotation_changes_deg", "constant_rate_segments", "pairs_in_segments"]


def pair_rotations_deg(poses: np.ndarray) -> np.ndarray:
    """(N-1,3) rotation vectors in degrees of the pairs' relative rotations ``R_k`` of (N,4,4) or (N,3,4) poses
    (angles below 180 deg; :func:`dfvo.geometry.pose_covariance.so3_log`)."""
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] not in ((4, 4), (3, 4)):
        raise ValueError(f"ground-truth check: poses of shape {poses.shape}; expected (N,4,4) or (N,3,4)")
    rot = np.einsum("nji,njk->nik", poses[:-1, :3, :3], poses[1:, :3, :3])
    return np.degrees(so3_log(rot).numpy())


def rotation_changes_deg(rates: np.ndarray) -> np.ndarray:
    """(P-2,) the largest axis of each second difference ``R_{k+2} - 2 R_{k+1} + R_k`` of the pairs' rotation
    vectors ``rates`` (P,3) degrees (:func:`pair_rotations_deg`): how much the rotation rate changes around pair
    ``k+1``."""
    return np.abs(rates[2:] - 2.0 * rates[1:-1] + rates[:-2]).max(1)


def constant_rate_segments(poses: np.ndarray, threshold_deg: float = 0.01,
                           min_pairs: int = 8) -> list[tuple[int, int]]:
    """Stretches of at least ``min_pairs`` consecutive pairs whose relative rotations are all the same to within
    ``threshold_deg``: every second difference ``R_{k+2} - 2 R_{k+1} + R_k`` of the pairs' rotation vectors is
    below ``threshold_deg`` on every axis.

    Args:
        poses: (N,4,4) or (N,3,4) ``T_w_c``.

    Returns:
        ``[(first_pair, count), ...]`` in order, disjoint.
    """
    if len(poses) < 4:
        return []
    steady = rotation_changes_deg(pair_rotations_deg(poses)) < threshold_deg  # (P-2,): pairs k, k+1, k+2 agree
    segments, k = [], 0
    while k < len(steady):
        if not steady[k]:
            k += 1
            continue
        end = k
        while end < len(steady) and steady[end]:
            end += 1
        count = end - k + 2  # a run of m steady second differences spans m + 2 pairs
        if count >= min_pairs:
            segments.append((k, count))
        k = end
    return segments


def pairs_in_segments(segments: list[tuple[int, int]], num_pairs: int) -> np.ndarray:
    """(num_pairs,) bool: pair ``k`` lies in one of ``segments``."""
    mask = np.zeros(num_pairs, dtype=bool)
    for first, count in segments:
        mask[first:first + count] = True
    return mask
