"""Image operations of the photometric flow refinements (:mod:`dfvo.matching.flow_refinement`, dense, and
:mod:`dfvo.matching.pyramid_refinement`, sparse): one copy of each, shared by both.

Convention:
    Images (N,3,H,W) RGB or (N,1,H,W) grey, float in [0,1]; every output is float32 on the input's device (the
    refinements run in float32). Gradients are per pixel, borders replicated.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from kornia.color import rgb_to_grayscale
from kornia.filters import gaussian_blur2d

__all__ = ["grey", "smooth", "gradient", "box_mean", "window_structure_tensor", "smaller_eigenvalue", "shi_tomasi"]


def grey(images: torch.Tensor) -> torch.Tensor:
    """(N,1,H,W) float32 grey of (N,3,H,W) (kornia's ``rgb_to_grayscale``: ITU-R 601 weights) or (N,1,H,W)
    images."""
    images = images.to(torch.float32)
    return rgb_to_grayscale(images) if images.shape[1] == 3 else images


def smooth(image: torch.Tensor, sigma: float) -> torch.Tensor:
    """Gaussian blur of (N,C,H,W) with standard deviation ``sigma`` pixels (kernel ``2 round(3 sigma) + 1``,
    separable, replicated border); ``sigma <= 0``: the image itself."""
    if sigma > 0:
        k = 2 * int(round(3 * sigma)) + 1
        image = gaussian_blur2d(image, (k, k), (sigma, sigma), border_type="replicate", separable=True)
    return image


def gradient(image: torch.Tensor) -> torch.Tensor:
    """Central differences (d/du, d/dv) of (N,1,H,W) with replicated borders -> (N,2,H,W).

    The same numbers as ``kornia.filters.spatial_gradient(mode="diff")``, without its 3x3 convolution (much slower
    on a CPU: docs/geometry.md, "kornia equivalents")."""
    p = F.pad(image, (1, 1, 1, 1), mode="replicate")
    return torch.cat([0.5 * (p[..., 1:-1, 2:] - p[..., 1:-1, :-2]), 0.5 * (p[..., 2:, 1:-1] - p[..., :-2, 1:-1])], 1)


def box_mean(x: torch.Tensor, window: int) -> torch.Tensor:
    """Mean over a ``window`` x ``window`` neighbourhood (replicate border): (N,C,H,W) float32 -> same.

    Running sums (``cumsum``) along each axis: O(1) per pixel whatever the window, several times faster on a CPU
    than pooling or depthwise convolutions. Each row (then column) has its mean removed before its running sum and
    added back after, so the sums stay small (a random walk, not a ramp) and float32 keeps them exact to ~1e-6
    of the values' spread even for flows of hundreds of pixels (plain running sums lose precision along the row).
    """
    r = window // 2
    x = F.pad(x, (r + 1, r, r + 1, r), mode="replicate")
    mean = x.mean(-1, keepdim=True)
    c = (x - mean).cumsum(-1)
    x = (c[..., window:] - c[..., :-window]) / window + mean
    mean = x.mean(-2, keepdim=True)
    c = (x - mean).cumsum(-2)
    return (c[..., window:, :] - c[..., :-window, :]) / window + mean


def window_structure_tensor(gx: torch.Tensor, gy: torch.Tensor, window: int) -> tuple[torch.Tensor, ...]:
    """Entries (xx, xy, yy) of the ``window`` x ``window`` mean structure tensor of (N,1,H,W) gradients, each
    (N,1,H,W) float32."""
    return box_mean(torch.cat([gx * gx, gx * gy, gy * gy], 1), window).split(1, 1)


def smaller_eigenvalue(sxx: torch.Tensor, sxy: torch.Tensor, syy: torch.Tensor) -> torch.Tensor:
    """Smaller eigenvalue of the symmetric 2x2 matrices ``[[sxx, sxy], [sxy, syy]]`` (same-shaped tensors)."""
    return 0.5 * (sxx + syy) - torch.sqrt((0.5 * (sxx - syy)) ** 2 + sxy * sxy)


def shi_tomasi(images: torch.Tensor, window: int, sigma: float) -> torch.Tensor:
    """Shi–Tomasi score of every pixel: the smaller eigenvalue of the ``window`` x ``window`` mean structure tensor
    of the grey image smoothed by ``sigma`` pixels (intensities in [0,1], gradients per pixel), the quantity the
    refinements test against their ``min_eigenvalue``. (N,3|1,H,W) -> (N,1,H,W) float32."""
    gx, gy = gradient(smooth(grey(images), sigma)).split(1, 1)
    return smaller_eigenvalue(*window_structure_tensor(gx, gy, window))
