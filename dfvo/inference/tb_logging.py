"""TensorBoard logging of an inference run (``tensorboard.enabled=true``): every ``every``-th frame's image, flow,
forward-backward inconsistency, inverse depth, the tracker's correspondences and its diagnostics as scalars; the
Training logs to TensorBoard through Lightning instead."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from dfvo.inference.config import TensorboardConfig
from dfvo.inference.loop import FrameRecord
from dfvo.matching.consistency import forward_backward_inconsistency
from dfvo.tracking.scale import has_depth
from dfvo.vis.colour import flow_to_color, scalar_to_color

__all__ = ["TensorboardObserver"]

SCALARS = ("num_correspondences", "num_inliers", "gric_e", "gric_h", "scale")


class TensorboardObserver:
    """Writes ``OUT/tensorboard`` as frames are tracked (``on_frame``), one event file per run.

    Args:
        folder: the event folder. every: log images of every ``every``-th frame (scalars of every frame).
    """

    def __init__(self, folder: Path, every: int = TensorboardConfig.every) -> None:
        from torch.utils.tensorboard import SummaryWriter

        self.writer = SummaryWriter(str(folder))
        self.every = max(1, int(every))

    def on_frame(self, record: FrameRecord) -> None:
        """Log frame ``record.index``."""
        step = record.index
        row = {**record.result.diagnostics.as_row(), **record.stage_seconds}
        for key in (*SCALARS, *record.stage_seconds):
            value = row.get(key)
            if isinstance(value, int | float) and not isinstance(value, bool) and np.isfinite(value):
                self.writer.add_scalar(f"frame/{key}", value, step)
        if (step - 1) % self.every:
            return
        image = record.image_prev.detach().cpu().float()
        fwd, bwd = record.flow_fwd.detach().cpu()[None], record.flow_bwd.detach().cpu()[None]
        self.writer.add_image("frame", image, step)
        self.writer.add_image("flow_fwd", flow_to_color(fwd)[0], step)
        self.writer.add_image("inconsistency", scalar_to_color(forward_backward_inconsistency(fwd, bwd),
                                                               vmax=1.0)[0], step)
        if has_depth(record.depth_prev):  # a frame without depth (depth.every) has none to show
            inv = 1.0 / record.depth_prev.detach().cpu().clamp(min=1e-3)
            self.writer.add_image("inverse_depth", (inv / inv.max().clamp(min=1e-6)).expand(3, -1, -1), step)
        matches = record.result.matches
        if matches is not None and len(matches.pts_prev):
            dots = image.clone()
            h, w = image.shape[-2:]
            pts = matches.pts_prev.round().long()
            u, v = pts[:, 0].clamp(0, w - 1), pts[:, 1].clamp(0, h - 1)
            inl = matches.inliers if matches.inliers is not None else torch.ones(len(pts), dtype=torch.bool)
            colour = torch.where(inl.cpu()[None], torch.tensor([0.0, 1.0, 0.0])[:, None],
                                 torch.tensor([1.0, 0.0, 0.0])[:, None])
            dots[:, v, u] = colour
            self.writer.add_image("correspondences", dots, step)

    def close(self) -> None:
        self.writer.close()
