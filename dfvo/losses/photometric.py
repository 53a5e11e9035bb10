"""Photometric error: SSIM + L1, and the per-pixel minimum over source views.

Convention:
    Images (B,3,H,W) in [0,1]; errors are per pixel (B,1,H,W), averaged over the colour channels.
"""

from __future__ import annotations

import torch
from kornia.core.check import KORNIA_CHECK_SHAPE
from kornia.metrics import ssim

INVALID_ERROR = 1e4  # error given to out-of-view pixels before the per-pixel minimum


def ssim_l1_error(target: torch.Tensor, warped: torch.Tensor, alpha: float = 0.85) -> torch.Tensor:
    """Per-pixel ``alpha * (1 - SSIM) / 2 + (1 - alpha) * |I - I'|``.

    Args:
        target: (B,3,H,W) image of the target view.
        warped: (B,3,H,W) source view warped into the target.
        alpha: weight of the SSIM term (0.85 in the paper).

    Returns:
        (B,1,H,W) error, 0 for identical images; SSIM with kornia's 3x3 window.
    """
    KORNIA_CHECK_SHAPE(target, ["B", "3", "H", "W"])
    KORNIA_CHECK_SHAPE(warped, ["B", "3", "H", "W"])
    if target.shape != warped.shape:
        raise ValueError(f"ssim_l1_error: target {tuple(target.shape)} and warped {tuple(warped.shape)} differ")
    l1 = (target - warped).abs().mean(1, keepdim=True)
    s = ssim(target, warped, window_size=3, max_val=1.0, padding="same")
    dssim = ((1.0 - s) / 2.0).clamp(0.0, 1.0).mean(1, keepdim=True)
    return alpha * dssim + (1.0 - alpha) * l1


def min_over_views(errors: list[torch.Tensor], valids: list[torch.Tensor | None]) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel minimum of several (B,1,H,W) error maps, ignoring views where a pixel is out of view.

    Args:
        errors: per-view errors (B,1,H,W).
        valids: per-view (B,1,H,W) bool masks (None = valid everywhere).

    Returns:
        min_error (B,1,H,W) (0 where no view is valid) and mask (B,1,H,W) bool: at least one view valid.
    """
    if not errors or len(errors) != len(valids):
        raise ValueError(f"min_over_views: expected as many masks as errors (>0), got {len(errors)}, {len(valids)}")
    stacked = []
    any_valid = torch.zeros_like(errors[0], dtype=torch.bool)
    for err, valid in zip(errors, valids):
        KORNIA_CHECK_SHAPE(err, ["B", "1", "H", "W"])
        if valid is None:
            valid = torch.ones_like(err, dtype=torch.bool)
        stacked.append(torch.where(valid, err, torch.full_like(err, INVALID_ERROR)))
        any_valid = any_valid | valid
    best = torch.cat(stacked, 1).min(1, keepdim=True).values
    return torch.where(any_valid, best, torch.zeros_like(best)), any_valid
