"""Putting two trajectories in correspondence: which poses pair up (association), and the transform that
superimposes them (alignment: Umeyama SE(3) / Sim(3), scale only, or none).

Convention:
    Association (:func:`associate_trajectories`) pairs a prediction with its ground truth, in this order of
    preference: by nearest timestamp within ``max_time_diff`` seconds when both have timestamps (as evo's
    ``associate_trajectories``: each pose of the shorter trajectory takes the closest pose of the longer one,
    one-to-one); by frame index when the prediction has frame indices (KITTI files with 13 numbers a line; the
    ground truth without indices counts its lines from 0); else line by line, where a shorter prediction is
    accepted only as a prefix with ``allow_prefix``. The result lays the prediction on the ground truth's rows
    with a ``valid`` mask, so that sparse predictions are evaluated on the ground truth's own frames (segment
    lengths, frame steps), as the DF-VO authors' KITTI toolkit does with 13-number files.

    The alignment ``(s, R, t)`` maps predicted positions onto ground truth, ``p_gt ~ s R p_pred + t``, and is
    applied to whole poses: ``T' = [[R R_i, s R t_i + t], [0, 1]]``. Rigid parts cancel in relative motions,
    so KITTI t_err/r_err and RPE only see the scale; ATE sees everything.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from dfvo.eval.trajectory_io import Trajectory
from dfvo.validation import choice, choices


class AlignMode(StrEnum):
    """How a prediction is aligned to the ground truth before the metrics: ``6dof`` (Umeyama SE(3): metric depth),
    ``7dof`` (Sim(3): monocular, up to scale), ``scale`` (scale only), ``none``."""

    se3 = "6dof"
    sim3 = "7dof"
    scale = "scale"
    none = "none"


ALIGN_MODES = tuple(choices(AlignMode))
ASSOCIATION_METHODS = ("order", "prefix", "frame_index", "timestamp")


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


# ------------------------------------------------------------------------------------------------ association


@dataclass
class Association:
    """A prediction laid on ground-truth rows.

    Attributes:
        gt: ``(M,4,4)`` ground-truth ``T_w_c`` (all its poses; for timestamp association the matched ones).
        pred: ``(M,4,4)`` predicted ``T_w_c`` on the same rows (identity where ``valid`` is False).
        valid: ``(M,)`` bool, rows that have a prediction.
        method: one of :data:`ASSOCIATION_METHODS`.
        num_gt: poses in the ground-truth file; num_pred: poses in the prediction file.
        max_time_diff: the tolerance (s) of timestamp association, else None.
        max_abs_dt: the largest |time difference| (s) among matched pairs (timestamp association), else None.
    """

    gt: np.ndarray
    pred: np.ndarray
    valid: np.ndarray
    method: str
    num_gt: int
    num_pred: int
    max_time_diff: float | None = None
    max_abs_dt: float | None = None

    @property
    def num_matched(self) -> int:
        return int(self.valid.sum())

    def describe(self) -> str:
        """One line saying how the poses were paired and how many matched."""
        k, n, m = self.num_matched, self.num_pred, self.num_gt
        if self.method == "order":
            return f"all {k} poses, paired line by line"
        if self.method == "prefix":
            return f"prefix: the first {k} of {m} ground-truth poses (allow_prefix=true)"
        if self.method == "frame_index":
            return f"{k} of {n} predicted poses matched by frame index ({m} ground-truth frames)"
        return (f"{k} of {n} predicted poses matched by timestamp within {self.max_time_diff:g} s "
                f"({m} ground-truth poses, largest |dt| {self.max_abs_dt:.3g} s)")

    def as_dict(self) -> dict:
        return {"method": self.method, "matched": self.num_matched, "pred_poses": self.num_pred,
                "gt_poses": self.num_gt, "max_time_diff": self.max_time_diff, "max_abs_dt": self.max_abs_dt,
                "description": self.describe()}


def match_timestamps(stamps_a: np.ndarray, stamps_b: np.ndarray, max_time_diff: float) -> tuple[np.ndarray, ...]:
    """Nearest-timestamp pairs: for each ``stamps_a[i]`` the closest ``stamps_b[j]`` with ``|dt| <= max_time_diff``
    (ties to the earlier), each ``j`` used once (the closest ``i`` keeps it).

    Returns:
        ``(ia, ib)`` int arrays of equal length, ordered by ``stamps_b``.
    """
    a, b = np.asarray(stamps_a, np.float64), np.asarray(stamps_b, np.float64)
    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    order_b = np.argsort(b, kind="stable")
    bs = b[order_b]
    ins = np.searchsorted(bs, a)
    lo, hi = np.clip(ins - 1, 0, len(bs) - 1), np.clip(ins, 0, len(bs) - 1)
    d_lo, d_hi = np.abs(a - bs[lo]), np.abs(bs[hi] - a)
    best = np.where(d_hi < d_lo, hi, lo)
    dist = np.minimum(d_lo, d_hi)
    ia = np.flatnonzero(dist <= max_time_diff)
    ia = ia[np.lexsort((dist[ia], best[ia]))]  # by partner, closest first
    first = np.ones(len(ia), bool)
    first[1:] = best[ia][1:] != best[ia][:-1]
    ia = ia[first]
    return ia, order_b[best[ia]]


def associate_trajectories(gt: Trajectory, pred: Trajectory, max_time_diff: float = 0.01, time_offset: float = 0.0,
                           allow_prefix: bool = False) -> Association:
    """Pair ``pred`` with ``gt`` (see the module's Convention).

    Args:
        gt: ground truth.
        pred: prediction.
        max_time_diff: timestamp tolerance (s).
        time_offset: added to the prediction's timestamps before matching (s).
        allow_prefix: accept a line-by-line prediction shorter than the ground truth as its first poses.

    Raises:
        ValueError: fewer than 2 matched poses, a longer line-by-line prediction, or a shorter one without
            ``allow_prefix`` (the message names both files).
    """
    n, m = len(pred), len(gt)
    where = f"{pred.source} ({n} poses) vs {gt.source} ({m} poses)"
    if gt.timestamps is not None and pred.timestamps is not None:
        t_pred = pred.timestamps + time_offset
        short_is_pred = n <= m
        i_s, i_l = match_timestamps(t_pred if short_is_pred else gt.timestamps,
                                    gt.timestamps if short_is_pred else t_pred, max_time_diff)
        ip, ig = (i_s, i_l) if short_is_pred else (i_l, i_s)
        order = np.argsort(gt.timestamps[ig], kind="stable")
        ip, ig = ip[order], ig[order]
        if len(ip) < 2:
            raise ValueError(f"{where}: {len(ip)} poses matched by timestamp within max_time_diff={max_time_diff:g} s "
                             f"(prediction {t_pred.min():.3f}..{t_pred.max():.3f} s, ground truth "
                             f"{gt.timestamps.min():.3f}..{gt.timestamps.max():.3f} s); check the time unit, "
                             "time_offset or max_time_diff")
        dt = float(np.abs(t_pred[ip] - gt.timestamps[ig]).max())
        return Association(gt.poses[ig], pred.poses[ip], np.ones(len(ip), bool), "timestamp", m, n,
                           float(max_time_diff), dt)
    placed = np.tile(np.eye(4), (m, 1, 1))
    valid = np.zeros(m, bool)
    if pred.frame_ids is not None:
        if gt.frame_ids is not None and np.any(np.diff(gt.frame_ids) < 0):
            gt = gt.select(np.argsort(gt.frame_ids, kind="stable"))
        gt_ids = gt.frame_ids if gt.frame_ids is not None else np.arange(m)
        rows = np.searchsorted(gt_ids, pred.frame_ids)
        hit = (rows < m) & (gt_ids[np.minimum(rows, m - 1)] == pred.frame_ids)
        if hit.sum() < 2:
            raise ValueError(f"{where}: {int(hit.sum())} predicted frame indices exist in the ground truth "
                             f"(prediction frames {pred.frame_ids.min()}..{pred.frame_ids.max()}, ground truth "
                             f"{gt_ids.min()}..{gt_ids.max()})")
        placed[rows[hit]], valid[rows[hit]] = pred.poses[hit], True
        return Association(gt.poses, placed, valid, "frame_index", m, n)
    hint = ("" if pred.timestamps is None or gt.timestamps is not None else
            "; or, to pair by time, give the ground truth's timestamps (gt_times=times.txt)")
    if n > m:
        raise ValueError(f"{where}: the prediction has more poses than the ground truth{hint}")
    if n < m and not allow_prefix:
        raise ValueError(f"{where}: the prediction is shorter than the ground truth; pass allow_prefix=true to "
                         f"evaluate its {n} poses against the first {n} of the ground truth{hint}")
    placed[:n], valid[:n] = pred.poses, True
    return Association(gt.poses, placed, valid, "order" if n == m else "prefix", m, n)
