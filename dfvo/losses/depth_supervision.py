"""Supervised depth loss on samples with true depth (the synthetic world): scale-aware log-depth L1.

The photometric losses teach metric depth only through the stereo baseline, whose disparity vanishes with range
(at 320x96 a point 40 m away shifts 2.5 px between the KITTI cameras), so far depth gets little signal; the synthetic
world's exact depth gives it directly. ``|log D - log D*|`` weighs a relative error alike at every range (a 10 % error
costs ~0.1 at 5 m and at 60 m), and is *not* scale invariant: a global scale error is penalised, which is the point.

Convention:
    Depth maps (B,1,H,W) in metres; a target depth of 0 (or below) marks a pixel without ground truth (e.g. a real
    sample padded into a mixed KITTI + synthetic batch); targets beyond ``max_depth`` (the synthetic sky is at
    ``SKY_DEPTH`` = 1000 m) are clamped to ``max_depth``, the farthest depth the network can output, so sky is taught
    as "as far as possible".
"""

from __future__ import annotations

import torch
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE

__all__ = ["log_depth_l1"]


def log_depth_l1(pred: torch.Tensor, target: torch.Tensor, max_depth: float,
                 valid: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean over pixels with ground truth of ``|log pred - log min(target, max_depth)|``.

    Args:
        pred: (B,1,H,W) predicted depth, positive (metres).
        target: (B,1,H,W) true depth (metres); ``<= 0`` where there is none.
        max_depth: the network's largest depth; targets beyond it are clamped to it (> 0).
        valid: optional (B,1,H,W) bool mask, combined with ``target > 0``.

    Returns:
        ``(loss, count)``: the scalar loss (0 when no pixel has ground truth; it still carries ``pred``'s graph) and
        the number of pixels it averages (a scalar tensor).
    """
    KORNIA_CHECK_SHAPE(pred, ["B", "1", "H", "W"])
    KORNIA_CHECK(target.shape == pred.shape, f"log_depth_l1: target {tuple(target.shape)} must have pred's shape "
                                             f"{tuple(pred.shape)}")
    KORNIA_CHECK(max_depth > 0, f"log_depth_l1: max_depth={max_depth}; expected > 0")
    mask = target > 0
    if valid is not None:
        KORNIA_CHECK(valid.shape == pred.shape, f"log_depth_l1: valid {tuple(valid.shape)} must have pred's shape")
        mask = mask & valid.bool()
    goal = target.clamp(min=1e-6, max=max_depth)
    err = (pred.clamp_min(1e-6).log() - goal.log()).abs()
    count = mask.sum()
    loss = torch.where(mask, err, torch.zeros_like(err)).sum() / count.clamp_min(1)
    return loss, count
