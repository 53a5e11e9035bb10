"""Forward-backward optical-flow consistency.

Convention:
    ``flow_fwd`` (B,2,H,W) is the flow i->j on the pixels of image i and ``flow_bwd`` (B,2,H,W) the flow j->i
    on the pixels of image j (pixels, channel 0 = u, channel 1 = v; see :mod:`dfvo.matching.flow_warp`).
    For a perfectly consistent pair, following the forward flow and then the backward flow returns to the
    start pixel, so ``F_fwd(x) + F_bwd(x + F_fwd(x)) = 0``.
"""

from __future__ import annotations

import torch
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE

from dfvo.matching.flow_warp import flow_magnitude, warp_by_flow


def forward_backward_inconsistency(flow_fwd: torch.Tensor, flow_bwd: torch.Tensor) -> torch.Tensor:
    """Per-pixel forward-backward inconsistency ``|| F_fwd(x) + F_bwd(x + F_fwd(x)) ||`` in pixels.

    The backward flow is sampled bilinearly at the forward target (``align_corners=True`` convention of
    :func:`dfvo.matching.flow_warp.warp_by_flow`).

    Args:
        flow_fwd: (B,2,H,W) flow i->j on image i.
        flow_bwd: (B,2,H,W) flow j->i on image j.

    Returns:
        (B,1,H,W) inconsistency in pixels on image i's grid; ``+inf`` where the forward target lies outside
        image j (or either flow is not finite there).
    """
    KORNIA_CHECK_SHAPE(flow_fwd, ["B", "2", "H", "W"])
    KORNIA_CHECK_SHAPE(flow_bwd, ["B", "2", "H", "W"])
    KORNIA_CHECK(flow_fwd.shape == flow_bwd.shape,
                 f"forward_backward_inconsistency: flow_fwd {tuple(flow_fwd.shape)} and flow_bwd "
                 f"{tuple(flow_bwd.shape)} must have the same shape")
    bwd_at_target, inside = warp_by_flow(flow_bwd, flow_fwd)
    return inconsistency_at(flow_fwd, bwd_at_target, inside)


def inconsistency_at(flow_fwd: torch.Tensor, bwd_at_target: torch.Tensor, inside: torch.Tensor) -> torch.Tensor:
    """:func:`forward_backward_inconsistency` from a warp already done: ``bwd_at_target`` (B,2,H,W) the backward flow
    sampled at ``x + F_fwd(x)`` and ``inside`` (B,1,H,W) bool, whether that target lies in image j
    (:func:`dfvo.matching.flow_warp.warp_by_flow`). (B,1,H,W) pixels, ``+inf`` outside or where not finite; the
    gradient stays finite at exactly consistent pixels, so losses can use it."""
    diff = flow_magnitude(flow_fwd + bwd_at_target)
    valid = inside & torch.isfinite(diff)
    return torch.where(valid, diff, torch.full_like(diff, float("inf")))
