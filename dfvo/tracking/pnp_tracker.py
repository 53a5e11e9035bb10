"""PnP-tracker: 3-D points from the previous frame's CNN depth, PnP-RANSAC + LM in the current image."""

from __future__ import annotations

import torch

from dfvo.geometry.camera import backproject_points
from dfvo.geometry.pnp import solve_pnp_ransac
from dfvo.tracking.config import TrackerConfig
from dfvo.tracking.scale import sample_depth

__all__ = ["track_pnp"]


def track_pnp(pts_i: torch.Tensor, pts_j: torch.Tensor, mask: torch.Tensor, depth_i: torch.Tensor, K: torch.Tensor,
              cfg: TrackerConfig, generators: list[torch.Generator]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``T_cur_prev`` from PnP on (B,N,2) pixel pairs and the previous frame's depth (B,1,H,W).

    Rows are used when selected and their depth lies in (0, ``cfg.scale.max_depth``] below the top
    ``cfg.scale.depth_crop_top``.
    Each frame runs with its own generator (batched == unbatched).

    Returns:
        T_cur_prev (B,4,4) float64 (identity where it failed), success (B,) bool, num_inliers (B,) long.
    """
    z, ok = sample_depth(depth_i, pts_i, cfg.scale.max_depth, cfg.scale.depth_crop_top)
    rows = mask & ok
    X = backproject_points(pts_i.to(torch.float64), torch.where(rows, z, 1.0), K.to(torch.float64))
    r = solve_pnp_ransac(X, pts_j.to(torch.float64), rows, K.to(torch.float64), threshold_px=cfg.pnp.threshold_px,
                         iterations=cfg.pnp.iterations, repeats=cfg.pnp.repeats, min_points=cfg.pnp.min_points,
                         generators=generators)
    return r.T_cur_prev.to(torch.float64), r.success, r.num_inliers
