"""Eigen depth metrics with optional median scaling and depth caps.

Convention:
    Depth maps ``(B,1,H,W)`` (or any equal shapes) in metres; ground truth ``<= 0`` is invalid. Following
    the common Eigen-split protocol, pixels are kept where ``min_depth < gt < max_depth``; with
    ``median_scaling`` each image's prediction is multiplied by ``median(gt)/median(pred)`` over its valid
    pixels; predictions are then clamped to ``[min_depth, max_depth]``. Metrics are computed per image
    and averaged over images.
"""

from __future__ import annotations

import torch

DEPTH_METRIC_NAMES = ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3")


def depth_errors(gt: torch.Tensor, pred: torch.Tensor) -> dict[str, float]:
    """Eigen metrics of 1-D tensors of valid, positive ``gt`` and ``pred`` (no masking, no scaling)."""
    gt, pred = gt.double(), pred.double()
    ratio = torch.maximum(gt / pred, pred / gt)
    return {
        "abs_rel": float(((gt - pred).abs() / gt).mean()),
        "sq_rel": float(((gt - pred) ** 2 / gt).mean()),
        "rmse": float(torch.sqrt(((gt - pred) ** 2).mean())),
        "rmse_log": float(torch.sqrt(((gt.log() - pred.log()) ** 2).mean())),
        "a1": float((ratio < 1.25).double().mean()),
        "a2": float((ratio < 1.25**2).double().mean()),
        "a3": float((ratio < 1.25**3).double().mean()),
    }


def compute_depth_metrics(pred: torch.Tensor, gt: torch.Tensor, min_depth: float = 1e-3, max_depth: float = 80.0,
                  median_scaling: bool = True, mask: torch.Tensor | None = None) -> dict[str, float]:
    """Mean over images of the Eigen metrics.

    Args:
        pred: ``(B,1,H,W)`` predicted depth.
        gt: ``(B,1,H,W)`` ground-truth depth (``<= 0`` = missing).
        min_depth: lower cap (m). max_depth: upper cap (m), e.g. 80 (Eigen) or 50 (Garg).
        median_scaling: per-image median scaling (monocular, up-to-scale predictions).
        mask: optional ``(B,1,H,W)`` bool, e.g. the Garg crop, and-ed with the depth range test.

    Returns:
        dict of the seven metrics plus ``scale`` (mean median-scaling factor, 1 without it) and ``num_images``.
    """
    if pred.shape != gt.shape or pred.dim() != 4 or pred.shape[1] != 1:
        raise ValueError(f"pred and gt must both be (B,1,H,W), got {tuple(pred.shape)} and {tuple(gt.shape)}")
    if mask is not None and mask.shape != gt.shape:
        raise ValueError(f"mask must have shape {tuple(gt.shape)}, got {tuple(mask.shape)}")
    sums = dict.fromkeys(DEPTH_METRIC_NAMES, 0.0)
    scales, count = [], 0
    for b in range(gt.shape[0]):
        valid = (gt[b] > min_depth) & (gt[b] < max_depth)
        if mask is not None:
            valid &= mask[b].bool()
        if not bool(valid.any()):
            continue
        g, p = gt[b][valid].double(), pred[b][valid].double()
        scale = float(g.median() / p.median()) if median_scaling else 1.0
        p = (p * scale).clamp(min_depth, max_depth)
        for k, v in depth_errors(g, p).items():
            sums[k] += v
        scales.append(scale)
        count += 1
    if count == 0:
        raise ValueError(f"compute_depth_metrics: no image has ground truth inside ({min_depth}, {max_depth}) m")
    out = {k: v / count for k, v in sums.items()}
    out["scale"] = sum(scales) / count
    out["num_images"] = count
    return out
