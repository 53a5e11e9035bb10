"""KITTI odometry metrics (devkit protocol), ATE and RPE, and the one-call ``evaluate_trajectory``.

Convention:
    Poses are ``T_w_c`` ``(N,4,4)``, frame ``k`` of the prediction matching frame ``k`` of ground truth.
    KITTI protocol (``evaluate_odometry.cpp`` of the KITTI devkit): cumulative GT path length ``dist``;
    for every start frame ``first = 0, 10, 20, ...`` and length ``L in 100..800 m`` the end frame is the
    first ``i`` with ``dist[i] > dist[first] + L`` (segment skipped if none);
    ``E = inv(inv(P_first) P_last) (inv(G_first) G_last)``; ``t_err = ||t(E)|| / L``,
    ``r_err = acos(clip(0.5 (trace(R(E)) - 1), -1, 1)) / L``. The sequence value is the mean over *all*
    segments of all lengths (not the mean of per-length means); reported as % and deg/100 m.
    RPE: mean over consecutive pairs of ``inv(ΔG) ΔP`` translation norm (m) and angle (deg).
    ATE: RMSE of position differences. As the DF-VO toolkit does, both trajectories are first expressed
    relative to their first frame (``inv(T_w_0) @ T_w_k``), then the chosen alignment is applied to the whole
    predicted trajectory before all metrics.
"""

from __future__ import annotations

import warnings

import numpy as np

from dfvo.eval.alignment import ALIGN_MODES, align_trajectory, rebase_to_first, umeyama

SEGMENT_LENGTHS = (100, 200, 300, 400, 500, 600, 700, 800)
STEP_SIZE = 10
SCALE_WARN_TOLERANCE = 0.1


def _check_pair(gt: np.ndarray, pred: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    gt, pred = np.asarray(gt, np.float64), np.asarray(pred, np.float64)
    for name, arr in (("gt", gt), ("pred", pred)):
        if arr.ndim != 3 or arr.shape[1:] != (4, 4):
            raise ValueError(f"{name} poses must have shape (N,4,4), got {arr.shape}")
    if len(gt) != len(pred):
        raise ValueError(f"gt has {len(gt)} poses but pred has {len(pred)}; they must match frame by frame")
    if len(gt) < 2:
        raise ValueError(f"need at least 2 poses, got {len(gt)}")
    return gt, pred


def rotation_angle(rot: np.ndarray) -> np.ndarray:
    """Angle (rad) of ``(...,3,3)`` rotations with the devkit formula ``acos(clip(0.5(tr-1), -1, 1))``."""
    tr = rot[..., 0, 0] + rot[..., 1, 1] + rot[..., 2, 2]
    return np.arccos(np.clip(0.5 * (tr - 1.0), -1.0, 1.0))


def trajectory_distances(poses: np.ndarray) -> np.ndarray:
    """Cumulative path length ``(N,)`` of the positions of ``(N,4,4)`` poses, ``dist[0] = 0``."""
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def kitti_segment_errors(gt: np.ndarray, pred: np.ndarray, lengths=SEGMENT_LENGTHS, step: int = STEP_SIZE) -> dict:
    """All devkit segments: arrays ``first, last, length, t_err (1/m... ratio), r_err (rad/m)``."""
    gt, pred = _check_pair(gt, pred)
    dist = trajectory_distances(gt)
    firsts_all = np.arange(0, len(gt), step)
    out = {k: [] for k in ("first", "last", "length", "t_err", "r_err")}
    inv_gt, inv_pred = np.linalg.inv(gt), np.linalg.inv(pred)
    for length in lengths:
        # first index with dist[i] > dist[first] + length (dist is non-decreasing).
        last = np.searchsorted(dist, dist[firsts_all] + length, side="right")
        ok = last < len(gt)
        first, last = firsts_all[ok], last[ok]
        d_gt = inv_gt[first] @ gt[last]
        d_pred = inv_pred[first] @ pred[last]
        err = np.linalg.inv(d_pred) @ d_gt
        out["first"].append(first)
        out["last"].append(last)
        out["length"].append(np.full(len(first), float(length)))
        out["t_err"].append(np.linalg.norm(err[:, :3, 3], axis=1) / length)
        out["r_err"].append(rotation_angle(err[:, :3, :3]) / length)
    return {k: np.concatenate(v) for k, v in out.items()}


def relative_pose_error(gt: np.ndarray, pred: np.ndarray) -> tuple[float, float]:
    """RPE: mean frame-to-frame ``(translation m, rotation deg)`` of ``inv(ΔG) ΔP``."""
    gt, pred = _check_pair(gt, pred)
    d_gt = np.linalg.inv(gt[:-1]) @ gt[1:]
    d_pred = np.linalg.inv(pred[:-1]) @ pred[1:]
    err = np.linalg.inv(d_gt) @ d_pred
    return float(np.linalg.norm(err[:, :3, 3], axis=1).mean()), float(np.degrees(rotation_angle(err[:, :3, :3])).mean())


def absolute_trajectory_error(gt: np.ndarray, pred: np.ndarray) -> float:
    """ATE: RMSE (m) of position differences of already aligned ``(N,4,4)`` trajectories."""
    gt, pred = _check_pair(gt, pred)
    return float(np.sqrt(np.mean(np.sum((gt[:, :3, 3] - pred[:, :3, 3]) ** 2, axis=1))))


def evaluate_trajectory(gt: np.ndarray, pred: np.ndarray, align: str = "7dof") -> dict:
    """All odometry metrics for one sequence.

    Args:
        gt: ``(N,4,4)`` ground-truth ``T_w_c``.
        pred: ``(N,4,4)`` predicted ``T_w_c``.
        align: ``"6dof"``, ``"7dof"``, ``"scale"`` or ``"none"``, applied to ``pred`` before all metrics.

    Returns:
        dict with ``t_err_pct``, ``r_err_deg_per_100m`` (None when no 100 m segment exists), ``ate_m``,
        ``rpe_m``, ``rpe_deg``, ``num_frames``, ``num_segments``, ``align``, ``align_scale``,
        ``sim3_scale`` (the 7-DoF scale, for diagnosis), ``scale_warning`` (str or None), ``per_length``.
    """
    if align not in ALIGN_MODES:
        raise ValueError(f"align={align!r}: expected one of {ALIGN_MODES}")
    gt, pred = _check_pair(gt, pred)
    gt, pred = rebase_to_first(gt), rebase_to_first(pred)
    aligned, params = align_trajectory(gt, pred, align)
    sim3_scale = umeyama(pred[:, :3, 3], gt[:, :3, 3], with_scale=True)[0]
    scale_warning = None
    if align in ("6dof", "none") and abs(sim3_scale - 1.0) > SCALE_WARN_TOLERANCE:
        scale_warning = (f"align={align} keeps the predicted scale, but the best 7-DoF scale is {sim3_scale:.3f} "
                         f"(off by more than {SCALE_WARN_TOLERANCE:.0%}); a monocular (up-to-scale) trajectory "
                         "should be evaluated with align=7dof or align=scale")
        warnings.warn(scale_warning, stacklevel=2)
    seg = kitti_segment_errors(gt, aligned)
    per_length = {}
    for length in SEGMENT_LENGTHS:
        sel = seg["length"] == length
        n = int(sel.sum())
        per_length[str(length)] = {
            "t_err_pct": float(seg["t_err"][sel].mean() * 100) if n else None,
            "r_err_deg_per_100m": float(np.degrees(seg["r_err"][sel].mean()) * 100) if n else None,
            "num_segments": n,
        }
    has = len(seg["t_err"]) > 0
    rpe_m, rpe_deg = relative_pose_error(gt, aligned)
    return {
        "t_err_pct": float(seg["t_err"].mean() * 100) if has else None,
        "r_err_deg_per_100m": float(np.degrees(seg["r_err"].mean()) * 100) if has else None,
        "ate_m": absolute_trajectory_error(gt, aligned),
        "rpe_m": rpe_m,
        "rpe_deg": rpe_deg,
        "num_frames": int(len(gt)),
        "num_segments": int(len(seg["t_err"])),
        "align": align,
        "align_scale": float(params["scale"]),
        "sim3_scale": float(sim3_scale),
        "scale_warning": scale_warning,
        "per_length": per_length,
    }
