"""Scale recovery of the essential-matrix translation from CNN depth.

Convention:
    ``R, t`` (B,3,3), (B,3) are ``T_cur_prev`` up to scale (unit ``t``) from the E-tracker; pixels ``pts_i``
    (B,N,2) belong to the previous image i, whose depth (B,1,H,W) the CNN gives in metres. The recovered
    scale ``s`` makes ``[R | s t]`` metric. Only depths in (0, max_depth] and rows below the top
    ``crop_top`` fraction of the image are used.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE

from dfvo.geometry.ransac import frame_rand
from dfvo.geometry.two_view import normalise_points, ray_depths
from dfvo.tracking.config import ScaleConfig

__all__ = ["has_depth", "sample_depth", "triangulated_depth", "triangulated_depths", "simple_scale",
           "iterative_scale"]


def has_depth(depth: torch.Tensor | None) -> bool:
    """Whether a depth map (1,1,H,W) holds any depth: a frame without depth (``depth.every``,
    :mod:`dfvo.sources.every_kth`) has a map of NaN; None has none either."""
    return depth is not None and bool(torch.isfinite(depth).any())


def sample_depth(depth: torch.Tensor, pts: torch.Tensor, max_depth: float = ScaleConfig.max_depth,
                 crop_top: float = ScaleConfig.depth_crop_top) -> tuple[torch.Tensor, torch.Tensor]:
    """Depth (B,1,H,W) at (B,N,2) pixels (nearest pixel) -> values (B,N) float64 and usable (B,N) bool."""
    KORNIA_CHECK_SHAPE(depth, ["B", "1", "H", "W"])
    KORNIA_CHECK_SHAPE(pts, ["B", "N", "2"])
    KORNIA_CHECK(depth.shape[0] == pts.shape[0], f"sample_depth: depth {tuple(depth.shape)} and pts "
                                                 f"{tuple(pts.shape)} must share B")
    B, _, H, W = depth.shape
    u = pts[..., 0].round().long()
    v = pts[..., 1].round().long()
    inside = (u >= 0) & (u < W) & (v >= int(crop_top * H)) & (v < H)
    idx = (v.clamp(0, H - 1) * W + u.clamp(0, W - 1))
    z = depth.reshape(B, H * W).gather(1, idx).to(torch.float64)
    return z, inside & (z > 0) & (z <= max_depth) & torch.isfinite(z)


def triangulated_depths(R: torch.Tensor, t: torch.Tensor, K: torch.Tensor, pts_i: torch.Tensor,
                        pts_j: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Depths in camera i and in camera j (B,N each, float64) of pixel pairs triangulated with
    ``T_cur_prev = [R | t]`` (unit t; both depths scale with the length of t), and (B,N) bool "in front of both
    cameras"."""
    Kd = K.to(torch.float64)
    xi, xj = normalise_points(pts_i.to(torch.float64), Kd), normalise_points(pts_j.to(torch.float64), Kd)
    z_i, z_j = ray_depths(R.to(torch.float64)[:, None], t.to(torch.float64)[:, None], xi, xj)
    return z_i[:, 0], z_j[:, 0], (z_i[:, 0] > 0) & (z_j[:, 0] > 0)


def triangulated_depth(R: torch.Tensor, t: torch.Tensor, K: torch.Tensor, pts_i: torch.Tensor,
                       pts_j: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Depth in camera i (B,N) of pixel pairs triangulated with ``T_cur_prev = [R | t]`` (unit t), and (B,N) bool
    "in front of both cameras"."""
    z_i, _, front = triangulated_depths(R, t, K, pts_i, pts_j)
    return z_i, front


def simple_scale(z_cnn: torch.Tensor, z_tri: torch.Tensor, mask: torch.Tensor,
                 trials: int = ScaleConfig.ransac_trials, samples: int = ScaleConfig.ransac_samples,
                 threshold: float = ScaleConfig.inlier_threshold, min_points: int = ScaleConfig.min_points,
                 generators: list[torch.Generator] | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One scale per frame by 1-D RANSAC on ratios ``z_cnn / z_tri``.

    Each trial averages ``samples`` random ratios; rows within ``threshold`` of it are its inliers; the trial
    with most inliers wins (ties: lowest absolute residual sum) and the scale is the mean of its inlier ratios.

    Args:
        z_cnn: (B,N) network depth at pixels of image i. z_tri: (B,N) triangulated depth (unit translation).
        mask: (B,N) bool usable rows (both depths positive, inside the depth crop).
        min_points: a frame needs more than this many usable rows.

    Returns:
        scale (B,) float64, inliers (B,N) bool, success (B,) bool.
    """
    KORNIA_CHECK_SHAPE(z_cnn, ["B", "N"])
    KORNIA_CHECK(z_tri.shape == z_cnn.shape and mask.shape == z_cnn.shape,
                 f"simple_scale: z_cnn {tuple(z_cnn.shape)}, z_tri {tuple(z_tri.shape)}, mask {tuple(mask.shape)}")
    B, N = z_cnn.shape
    m = mask & (z_tri > 0) & (z_cnn > 0)
    ratio = torch.where(m, z_cnn.to(torch.float64) / z_tri.to(torch.float64).clamp_min(1e-12),
                        torch.zeros((), dtype=torch.float64, device=z_cnn.device))
    n = m.sum(-1)
    success = n > min_points
    if N == 0:
        return torch.zeros(B, dtype=torch.float64), m, success
    u = frame_rand(generators, B, (trials, N), z_cnn.device)
    u = torch.where(m[:, None], u, torch.full_like(u, -1.0))
    idx = u.topk(min(samples, N), dim=-1).indices  # (B,T,s)
    hyp = ratio[:, None].expand(-1, trials, -1).gather(2, idx).mean(-1)  # (B,T)
    res = (ratio[:, None] - hyp[..., None]).abs()
    inl = m[:, None] & (res < threshold)
    key = inl.sum(-1).to(torch.float64) - torch.where(inl, res, 0.0).sum(-1) / (threshold * (N + 1))
    best = key.argmax(-1)
    inliers = inl[torch.arange(B), best]
    cnt = inliers.sum(-1)
    scale = torch.where(inliers, ratio, 0.0).sum(-1) / cnt.clamp_min(1)
    return scale, inliers, success & (cnt > 0)


def iterative_scale(pts_i: torch.Tensor, pts_j: torch.Tensor, mask: torch.Tensor, z_cnn: torch.Tensor,
                    z_valid: torch.Tensor, K: torch.Tensor, R: torch.Tensor, t: torch.Tensor, init_scale: float,
                    estimate: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor, torch.Tensor,
                                                             torch.Tensor]],
                    max_iters: int = ScaleConfig.iterative_max_iters, tol: float = ScaleConfig.iterative_tol,
                    flow_threshold_px: float = ScaleConfig.iterative_flow_threshold_px,
                    ) -> tuple[float, torch.Tensor, torch.Tensor, bool, int]:
    """Paper Algorithm 2 for one frame (B=1): alternate rigid-flow re-selection and pose + scale estimation.

    From the current ``[R | s t]`` and the CNN depth, the rigid flow of each selected pixel is compared with
    its optical flow (``pts_j - pts_i``); rows within ``flow_threshold_px`` are re-selected and ``estimate``
    re-fits pose and scale ON THOSE ROWS ONLY (unlike the official code, whose re-selection never reached the
    scale). Stops after ``max_iters`` or when the scale changes by less than ``tol``.

    Args:
        pts_i, pts_j: (1,N,2) pixels. mask: (1,N) selected rows. z_cnn, z_valid: (1,N) CNN depth at pts_i.
        K: (1,3,3). R, t: (1,3,3), (1,3) initial ``T_cur_prev`` with unit t. init_scale: previous frame's scale.
        estimate: ``estimate(rows (1,N) bool) -> (R, t, scale (1,), success (1,))``.

    Returns:
        scale, R, t, success, iterations run.
    """
    KORNIA_CHECK(pts_i.shape[0] == 1, f"iterative_scale runs one frame at a time; got B={pts_i.shape[0]}")
    Kd = K.to(torch.float64)
    s, ok, it = float(init_scale), False, 0
    ray = torch.cat([normalise_points(pts_i.to(torch.float64), Kd), torch.ones_like(pts_i[..., :1],
                                                                                  dtype=torch.float64)], -1)
    X = ray * z_cnn[..., None]  # (1,N,3) in frame i
    flow = (pts_j - pts_i).to(torch.float64)
    for it in range(1, max_iters + 1):  # noqa: B007
        Xj = X @ R.transpose(-1, -2) + s * t[:, None]
        proj = Xj @ Kd.transpose(-1, -2)
        uv = proj[..., :2] / proj[..., 2:].clamp_min(1e-9)
        diff = (uv - pts_i.to(torch.float64) - flow).norm(dim=-1)
        rows = mask & z_valid & (proj[..., 2] > 0) & (diff < flow_threshold_px)
        R_new, t_new, s_new, good = estimate(rows)
        if not bool(good[0]):
            break
        R, t, ok = R_new, t_new, True
        change = abs(float(s_new[0]) - s)
        s = float(s_new[0])
        if change < tol:
            break
    return s, R, t, ok, it
