"""What a flow source and a depth source are: the two interfaces the inference loop calls.

Convention:
    Images (B,3,H,W) float in [0,1] at the working size. Flow (B,2,H,W) in pixels: ``flow_fwd`` prev→cur on prev's
    pixels, ``flow_bwd`` cur→prev on cur's pixels. Depth (B,1,H,W) in metres. ``indices`` are the frames' indices
    in their sequence (B of them: the earlier frame of each pair for flow); only sources that read ground truth
    (the oracle) need them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol, runtime_checkable

import torch

__all__ = ["FlowSource", "DepthSource"]


@runtime_checkable
class FlowSource(Protocol):
    """Gives forward and backward flow of B frame pairs in one call; ``name`` says which source it is."""

    name: str

    def __call__(self, images_prev: torch.Tensor, images_cur: torch.Tensor,
                 indices: Sequence[int] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``(flow_fwd, flow_bwd)``, each (B,2,H,W), for images (B,3,H,W) prev and cur."""
        ...


@runtime_checkable
class DepthSource(Protocol):
    """Gives the depth of B frames in one call; ``name`` says which source it is."""

    name: str

    def __call__(self, images: torch.Tensor, indices: Sequence[int] | None = None) -> torch.Tensor:
        """Depth (B,1,H,W) in metres of images (B,3,H,W)."""
        ...
