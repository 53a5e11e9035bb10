"""Camera-height scale: the road plane among the points the E-tracker triangulated, and the known camera height.

The E-tracker's pose has a unit translation, so the points it triangulates are in units of the (unknown) length of
that translation; so is the camera's height above the road plane fitted to them. With the camera's true height
``H`` (metres) above the road, ``H / fitted height`` is the translation's metric length: a scale observation that
does not depend on the depth network (whose metric scale varies from road to road).

Convention:
    Points ``X`` (B,N,3) in the camera frame of the earlier image i (x right, y down, z forward), in the unit of the
    E-tracker's translation; ``pts`` (B,N,2) their pixels in image i; ``K`` (B,3,3). The road plane is
    ``n . X = d`` with unit normal ``n`` pointing down (``n_y > 0``) and ``d > 0`` the camera's height above it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE

from dfvo.geometry.ransac import sample_rows
from dfvo.tracking.config import RoadPlaneConfig

MAD_TO_STD = 1.4826

__all__ = ["RoadPlane", "road_candidates", "road_grid", "fit_road_plane", "parallax_deg"]


@dataclass
class RoadPlane:
    """Per-frame (B,) road planes of :func:`fit_road_plane`.

    Attributes:
        height: (B,) float64 camera height above the plane in the points' unit (NaN where it failed).
        normal: (B,3) float64 unit normal pointing down (towards the road, ``n_y > 0``).
        inliers: (B,N) bool rows on the plane. num_inliers: (B,) long. success: (B,) bool.
    """

    height: torch.Tensor
    normal: torch.Tensor
    inliers: torch.Tensor
    num_inliers: torch.Tensor
    success: torch.Tensor


def road_candidates(pts: torch.Tensor, height: int, width: int, min_row_fraction: float,
                    max_col_offset_fraction: float, max_row_fraction: float) -> torch.Tensor:
    """(B,N) bool: pixels ``pts`` (B,N,2) in the lower image (rows from ``min_row_fraction`` to ``max_row_fraction``
    of ``height - 1``) and within ``max_col_offset_fraction * width`` of the image's centre column (the road ahead,
    not the kerbs)."""
    KORNIA_CHECK_SHAPE(pts, ["B", "N", "2"])
    u, v = pts[..., 0], pts[..., 1]
    return (v >= min_row_fraction * (height - 1)) & (v <= max_row_fraction * (height - 1)) & \
        ((u - 0.5 * (width - 1)).abs() <= max_col_offset_fraction * width)


def road_grid(height: int, width: int, min_row_fraction: float, max_row_fraction: float,
              max_col_offset_fraction: float, step: int) -> torch.Tensor:
    """(M,2) float64 pixels every ``step`` px of the band :func:`road_candidates` accepts."""
    v = torch.arange(math.ceil(min_row_fraction * (height - 1)), math.floor(max_row_fraction * (height - 1)) + 1, step)
    c, half = 0.5 * (width - 1), max_col_offset_fraction * width
    u = torch.arange(max(0, math.ceil(c - half)), min(width - 1, math.floor(c + half)) + 1, step)
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    return torch.stack([uu.flatten(), vv.flatten()], -1).to(torch.float64)


def parallax_deg(X_i: torch.Tensor, t: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """Angle (degrees) between the rays from the two camera centres to points ``X_i`` (B,N,3) in camera i under
    ``T_cur_prev = [R | t]`` (B,3,3), (B,3): camera j's centre in frame i is ``-R^T t``. A small angle means a
    poorly conditioned triangulation."""
    c_j = -(R.transpose(-1, -2) @ t[..., None])[..., 0]  # (B,3)
    a, b = X_i, X_i - c_j[:, None]
    cos = (a * b).sum(-1) / (a.norm(dim=-1) * b.norm(dim=-1)).clamp_min(1e-30)
    return torch.rad2deg(torch.acos(cos.clamp(-1.0, 1.0)))


def _plane_residual_sq(normal: torch.Tensor, d: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    """Squared point-plane distances relative to the height: normal (B,C,3), d (B,C), X (B,N,3) -> (B,C,N)."""
    dist = torch.einsum("bcr,bnr->bcn", normal, X) - d[..., None]
    return (dist / d[..., None]) ** 2


def _least_squares(X: torch.Tensor, w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Total-least-squares plane of the rows ``w`` (B,N) bool of X (B,N,3): normal (B,3) with n_y >= 0, d (B,)."""
    wf = w.to(X.dtype)[..., None]
    X = torch.where(w[..., None], X, 0.0)  # rows outside ``w`` may hold NaN (no depth there): 0 * NaN is NaN
    cnt = wf.sum(1).clamp_min(1.0)
    mean = (X * wf).sum(1) / cnt
    Xc = (X - mean[:, None]) * wf
    cov = Xc.transpose(-1, -2) @ Xc
    _, vecs = torch.linalg.eigh(cov)
    n = vecs[..., 0]  # smallest eigenvalue
    n = torch.where(n[:, 1:2] < 0, -n, n)
    return n, (n * mean).sum(-1)


def fit_road_plane(X: torch.Tensor, rows: torch.Tensor, threshold: float = RoadPlaneConfig.threshold,
                   max_tilt_deg: float = RoadPlaneConfig.max_tilt_deg, min_inliers: int = RoadPlaneConfig.min_inliers,
                   trials: int = RoadPlaneConfig.trials, refinements: int = 3, min_threshold: float = 0.002,
                   quantile: float = RoadPlaneConfig.quantile,
                   generators: list[torch.Generator] | None = None) -> RoadPlane:
    """Robust road plane per frame: random 3-point planes whose normal lies within ``max_tilt_deg`` of the camera's
    down axis (0,1,0) and which lie below the camera (``d > 0``); the one whose ``quantile``-th smallest distance
    (relative to its ``d``, since the points' unit is unknown) is least wins (least-quantile, like LMedS), its
    inliers within 2.5 times that distance (clamped to [min_threshold, threshold]); then ``refinements``
    total-least-squares refits on the inliers, each re-selected within 3 robust standard deviations of the inliers'
    distances (clamped alike). ``num_inliers`` counts the rows within ``threshold`` of the final plane.

    Args:
        X: (B,N,3) points in camera i (any common unit per frame). rows: (B,N) bool candidate rows.
        threshold: largest inlier distance as a fraction of the camera's height above the plane.
        quantile: the fraction of the candidate rows expected on the road, at least (the ranking quantile).
        max_tilt_deg: largest angle between the plane's normal and the camera's y axis.
        min_inliers: a frame fails with fewer inliers (or fewer candidate rows).
        trials: RANSAC hypotheses per frame; generators: one per frame (batched == unbatched).

    Returns:
        :class:`RoadPlane`.
    """
    KORNIA_CHECK_SHAPE(X, ["B", "N", "3"])
    KORNIA_CHECK(rows.shape == X.shape[:2], f"fit_road_plane: rows {tuple(rows.shape)}; expected {tuple(X.shape[:2])}")
    B, N, _ = X.shape
    X = X.to(torch.float64)
    rows = rows & torch.isfinite(X).all(-1)
    nan = torch.full((B,), float("nan"), dtype=torch.float64, device=X.device)
    if N < 3:
        return RoadPlane(nan, torch.zeros(B, 3, dtype=torch.float64), torch.zeros_like(rows),
                         torch.zeros(B, dtype=torch.long), torch.zeros(B, dtype=torch.bool))
    cos_max = math.cos(math.radians(max_tilt_deg))
    idx = sample_rows(rows, trials, 3, generators)  # (B,T,3)
    P = X.gather(1, idx.reshape(B, -1, 1).expand(-1, -1, 3)).reshape(B, trials, 3, 3)
    n = torch.linalg.cross(P[:, :, 1] - P[:, :, 0], P[:, :, 2] - P[:, :, 0], dim=-1)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    n = torch.where(n[..., 1:2] < 0, -n, n)
    d = (n * P[:, :, 0]).sum(-1)
    ok = (n[..., 1] >= cos_max) & (d > 0)
    err = _plane_residual_sq(n, torch.where(ok, d, 1.0), X)
    err = torch.where(ok[..., None], err, torch.full_like(err, float("inf")))
    thr_sq = threshold ** 2
    # least quantile of distances (LMedS-like, no threshold): on exact data the road plane's distances are zero
    # for every road point, while a plane tilted to catch kerbs too would win an inlier count or an MSAC cost
    dist = err.sqrt()  # (B,T,N) relative distances, inf for invalid hypotheses
    dist = torch.where(rows[:, None], dist, torch.full_like(dist, float("inf")))
    k = (quantile * rows.sum(-1).to(torch.float64)).floor().long().clamp(1, N) - 1  # (B,)
    if bool((k == k[0]).all()):  # one selection instead of a sort (the same value)
        score = dist.kthvalue(int(k[0]) + 1, dim=-1).values  # (B,T)
    else:
        score = dist.sort(-1).values.gather(-1, k[:, None, None].expand(B, trials, 1))[..., 0]
    best = score.argmin(-1)
    ar = torch.arange(B, device=X.device)
    n_best, d_best = n[ar, best], d[ar, best]
    found = torch.isfinite(score[ar, best]) & ok[ar, best]
    thr0 = (2.5 * score[ar, best]).nan_to_num(threshold, posinf=threshold).clamp(min(min_threshold, threshold),
                                                                                  threshold)
    inl = rows & (dist[ar, best] < thr0[:, None]) & found[:, None]
    for _ in range(max(0, int(refinements))):
        # threshold from the inliers' own spread (3 robust sigmas, within [min_threshold, threshold]): points just
        # off the road (kerbs, car sills) that RANSAC's threshold let in do not tilt the least-squares plane
        e = _plane_residual_sq(n_best[:, None], torch.where(d_best > 0, d_best, 1.0)[:, None], X)[:, 0].sqrt()
        sigma = MAD_TO_STD * torch.where(inl, e, float("nan")).nanmedian(-1).values
        thr_k = (3.0 * sigma).nan_to_num(threshold).clamp(min(min_threshold, threshold), threshold)
        inl = rows & (e < thr_k[:, None]) & found[:, None]
        n_ls, d_ls = _least_squares(X, inl)
        good = found & (inl.sum(-1) >= 3) & (d_ls > 0)
        n_best = torch.where(good[:, None], n_ls, n_best)
        d_best = torch.where(good, d_ls, d_best)
    e = _plane_residual_sq(n_best[:, None], torch.where(d_best > 0, d_best, 1.0)[:, None], X)[:, 0]
    inl = rows & (e < thr_sq) & found[:, None]
    count = inl.sum(-1)
    success = found & (count >= max(3, int(min_inliers))) & (n_best[:, 1] >= cos_max) & (d_best > 0)
    return RoadPlane(torch.where(success, d_best, nan), n_best, inl & success[:, None], count, success)
