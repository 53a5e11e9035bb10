"""Photometric error: SSIM + L1, and the per-pixel minimum over source views.

Convention:
    Images (B,3,H,W) in [0,1]; errors are per pixel (B,1,H,W), averaged over the colour channels.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from kornia.core.check import KORNIA_CHECK_SHAPE
from kornia.filters import get_gaussian_kernel1d

INVALID_ERROR = 1e4  # error given to out-of-view pixels before the per-pixel minimum


SSIM_C1, SSIM_C2 = 0.01**2, 0.03**2  # SSIM's stabilising constants for images in [0, 1]


def ssim_map(x: torch.Tensor, y: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Per-pixel, per-channel SSIM (B,C,H,W) of images (B,C,H,W) in [0,1] with a 3x3 Gaussian window (sigma 1.5) and
    reflect padding: ``kornia.metrics.ssim(x, y, 3, padding="same")``'s values (equal to the last bit, tested).

    The five local moments (means, second moments, cross moment) are filtered in one stacked tensor: two padded
    depthwise convolutions instead of kornia's ten, which makes a training step's SSIM (forward and backward)
    about 1.5x faster on a CPU (``benchmarks/train_step.py``). Images need at least 2 rows and columns.
    """
    c = x.shape[1]
    kernel = get_gaussian_kernel1d(3, 1.5, device=x.device, dtype=x.dtype)
    moments = torch.cat([x, y, x * x, y * y, x * y], 1)
    n = moments.shape[1]
    # reflect padding by one pixel as concatenated slices: F.pad's reflect backward is ~2x slower on CPUs
    moments = torch.cat([moments[..., 1:2], moments, moments[..., -2:-1]], -1)
    moments = F.conv2d(moments, kernel.view(1, 1, 1, 3).expand(n, 1, 1, 3), groups=n)
    moments = torch.cat([moments[..., 1:2, :], moments, moments[..., -2:-1, :]], -2)
    moments = F.conv2d(moments, kernel.view(1, 1, 3, 1).expand(n, 1, 3, 1), groups=n)
    mu_x, mu_y, e_xx, e_yy, e_xy = moments.split(c, 1)
    mu_xx, mu_yy, mu_xy = mu_x**2, mu_y**2, mu_x * mu_y
    num = (2.0 * mu_xy + SSIM_C1) * (2.0 * (e_xy - mu_xy) + SSIM_C2)
    den = (mu_xx + mu_yy + SSIM_C1) * ((e_xx - mu_xx) + (e_yy - mu_yy) + SSIM_C2)
    return num / (den + eps)


def ssim_l1_error(target: torch.Tensor, warped: torch.Tensor, alpha: float = 0.85) -> torch.Tensor:
    """Per-pixel ``alpha * (1 - SSIM) / 2 + (1 - alpha) * |I - I'|``.

    Args:
        target: (B,3,H,W) image of the target view.
        warped: (B,3,H,W) source view warped into the target.
        alpha: weight of the SSIM term (0.85 in the paper).

    Returns:
        (B,1,H,W) error, 0 for identical images; SSIM with kornia's 3x3 window (:func:`ssim_map`).
    """
    KORNIA_CHECK_SHAPE(target, ["B", "3", "H", "W"])
    KORNIA_CHECK_SHAPE(warped, ["B", "3", "H", "W"])
    if target.shape != warped.shape:
        raise ValueError(f"ssim_l1_error: target {tuple(target.shape)} and warped {tuple(warped.shape)} differ")
    l1 = (target - warped).abs().mean(1, keepdim=True)
    s = ssim_map(target, warped)
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
