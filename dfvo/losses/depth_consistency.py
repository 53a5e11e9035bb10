"""Inverse depth consistency between views (the paper's λ_dc term of the ``depth_mono_sc`` model).

For a target pixel x with depth D_i(x), its 3-D point seen from view j has depth z_j(x) (computed by the
pose); the network's depth of view j at the projection is D_j(π(x)) (bilinearly sampled, "D_j→i").
A scale-consistent pair of depth maps has ``1/z_j(x) = 1/D_j(π(x))``. The error is their absolute
difference, with a per-pixel minimum over the source views (occlusions show up in only one of them).
"""

from __future__ import annotations

import torch
from kornia.core.check import KORNIA_CHECK_SHAPE

from dfvo.losses.photometric import min_over_views


def inverse_depth_difference(depth_in_source: torch.Tensor, sampled_source_depth: torch.Tensor) -> torch.Tensor:
    """``|1/z_j - 1/D_j→i|`` per pixel.

    Args:
        depth_in_source: (B,1,H,W) depth z_j of the target's 3-D points in the source camera.
        sampled_source_depth: (B,1,H,W) the source view's predicted depth sampled at the projections.

    Returns:
        (B,1,H,W) absolute inverse-depth difference (0 where the two agree).
    """
    KORNIA_CHECK_SHAPE(depth_in_source, ["B", "1", "H", "W"])
    KORNIA_CHECK_SHAPE(sampled_source_depth, ["B", "1", "H", "W"])
    return (1.0 / depth_in_source.clamp_min(1e-3) - 1.0 / sampled_source_depth.clamp_min(1e-3)).abs()


def depth_consistency_loss(differences: list[torch.Tensor], valids: list[torch.Tensor | None]) -> torch.Tensor:
    """Mean over pixels of the per-pixel minimum (over views) of inverse-depth differences.

    Args:
        differences: per-view (B,1,H,W) maps from :func:`inverse_depth_difference`.
        valids: per-view (B,1,H,W) bool masks (None = everywhere valid).

    Returns:
        scalar tensor (0 if no pixel is valid in any view).
    """
    best, mask = min_over_views(differences, valids)
    return (best * mask).sum() / mask.sum().clamp_min(1)
