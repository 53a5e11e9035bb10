"""Optical flow colour coding and scalar maps (inconsistency) as colour images, for TensorBoard and Rerun.

Convention:
    Flow (B,2,H,W) in pixels. The colour wheel follows the usual Middlebury-style coding: hue = direction
    (angle of (u, v), 0 = pointing right = red, turning towards +v), saturation = magnitude / max_magnitude
    (clipped to 1), value = 1; so zero flow is white. Outputs are (B,3,H,W) float in [0,1].
"""

from __future__ import annotations

import math

import torch
from kornia.color import hsv_to_rgb
from kornia.core.check import KORNIA_CHECK_SHAPE


def flow_to_color(flow: torch.Tensor, max_magnitude: float | None = None) -> torch.Tensor:
    """Colour-code a flow field.

    Args:
        flow: (B,2,H,W) flow in pixels.
        max_magnitude: magnitude shown fully saturated; default the per-image maximum (at least 1e-6).

    Returns:
        (B,3,H,W) RGB in [0,1].
    """
    KORNIA_CHECK_SHAPE(flow, ["B", "2", "H", "W"])
    flow = torch.nan_to_num(flow.detach().float(), nan=0.0, posinf=0.0, neginf=0.0)
    u, v = flow[:, 0], flow[:, 1]
    mag = torch.sqrt(u * u + v * v)
    if max_magnitude is None:
        scale = mag.flatten(1).amax(1).clamp(min=1e-6).view(-1, 1, 1)
    else:
        scale = torch.full_like(mag[:, :1, :1], float(max_magnitude))
    hue = torch.remainder(torch.atan2(v, u), 2 * math.pi)
    sat = (mag / scale).clamp(0.0, 1.0)
    hsv = torch.stack([hue, sat, torch.ones_like(sat)], dim=1)
    return hsv_to_rgb(hsv).clamp(0.0, 1.0)


def scalar_to_color(x: torch.Tensor, vmax: float | None = None) -> torch.Tensor:
    """Map a (B,1,H,W) non-negative map (e.g. fb inconsistency in pixels; +inf allowed) to a heat image.

    Black (0) → red → yellow → white (>= vmax); non-finite values (outside the image) are shown blue.

    Returns:
        (B,3,H,W) RGB in [0,1].
    """
    KORNIA_CHECK_SHAPE(x, ["B", "1", "H", "W"])
    x = x.detach().float()
    finite = torch.isfinite(x)
    xf = torch.where(finite, x, torch.zeros_like(x))
    if vmax is None:
        vmax_t = xf.flatten(1).amax(1).clamp(min=1e-6).view(-1, 1, 1, 1)
    else:
        vmax_t = torch.full_like(xf[:, :, :1, :1], float(vmax))
    t = (xf / vmax_t).clamp(0.0, 1.0)
    rgb = torch.cat([(3 * t).clamp(0, 1), (3 * t - 1).clamp(0, 1), (3 * t - 2).clamp(0, 1)], dim=1)
    blue = torch.tensor([0.0, 0.0, 1.0], device=x.device).view(1, 3, 1, 1).expand_as(rgb)
    return torch.where(finite.expand_as(rgb), rgb, blue)
