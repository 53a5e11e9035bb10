"""SE(3) helpers that kornia does not already provide.

Convention:
    Poses are (B,4,4) homogeneous matrices. ``T_a_b`` maps points from frame b into frame a. A camera pose in
    a trajectory is ``T_w_c`` (camera to world, as in KITTI pose files). The relative motion between
    consecutive frames is ``T_prev_cur = inv(T_w_prev) @ T_w_cur`` and trajectories accumulate
    ``T_w_cur = T_w_prev @ T_prev_cur``.

Invert poses with :func:`se3_inverse` (any batch shape and dtype); for composition and relative transforms use
``kornia.geometry.linalg.compose_transformations`` and ``relative_transformation``.
"""

from __future__ import annotations

import math

import torch
from kornia.core.check import KORNIA_CHECK
from kornia.geometry.conversions import axis_angle_to_rotation_matrix


def se3_inverse(T: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid transforms in closed form: ``inv([R | t]) = [R^T | -R^T t]``.

    Convention:
        (...,4,4) ``T_a_b`` -> (...,4,4) ``T_b_a``, any batch shape, same dtype and device (the last row is
        written as ``[0, 0, 0, 1]``). ``R`` is assumed orthonormal (no general matrix inverse).
    """
    KORNIA_CHECK(T.ndim >= 2 and tuple(T.shape[-2:]) == (4, 4),
                 f"se3_inverse: expected a (...,4,4) pose tensor, got {tuple(T.shape)}")
    Rt = T[..., :3, :3].transpose(-1, -2)
    out = torch.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3:] = -Rt @ T[..., :3, 3:]
    out[..., 3, 3] = 1
    return out


def pose_from_rt(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Assemble poses from rotations and translations.

    Convention:
        R (B,3,3), t (B,3) or (B,3,1) of ``T_a_b`` -> (B,4,4) ``T_a_b`` in R's dtype.
    """
    B = R.shape[0]
    T = torch.eye(4, dtype=R.dtype, device=R.device).repeat(B, 1, 1)
    T[:, :3, :3] = R
    T[:, :3, 3] = t.reshape(B, 3)
    return T


def pose_from_axis_angle(axis_angle: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
    """Pose from an axis-angle rotation and a translation.

    Convention:
        axis_angle (B,3) radians, translation (B,3) -> (B,4,4) ``[exp([axis_angle]_x) | translation]``.
    """
    return pose_from_rt(axis_angle_to_rotation_matrix(axis_angle), translation)


def rotation_angle(R: torch.Tensor) -> torch.Tensor:
    """Rotation angle of rotation matrices, numerically safe near 0 and pi.

    Convention:
        (...,3,3) -> (...) radians in [0, pi].
    """
    trace = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    cos = ((trace - 1.0) / 2.0).clamp(-1.0, 1.0)
    # atan2 form is accurate for small angles, where acos loses precision
    skew = torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    sin = 0.5 * skew.norm(dim=-1)
    return torch.atan2(sin, cos)


def rotation_error_deg(R_est: torch.Tensor, R_true: torch.Tensor) -> torch.Tensor:
    """Angle of ``R_true^T R_est``.

    Convention:
        (...,3,3) rotations (same frames) -> (...) degrees.
    """
    return rotation_angle(R_true.transpose(-1, -2) @ R_est) * (180.0 / math.pi)


def direction_error_deg(t_est: torch.Tensor, t_true: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Angle between translation directions (their lengths do not matter).

    Convention:
        (...,3) translations in the same frame -> (...) degrees in [0, 180].
    """
    a = t_est / t_est.norm(dim=-1, keepdim=True).clamp_min(eps)
    b = t_true / t_true.norm(dim=-1, keepdim=True).clamp_min(eps)
    cross = torch.linalg.cross(a, b, dim=-1).norm(dim=-1)
    return torch.atan2(cross, (a * b).sum(-1)) * (180.0 / math.pi)
