"""KITTI odometry metrics (devkit protocol), ATE and RPE, and the one-call ``evaluate_trajectory``.

Convention:
    Poses are ``T_w_c`` ``(N,4,4)``, frame ``k`` of the prediction matching frame ``k`` of ground truth; an
    optional ``valid`` ``(N,)`` mask marks the frames that have a prediction (sparse or prefix predictions laid
    on the ground truth's frames by :func:`dfvo.io.association.associate_trajectories`).
    KITTI protocol (``evaluate_odometry.cpp`` of the KITTI devkit): cumulative GT path length ``dist`` over all
    ground-truth frames; for every start frame ``first = 0, 10, 20, ...`` and length ``L in 100..800 m`` the end
    frame is the first ``i`` with ``dist[i] > dist[first] + L`` (segment skipped if none, or if ``first`` or
    ``i`` has no prediction, as in the DF-VO authors' toolkit);
    ``E = inv(inv(P_first) P_last) (inv(G_first) G_last)``; ``t_err = ||t(E)|| / L``,
    ``r_err = acos(clip(0.5 (trace(R(E)) - 1), -1, 1)) / L``. The sequence value is the mean over *all*
    segments of all lengths (not the mean of per-length means); reported as % and deg/100 m.
    RPE: mean over consecutive frame pairs ``(k, k+1)`` (both predicted) of ``inv(ΔG) ΔP`` translation norm (m)
    and angle (deg). ATE: RMSE of position differences over predicted frames. As the DF-VO toolkit does, both
    trajectories are first expressed relative to their first predicted frame (``inv(T_w_0) @ T_w_k``), then the
    alignment estimated on the predicted frames is applied to the whole predicted trajectory before all metrics.
"""

from __future__ import annotations

import warnings

import numpy as np

from dfvo.eval.alignment import AlignMode, apply_alignment, estimate_alignment, umeyama
from dfvo.validation import choice

SEGMENT_LENGTHS = (100, 200, 300, 400, 500, 600, 700, 800)
STEP_SIZE = 10
SCALE_WARN_TOLERANCE = 0.1


def _check_pair(gt: np.ndarray, pred: np.ndarray, valid: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    gt, pred = np.asarray(gt, np.float64), np.asarray(pred, np.float64)
    for name, arr in (("gt", gt), ("pred", pred)):
        if arr.ndim != 3 or arr.shape[1:] != (4, 4):
            raise ValueError(f"{name} poses must have shape (N,4,4), got {arr.shape}")
    if len(gt) != len(pred):
        raise ValueError(f"gt has {len(gt)} poses but pred has {len(pred)}; they must match frame by frame")
    valid = np.ones(len(gt), bool) if valid is None else np.asarray(valid, bool)
    if valid.shape != (len(gt),):
        raise ValueError(f"valid must have shape ({len(gt)},), got {valid.shape}")
    if valid.sum() < 2:
        raise ValueError(f"need at least 2 (predicted) poses, got {int(valid.sum())}")
    for name, arr in (("gt", gt), ("pred", pred[valid])):
        bad = np.flatnonzero(~np.isfinite(arr).all(axis=(1, 2)))
        if len(bad):
            raise ValueError(f"{name} pose {bad[0]} is not finite ({len(bad)} such); drop the frames without a "
                             "ground-truth pose (or mark missing predictions with valid=False) first")
    return gt, pred, valid


def rotation_angle(rot: np.ndarray) -> np.ndarray:
    """Angle (rad) of ``(...,3,3)`` rotations with the devkit formula ``acos(clip(0.5(tr-1), -1, 1))``."""
    tr = rot[..., 0, 0] + rot[..., 1, 1] + rot[..., 2, 2]
    return np.arccos(np.clip(0.5 * (tr - 1.0), -1.0, 1.0))


def trajectory_distances(poses: np.ndarray) -> np.ndarray:
    """Cumulative path length ``(N,)`` of the positions of ``(N,4,4)`` poses, ``dist[0] = 0``."""
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def kitti_segment_errors(gt: np.ndarray, pred: np.ndarray, lengths=SEGMENT_LENGTHS, step: int = STEP_SIZE,
                         valid: np.ndarray | None = None) -> dict:
    """All devkit segments: arrays ``first, last, length, t_err (ratio), r_err (rad/m)``; segments whose first or
    last frame is not ``valid`` are skipped."""
    gt, pred, valid = _check_pair(gt, pred, valid)
    dist = trajectory_distances(gt)
    firsts_all = np.arange(0, len(gt), step)
    out = {k: [] for k in ("first", "last", "length", "t_err", "r_err")}
    inv_gt, inv_pred = np.linalg.inv(gt), np.linalg.inv(pred)
    for length in lengths:
        # first index with dist[i] > dist[first] + length (dist is non-decreasing).
        last = np.searchsorted(dist, dist[firsts_all] + length, side="right")
        ok = last < len(gt)
        ok[ok] &= valid[firsts_all[ok]] & valid[last[ok]]
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


def relative_pose_errors(gt: np.ndarray, pred: np.ndarray,
                         valid: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pair ``(k, k+1)`` with both frames ``valid``: ``(pairs (P,) int k, translation errors (P,) m, rotation
    errors (P,) deg)`` of ``inv(ΔG) ΔP`` (what :func:`relative_pose_error` averages)."""
    gt, pred, valid = _check_pair(gt, pred, valid)
    pair = np.flatnonzero(valid[:-1] & valid[1:])
    d_gt = np.linalg.inv(gt[pair]) @ gt[pair + 1]
    d_pred = np.linalg.inv(pred[pair]) @ pred[pair + 1]
    err = np.linalg.inv(d_gt) @ d_pred
    return pair, np.linalg.norm(err[:, :3, 3], axis=1), np.degrees(rotation_angle(err[:, :3, :3]))


def relative_pose_error(gt: np.ndarray, pred: np.ndarray,
                        valid: np.ndarray | None = None) -> tuple[float | None, float | None]:
    """RPE: mean frame-to-frame ``(translation m, rotation deg)`` of ``inv(ΔG) ΔP`` over pairs ``(k, k+1)`` that
    are both ``valid``; ``(None, None)`` when there is no such pair."""
    pair, t_err, r_err = relative_pose_errors(gt, pred, valid)
    if len(pair) == 0:
        return None, None
    return float(t_err.mean()), float(r_err.mean())


def absolute_trajectory_error(gt: np.ndarray, pred: np.ndarray, valid: np.ndarray | None = None) -> float:
    """ATE: RMSE (m) of position differences of already aligned ``(N,4,4)`` trajectories (over ``valid`` frames)."""
    gt, pred, valid = _check_pair(gt, pred, valid)
    return float(np.sqrt(np.mean(np.sum((gt[valid, :3, 3] - pred[valid, :3, 3]) ** 2, axis=1))))


def aligned_prediction(gt: np.ndarray, pred: np.ndarray, align: str = "7dof",
                       valid: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """The trajectories as the metrics see them: ``(gt, pred)`` re-based to their first valid frame, ``pred``
    aligned onto ``gt`` (alignment estimated on the valid frames), and ``{"scale", "rotation", "translation"}``.
    All arrays ``(N,4,4)``. Frames whose ground truth is NaN (none) are left out of the alignment and stay NaN in the
    returned ``gt``."""
    gt = np.asarray(gt, np.float64)
    gt_known = np.isfinite(gt).all(axis=(1, 2)) if gt.ndim == 3 else np.ones(len(gt), bool)
    valid = (np.ones(len(gt), bool) if valid is None else np.asarray(valid, bool)) & gt_known
    gt, pred, valid = _check_pair(np.where(gt_known[:, None, None], gt, np.eye(4)), pred, valid)
    first = int(np.argmax(valid))
    gt, pred = np.linalg.inv(gt[first]) @ gt, np.linalg.inv(pred[first]) @ pred
    gt[~gt_known] = np.nan
    params = dict(zip(("scale", "rotation", "translation"), estimate_alignment(gt[valid], pred[valid], align)))
    return gt, pred, apply_alignment(pred, params["scale"], params["rotation"], params["translation"]), params


def evaluate_trajectory(gt: np.ndarray, pred: np.ndarray, align: str = "7dof", valid: np.ndarray | None = None) -> dict:
    """All odometry metrics for one sequence.

    Args:
        gt: ``(N,4,4)`` ground-truth ``T_w_c``.
        pred: ``(N,4,4)`` predicted ``T_w_c``.
        align: ``"6dof"``, ``"7dof"``, ``"scale"`` or ``"none"``, applied to ``pred`` before all metrics.
        valid: ``(N,)`` bool, frames that have a prediction (default: all). Frames whose ground truth is not
            finite (NaN: no ground truth) are left out and counted in ``gt_missing``.

    Returns:
        dict with ``t_err_pct``, ``r_err_deg_per_100m`` (None when no 100 m segment exists), ``ate_m``,
        ``rpe_m``, ``rpe_deg`` (None without two consecutive predicted frames), ``num_frames`` (predicted
        frames evaluated), ``num_gt_frames``, ``gt_missing``, ``num_segments``, ``align``, ``align_scale``,
        ``sim3_scale`` (the 7-DoF scale, for diagnosis), ``scale_warning`` (str or None), ``per_length``.
    """
    choice(AlignMode, align, "align")
    gt, pred = np.asarray(gt, np.float64), np.asarray(pred, np.float64)
    gt_known = np.isfinite(gt).all(axis=(1, 2)) if gt.ndim == 3 else None
    gt_missing = 0
    if gt_known is not None and not gt_known.all() and len(gt) == len(pred):  # frames without ground truth (NaN)
        gt_missing = int((~gt_known).sum())
        gt, pred = gt[gt_known], pred[gt_known]
        valid = None if valid is None else np.asarray(valid, bool)[gt_known]
    gt, pred, valid = _check_pair(gt, pred, valid)
    gt, pred, aligned, params = aligned_prediction(gt, pred, align, valid)
    sim3_scale = umeyama(pred[valid, :3, 3], gt[valid, :3, 3], with_scale=True)[0]
    scale_warning = None
    if align in ("6dof", "none") and abs(sim3_scale - 1.0) > SCALE_WARN_TOLERANCE:
        scale_warning = (f"align={align} keeps the predicted scale, but the best 7-DoF scale is {sim3_scale:.3f} "
                         f"(off by more than {SCALE_WARN_TOLERANCE:.0%}); a monocular (up-to-scale) trajectory "
                         "should be evaluated with align=7dof or align=scale")
        warnings.warn(scale_warning, stacklevel=2)
    seg = kitti_segment_errors(gt, aligned, valid=valid)
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
    rpe_m, rpe_deg = relative_pose_error(gt, aligned, valid)
    return {
        "t_err_pct": float(seg["t_err"].mean() * 100) if has else None,
        "r_err_deg_per_100m": float(np.degrees(seg["r_err"].mean()) * 100) if has else None,
        "ate_m": absolute_trajectory_error(gt, aligned, valid),
        "rpe_m": rpe_m,
        "rpe_deg": rpe_deg,
        "num_frames": int(valid.sum()),
        "num_gt_frames": int(len(gt)),
        "gt_missing": gt_missing,
        "num_segments": int(len(seg["t_err"])),
        "align": align,
        "align_scale": float(params["scale"]),
        "sim3_scale": float(sim3_scale),
        "scale_warning": scale_warning,
        "per_length": per_length,
    }
