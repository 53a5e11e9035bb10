"""Correlation (cost volume) layer in plain PyTorch: no CUDA or CuPy build, runs wherever PyTorch runs.

Convention:
    - Features are (B,C,H,W). The cost volume compares pixel ``x`` of ``feat1`` with pixel ``x + d`` of
      ``feat2`` for every integer displacement ``d = (dx, dy)`` with ``|dx|, |dy| <= max_displacement``
      (in pixels of the feature map, multiplied by ``stride`` when a dilated search is asked for).
    - Output channel ``k = (dy + R) * (2R + 1) + (dx + R)`` (row-major over (dy, dx), ``R`` the radius),
      value ``mean_c feat1[c, y, x] * feat2[c, y + dy, x + dx]``; positions outside ``feat2`` count as 0.
    - Memory is bounded: one row of displacements (2R+1 shifts) is materialised at a time, i.e. at most
      ``B*C*H*W*(2R+1)`` extra elements, never the full ``(2R+1)^2`` stack of shifted features.
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
    b, c, h, w = feat1.shape
    r = max_displacement
    pad = r * stride
    f2 = F.pad(feat2, (pad, pad, pad, pad))
    rows = []
    for iy in range(2 * r + 1):
        band = f2[:, :, iy * stride: iy * stride + h, :]  # (B,C,H,W+2*pad): all dx for this dy
        # (B,C,H,2R+1,W) view of the horizontal shifts; unfold makes no copy.
        shifts = band.unfold(3, w, 1)[:, :, :, ::stride, :] if stride > 1 else band.unfold(3, w, 1)
        rows.append(torch.einsum("bchw,bchdw->bdhw", feat1, shifts))
    return torch.cat(rows, dim=1) / c
