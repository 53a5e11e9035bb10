"""The transform that superimposes two paired trajectories: Umeyama SE(3) / Sim(3), scale only, or none. Which poses
pair up (association) is :mod:`dfvo.io.association`.

Convention:
    The alignment ``(s, R, t)`` maps predicted positions onto ground truth, ``p_gt ~ s R p_pred + t``, and is
    applied to whole poses: ``T' = [[R R_i, s R t_i + t], [0, 1]]``. Rigid parts cancel in relative motions,
    so KITTI t_err/r_err and RPE only see the scale; ATE sees everything.
"""

from __future__ import annotations

from enum import StrEnum

import numpy as np

from dfvo.validation import choice, choices


class AlignMode(StrEnum):
    """How a prediction is aligned to the ground truth before the metrics: ``6dof`` (Umeyama SE(3): metric depth),
    ``7dof`` (Sim(3): monocular, up to scale), ``scale`` (scale only), ``none``."""

    se3 = "6dof"
    sim3 = "7dof"
    scale = "scale"
    none = "none"


ALIGN_MODES = tuple(choices(AlignMode))


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity ``dst ~ s R src + t`` (Umeyama 1991).

    Args:
        src: ``(N, 3)`` points.
        dst: ``(N, 3)`` points.
        with_scale: estimate ``s``; otherwise ``s = 1`` (SE(3)).

    Returns:
        ``(s, R (3,3), t (3,))``.
    """
    src = np.asarray(src, np.float64)
    dst = np.asarray(dst, np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"umeyama expects two (N,3) arrays of equal shape, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    u, d, vt = np.linalg.svd(cov)
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2, 2] = -1
    rot = u @ sign @ vt
    var_s = (xs**2).sum() / len(src)
    scale = float(np.trace(np.diag(d) @ sign) / var_s) if with_scale and var_s > 0 else 1.0
    trans = mu_d - scale * rot @ mu_s
    return scale, rot, trans


def rebase_to_first(poses: np.ndarray) -> np.ndarray:
    """Express ``(N,4,4)`` poses ``T_w_c`` relative to their first frame: ``inv(T_w_0) @ T_w_k`` (first = identity).

    The DF-VO toolkit does this to both trajectories before any alignment; it matters for ``scale`` and
    ``none`` alignment and for ATE when a trajectory does not start at the identity.
    """
    poses = np.asarray(poses, np.float64)
    return np.linalg.inv(poses[0]) @ poses


def estimate_alignment(gt: np.ndarray, pred: np.ndarray, align: str) -> tuple[float, np.ndarray, np.ndarray]:
    """Alignment ``(s, R, t)`` of ``pred`` ``(N,4,4)`` onto ``gt`` ``(N,4,4)`` positions for ``align``.

    ``scale`` is the least-squares scale about the origin, ``s = <p_gt, p_pred> / <p_pred, p_pred>``.
    """
    choice(AlignMode, align, "align")
    p_gt, p_pred = gt[:, :3, 3], pred[:, :3, 3]
    if align == "none":
        return 1.0, np.eye(3), np.zeros(3)
    if align == "scale":
        den = float((p_pred**2).sum())
        return (float((p_gt * p_pred).sum()) / den if den > 0 else 1.0), np.eye(3), np.zeros(3)
    return umeyama(p_pred, p_gt, with_scale=align == "7dof")


def apply_alignment(poses: np.ndarray, scale: float, rot: np.ndarray, trans: np.ndarray) -> np.ndarray:
    """Apply ``(s, R, t)`` to ``(N,4,4)`` poses (rotations rotated, positions transformed)."""
    out = np.array(poses, dtype=np.float64, copy=True)
    out[:, :3, :3] = rot @ poses[:, :3, :3]
    out[:, :3, 3] = scale * poses[:, :3, 3] @ rot.T + trans
    return out


def align_trajectory(gt: np.ndarray, pred: np.ndarray, align: str) -> tuple[np.ndarray, dict]:
    """Align ``pred`` onto ``gt``; returns the aligned poses and ``{"scale", "rotation", "translation"}``."""
    s, r, t = estimate_alignment(gt, pred, align)
    return apply_alignment(pred, s, r, t), {"scale": s, "rotation": r.tolist(), "translation": t.tolist()}
