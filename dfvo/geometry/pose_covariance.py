"""Covariances of relative and absolute poses: the error convention, its propagation along a trajectory, ROS's
order and frames, and the flat form of ``frames.csv``. The estimation of each step's covariance is
:mod:`dfvo.tracking.covariance`.

Convention (one for the whole package: ``frames.csv``, :class:`dfvo.api.Odometry`, the ROS bag):
    The covariance of a relative step ``T_prev_cur`` (4,4; maps points of the current camera into the previous one) is
    that of its error 6-vector ``xi = [phi (3, rad), dt (3, m)]`` with

        R_true = exp([phi]_x) R_est,     t_true = t_est + dt,

    both expressed in the axes of the previous camera (x right, y down, z forward). Order: ``[rx, ry, rz, tx, ty,
    tz]`` (:data:`PARAMETERS`). :func:`step_error` computes ``xi`` from an estimate and the truth, so the normalised
    estimation error squared is ``xi^T C^-1 xi`` (:func:`nees`; 6 degrees of freedom when ``C`` is calibrated). A
    world pose's covariance uses the same convention with the world's axes. The ROS messages use their own order
    (translation first) and frames: :func:`ros_pose_covariance` and :func:`ros_twist_covariance`.
"""

from __future__ import annotations

import numpy as np
import torch

from dfvo.geometry.essential_refine import skew

__all__ = ["PARAMETERS", "COVARIANCE_FIELDS", "antisymmetric_vee", "so3_log", "symmetric", "step_error", "nees",
           "propagate_pose_covariance", "ros_pose_covariance", "ros_twist_covariance", "covariance_to_row",
           "covariance_from_row"]

PARAMETERS = ("rx", "ry", "rz", "tx", "ty", "tz")
"""Order of the 6-vector of the step's error (rotation vector in rad, translation in m; previous camera's axes)."""

COVARIANCE_FIELDS = [f"cov_{PARAMETERS[i]}_{PARAMETERS[j]}" for i in range(6) for j in range(i, 6)]
"""The 21 columns of the upper triangle (row by row) in ``frames.csv``."""


def symmetric(C: torch.Tensor) -> torch.Tensor:
    """The symmetric part of (...,n,n) matrices (rounding asymmetry removed)."""
    return 0.5 * (C + C.transpose(-1, -2))


def so3_log(R: torch.Tensor | np.ndarray) -> torch.Tensor:
    """Rotation vectors (...,3) of rotation matrices (...,3,3) (torch or numpy), float64 (exact for angles below
    pi; below 1e-6 rad the first-order ``vee(R - R^T) / 2``)."""
    R = torch.as_tensor(R, dtype=torch.float64)
    cos = ((torch.diagonal(R, dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0).clamp(-1.0, 1.0)
    angle = torch.arccos(cos)
    v = antisymmetric_vee(R) * 2.0  # 2 sin(angle) axis
    small = angle < 1e-6
    factor = torch.where(small, torch.full_like(angle, 0.5), angle / (2.0 * torch.sin(angle)).masked_fill(small, 1.0))
    return v * factor[..., None]

def antisymmetric_vee(M: torch.Tensor) -> torch.Tensor:
    """The rotation vector of a rotation matrix ``M`` near the identity, to first order (exact derivative at I)."""
    A = 0.5 * (M - M.transpose(-1, -2))
    return torch.stack([A[..., 2, 1], A[..., 0, 2], A[..., 1, 0]], -1)


def step_error(T_est: torch.Tensor, T_true: torch.Tensor) -> torch.Tensor:
    """The error 6-vectors ``[phi, dt]`` (...,6) (module convention) of estimated steps ``T_est`` (...,4,4) against
    the true ``T_true`` (...,4,4) (broadcast): ``R_true = exp([phi]) R_est``, ``t_true = t_est + dt``."""
    T_est, T_true = torch.as_tensor(T_est, dtype=torch.float64), torch.as_tensor(T_true, dtype=torch.float64)
    phi = so3_log(T_true[..., :3, :3] @ T_est[..., :3, :3].transpose(-1, -2))
    return torch.cat([phi, T_true[..., :3, 3] - T_est[..., :3, 3]], -1)


def nees(error: torch.Tensor, covariance: torch.Tensor) -> float:
    """Normalised estimation error squared ``e^T C^-1 e`` (chi-square with len(e) degrees of freedom when ``C`` is
    the error's covariance)."""
    e = torch.as_tensor(error, dtype=torch.float64)
    C = torch.as_tensor(covariance, dtype=torch.float64)
    return float(e @ torch.linalg.solve(C, e))


def propagate_pose_covariance(cov_w_prev: torch.Tensor, T_w_prev: torch.Tensor, cov_step: torch.Tensor,
                              T_prev_cur: torch.Tensor) -> torch.Tensor:
    """Covariance of ``T_w_cur = T_w_prev @ T_prev_cur`` to first order, steps independent.

    Both pose covariances use the module's convention with the world's axes (``R_true = exp([phi]) R``, ``t_true =
    t + dt`` in world coordinates); ``cov_step`` is the step's (previous camera's axes).
    """
    Tw = torch.as_tensor(T_w_prev, dtype=torch.float64)
    Ts = torch.as_tensor(T_prev_cur, dtype=torch.float64)
    Rw = Tw[:3, :3]
    F = torch.eye(6, dtype=torch.float64)
    F[3:, :3] = -skew(Rw @ Ts[:3, 3])
    G = torch.zeros(6, 6, dtype=torch.float64)
    G[:3, :3], G[3:, 3:] = Rw, Rw
    return symmetric(F @ torch.as_tensor(cov_w_prev, dtype=torch.float64) @ F.T + G @ cov_step @ G.T)


def ros_pose_covariance(cov_w: torch.Tensor) -> list[float]:
    """A world-pose covariance (module convention, world axes) as the 36 row-major numbers of
    ``geometry_msgs/PoseWithCovariance``: order (x, y, z, rotation about X, Y, Z), fixed (parent-frame) axes."""
    C = torch.as_tensor(cov_w, dtype=torch.float64)
    order = [3, 4, 5, 0, 1, 2]
    return C[order][:, order].reshape(-1).tolist()


def ros_twist_covariance(cov_step: torch.Tensor, T_prev_cur: torch.Tensor, dt: float) -> list[float]:
    """The step's covariance as that of ``geometry_msgs/TwistWithCovariance`` in the child (current camera) frame:
    velocity = step / ``dt``, rotated into the current camera's axes, order (vx, vy, vz, wx, wy, wz)."""
    Rt = torch.as_tensor(T_prev_cur, dtype=torch.float64)[:3, :3].T
    G = torch.zeros(6, 6, dtype=torch.float64)
    G[:3, 3:], G[3:, :3] = Rt, Rt  # (v, w) from (phi, dt)
    C = G @ torch.as_tensor(cov_step, dtype=torch.float64) @ G.T / (dt * dt)
    return symmetric(C).reshape(-1).tolist()


def covariance_to_row(cov: torch.Tensor | None) -> dict[str, float | None]:
    """The 21 upper-triangle entries (:data:`COVARIANCE_FIELDS`) of a (6,6) covariance, for ``frames.csv``."""
    if cov is None:
        return {k: None for k in COVARIANCE_FIELDS}
    C = torch.as_tensor(cov, dtype=torch.float64)
    iu = torch.triu_indices(6, 6)
    return dict(zip(COVARIANCE_FIELDS, C[iu[0], iu[1]].tolist(), strict=True))


def covariance_from_row(row: dict[str, object]) -> torch.Tensor | None:
    """The (6,6) covariance of a ``frames.csv`` row (None when the row has none, e.g. frame 0)."""
    values = [row.get(k) for k in COVARIANCE_FIELDS]
    if any(v in (None, "") for v in values):
        return None
    C = torch.zeros(6, 6, dtype=torch.float64)
    iu = torch.triu_indices(6, 6)
    C[iu[0], iu[1]] = torch.tensor([float(v) for v in values], dtype=torch.float64)
    return C + C.T - torch.diag(torch.diagonal(C))
