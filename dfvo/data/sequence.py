"""One sequence of frames behind one small interface: what the inference loop reads from every dataset reader.

Convention:
    ``FrameSequence.image(i)`` is (3,H,W) float in [0,1] at the working resolution, ``K`` (3,3) in its pixels,
    ``poses`` (N,4,4) float64 ``T_w_c`` of the camera when ground truth exists (else None; NaN rows for frames without
    a ground-truth pose), ``world`` the :class:`~dfvo.synthetic.SyntheticWorld` for synthetic data (oracle
    sources need it), ``timestamps`` (N,) float64 seconds of each frame when the dataset has them (else None),
    ``frame_ids`` (N,) the frames' indices in the dataset's own list when a range or step selected them (else None).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

__all__ = ["FrameSequence"]


@dataclass
class FrameSequence:
    """One sequence ready for inference (see module docstring)."""

    name: str
    length: int
    K: torch.Tensor
    load: Callable[[int], torch.Tensor]
    poses: np.ndarray | None = None
    world: Any = None
    timestamps: np.ndarray | None = None
    frame_ids: np.ndarray | None = field(default=None, repr=False)

    def image(self, index: int) -> torch.Tensor:
        """(3,H,W) frame ``index``."""
        return self.load(index)
