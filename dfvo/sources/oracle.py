"""Oracle sources: the exact flow and depth of the synthetic world (to separate learning from geometry errors).

Convention:
    Frames are identified by their index in the :class:`~dfvo.synthetic.SyntheticWorld`; the images passed
    in are only used to check shapes (the answer comes from the world's ground truth, not from pixels).
    Flow (B,2,H,W) in pixels (``flow_i->j(x)`` = position in j minus x), depth (B,1,H,W) in metres (sky =
    ``SKY_DEPTH``, which the tracker's depth range removes).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import torch
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE

if TYPE_CHECKING:
    from dfvo.synthetic import SyntheticWorld

__all__ = ["OracleFlow", "OracleDepth"]


def _require_world(world: SyntheticWorld | None, what: str) -> None:
    if world is None:
        raise ValueError(f"{what}: the oracle source needs ground truth, which only data=synthetic provides "
                         f"(choose {what.split('=')[0]}=network for this dataset)")


def _check_indices(world: SyntheticWorld | None, indices: Sequence[int] | None, batch: int, what: str) -> list[int]:
    if indices is None or len(indices) != batch:
        raise ValueError(f"{what}: expected one frame index per image ({batch}), got {indices}")
    return [int(i) for i in indices]


class OracleFlow:
    """True forward/backward flow between consecutive synthetic frames.

    Args:
        world: the synthetic world the frames come from (None: ValueError, the data has no ground truth).
    """

    name = "oracle"

    def __init__(self, world: SyntheticWorld | None) -> None:
        _require_world(world, "flow=oracle")
        self.world = world

    def __call__(self, images_prev: torch.Tensor, images_cur: torch.Tensor,
                 indices: Sequence[int] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Flow prev→cur and cur→prev.

        Args:
            images_prev: (B,3,H,W) frames t-1 (shape check only).
            images_cur: (B,3,H,W) frames t.
            indices: the B world indices of frames t-1 (frame t is index + 1).

        Returns:
            ``(flow_fwd, flow_bwd)``, each (B,2,H,W): prev→cur on prev's pixels, cur→prev on cur's pixels.
        """
        KORNIA_CHECK_SHAPE(images_prev, ["B", "3", "H", "W"])
        KORNIA_CHECK(images_prev.shape == images_cur.shape, "OracleFlow: images_prev and images_cur differ in shape")
        idx = _check_indices(self.world, indices, images_prev.shape[0], "flow=oracle")
        fwd = torch.stack([self.world.flow(i, i + 1)[0] for i in idx])
        bwd = torch.stack([self.world.flow(i + 1, i)[0] for i in idx])
        KORNIA_CHECK(fwd.shape[-2:] == images_prev.shape[-2:],
                     f"flow=oracle: world renders {tuple(fwd.shape[-2:])}, images are {tuple(images_prev.shape[-2:])}")
        return fwd.to(images_prev.device), bwd.to(images_prev.device)


class OracleDepth:
    """True depth of synthetic frames.

    Args:
        world: the synthetic world the frames come from.
    """

    name = "oracle"

    def __init__(self, world: SyntheticWorld | None) -> None:
        _require_world(world, "depth=oracle")
        self.world = world

    def __call__(self, images: torch.Tensor, indices: Sequence[int] | None = None) -> torch.Tensor:
        """Depth (B,1,H,W) in metres of the frames ``indices`` (images (B,3,H,W) for the shape check)."""
        KORNIA_CHECK_SHAPE(images, ["B", "3", "H", "W"])
        idx = _check_indices(self.world, indices, images.shape[0], "depth=oracle")
        depth = torch.stack([self.world.depth(i) for i in idx])
        KORNIA_CHECK(depth.shape[-2:] == images.shape[-2:],
                     f"depth=oracle: world renders {tuple(depth.shape[-2:])}, images are {tuple(images.shape[-2:])}")
        return depth.to(images.device)
