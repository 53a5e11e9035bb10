"""Depth on every k-th frame only (``depth.every``): the depth network's cost divided by k.

The frames whose index (in the sequence as read, after ``data.step``) is a multiple of ``every`` get the wrapped
source's depth; the others get a map of NaN, which the tracker reads as "no depth for this frame"
(:func:`dfvo.tracking.scale.has_depth`): with the two-view scale (``tracker.scale.depth_views=2``) each pair of a
run with ``every=2`` still has one frame with depth, and the tracker takes its scale, road plane and PnP points from
that frame (``docs/speed.md``, measurements).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from kornia.core.check import KORNIA_CHECK_SHAPE

from dfvo.sources.base import DepthSource

__all__ = ["EveryKthDepth"]


class EveryKthDepth:
    """``source``'s depth on the frames whose index is a multiple of ``every``; NaN maps on the others.

    Args:
        source: the depth source that runs (network, oracle).
        every: k >= 2.
    """

    def __init__(self, source: DepthSource, every: int) -> None:
        if int(every) < 2:
            raise ValueError(f"EveryKthDepth: every={every}; expected >= 2 (1: use the source itself)")
        self.source, self.every = source, int(every)
        self.name = source.name

    def __getattr__(self, item: str) -> object:  # checkpoint, runtime, ...: the wrapped source's
        if item == "source":
            raise AttributeError(item)
        return getattr(self.source, item)

    def __call__(self, images: torch.Tensor, indices: Sequence[int] | None = None) -> torch.Tensor:
        """Depth (B,1,H,W) in metres of images (B,3,H,W) whose frame indices are ``indices`` (required); NaN on the
        frames without depth."""
        KORNIA_CHECK_SHAPE(images, ["B", "C", "H", "W"])
        if indices is None or len(indices) != images.shape[0]:
            raise ValueError(f"depth.every={self.every} needs each image's frame index; got {indices!r} for "
                             f"{images.shape[0]} images")
        keep = [k for k, i in enumerate(indices) if int(i) % self.every == 0]
        B, _, H, W = images.shape
        out = torch.full((B, 1, H, W), float("nan"), dtype=torch.float32, device=images.device)
        if keep:
            depth = self.source(images[keep], [int(indices[k]) for k in keep])
            out = out.to(depth.dtype)
            out[keep] = depth
        return out
