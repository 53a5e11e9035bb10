"""Model selection between the E-tracker and the PnP-tracker: GRIC (E vs H) or flow magnitude."""

from __future__ import annotations

import torch
from kornia.core.check import KORNIA_CHECK_SHAPE

__all__ = ["prefer_pnp_gric", "prefer_pnp_flow"]


def prefer_pnp_gric(gric_e: torch.Tensor, gric_h: torch.Tensor) -> torch.Tensor:
    """(B,) bool: the homography explains the pair better (``GRIC_E > GRIC_H``: rotation-only, planar or
    standing-still pairs), so E is unreliable and PnP should be used."""
    return gric_e > gric_h


def prefer_pnp_flow(pts_i: torch.Tensor, pts_j: torch.Tensor, mask: torch.Tensor, threshold_px: float) -> torch.Tensor:
    """(B,) bool: the median flow magnitude of the selected rows is at most ``threshold_px`` pixels (too little
    parallax for E), the paper's cheap alternative to GRIC."""
    KORNIA_CHECK_SHAPE(pts_i, ["B", "N", "2"])
    mag = (pts_j - pts_i).norm(dim=-1)
    out = []
    for b in range(mag.shape[0]):
        vals = mag[b][mask[b]]
        out.append(bool(vals.numel() == 0 or float(vals.median()) <= threshold_px))
    return torch.tensor(out, dtype=torch.bool, device=pts_i.device)
