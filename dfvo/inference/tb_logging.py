"""Optional TensorBoard logging of an inference run (``tensorboard.enabled=true``).

Per logged frame (every ``tensorboard.every`` frames): the frame, its forward flow (colour wheel), the
forward-backward inconsistency (heat map, blue = leaves the image), the depth (inverse, normalised), the
correspondences that selection keeps (green dots on the frame), and the per-frame scalars of ``frames.csv``.
At the end: a bird's-eye trajectory figure and the metrics.

Convention: tensors of one frame pair without the batch axis: image (3,H,W), flows (2,H,W), depth (1,H,W).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from dfvo.matching.consistency import forward_backward_inconsistency
from dfvo.matching.selection import select_correspondences
from dfvo.training.flow_viz import flow_to_color, scalar_to_color

__all__ = ["log_frame", "log_trajectory"]

SCALARS = ("num_correspondences", "num_inliers", "gric_e", "gric_h", "scale", "t_flow", "t_depth", "t_tracker")


def log_frame(writer: Any, step: int, image: torch.Tensor, flow_fwd: torch.Tensor, flow_bwd: torch.Tensor,
              depth: torch.Tensor, row: dict[str, Any], cfg: Any) -> None:
    """Log images and scalars of frame ``step`` (the later frame of the pair; ``image`` is the earlier one)."""
    image = image.detach().cpu().float()
    fwd, bwd = flow_fwd.detach().cpu()[None], flow_bwd.detach().cpu()[None]
    incon = forward_backward_inconsistency(fwd, bwd)
    writer.add_image("frame", image, step)
    writer.add_image("flow_fwd", flow_to_color(fwd)[0], step)
    writer.add_image("inconsistency", scalar_to_color(incon, vmax=1.0)[0], step)
    inv = 1.0 / depth.detach().cpu().clamp(min=1e-3)
    writer.add_image("inverse_depth", (inv / inv.max().clamp(min=1e-6)).expand(3, -1, -1), step)
    corr = cfg.get("correspondence", {})
    sel = select_correspondences(fwd, incon, method=str(corr.get("selection_method", "local_best_k")),
                                 num=int(corr.get("num_correspondences", 2000)))
    dots = image.clone()
    pts = sel.pts_i[0][sel.mask[0]].round().long()
    h, w = image.shape[-2:]
    u, v = pts[:, 0].clamp(0, w - 1), pts[:, 1].clamp(0, h - 1)
    dots[:, v, u] = torch.tensor([0.0, 1.0, 0.0])[:, None]
    writer.add_image("correspondences", dots, step)
    for key in SCALARS:
        value = row.get(key)
        if isinstance(value, torch.Tensor):
            value = value.item() if value.numel() == 1 else None
        if isinstance(value, int | float) and np.isfinite(value):
            writer.add_scalar(f"frame/{key}", value, step)


def log_trajectory(writer: Any, gt: np.ndarray | None, pred: np.ndarray, metrics: dict[str, Any] | None) -> None:
    """Log the bird's-eye trajectory (x, z) and the scalar metrics."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 5))
    if gt is not None:
        ax.plot(gt[:, 0, 3], gt[:, 2, 3], "k--", label="ground truth")
    ax.plot(pred[:, 0, 3], pred[:, 2, 3], "b-", label="prediction")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend()
    writer.add_figure("trajectory", fig, 0)
    plt.close(fig)
    for key, value in (metrics or {}).items():
        if isinstance(value, int | float) and np.isfinite(value):
            writer.add_scalar(f"metrics/{key}", value, 0)
