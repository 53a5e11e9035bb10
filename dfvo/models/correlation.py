"""Correlation (cost volume) layer in plain PyTorch: no CUDA or CuPy build, runs wherever PyTorch runs.

Convention:
    - Features are (B,C,H,W). The cost volume compares pixel ``x`` of ``feat1`` with pixel ``x + d`` of
      ``feat2`` for every integer displacement ``d = (dx, dy)`` with ``|dx|, |dy| <= max_displacement``
      (in pixels of the feature map, multiplied by ``stride`` when a dilated search is asked for).
    - Output channel ``k = (dy + R) * (2R + 1) + (dx + R)`` (row-major over (dy, dx), ``R`` the radius),
      value ``mean_c feat1[c, y, x] * feat2[c, y + dy, x + dx]``; positions outside ``feat2`` count as 0.
    - Memory is bounded: one displacement's product is materialised at a time (``B*C*H*W`` extra elements), never
      the ``(2R+1)^2`` stack of shifted features. (A multiply and a channel sum per displacement: on a CPU faster than
      an einsum per row of displacements, whose batched matrix products are tiny.)
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE


def correlation(feat1: torch.Tensor, feat2: torch.Tensor, max_displacement: int, stride: int = 1) -> torch.Tensor:
    """Local cost volume between two feature maps.

    Args:
        feat1: (B,C,H,W) features of the reference image.
        feat2: (B,C,H,W) features of the other image (usually already warped by the current flow).
        max_displacement: search radius ``R`` in displacement steps (>= 0).
        stride: pixels between two displacement steps (1 = dense search, 2 = every other pixel, ...).

    Returns:
        (B,(2R+1)^2,H,W) channel-averaged dot products, ordered as in the module docstring.
    """
    KORNIA_CHECK_SHAPE(feat1, ["B", "C", "H", "W"])
    KORNIA_CHECK_SHAPE(feat2, ["B", "C", "H", "W"])
    KORNIA_CHECK(feat1.shape == feat2.shape,
                 f"correlation: feat1 {tuple(feat1.shape)} and feat2 {tuple(feat2.shape)} must have the same shape")
    KORNIA_CHECK(max_displacement >= 0 and stride >= 1,
                 f"correlation: need max_displacement >= 0 and stride >= 1, got {max_displacement}, {stride}")
    c, h, w = feat1.shape[1:]
    r = max_displacement
    pad = r * stride
    f2 = F.pad(feat2, (pad, pad, pad, pad))
    costs = []  # one displacement at a time: B*C*H*W extra elements at most (autograd-friendly: no out=)
    for iy in range(2 * r + 1):
        for ix in range(2 * r + 1):
            costs.append((feat1 * f2[:, :, iy * stride: iy * stride + h, ix * stride: ix * stride + w]).sum(1))
    return torch.stack(costs, 1) / c
