"""Optical-flow metrics: AEPE, Out-N, KITTI Fl, and the KITTI devkit's filling of sparse predictions.

Convention:
    Flow ``(B,2,H,W)`` or ``(2,H,W)`` in pixels (u right, v down); a validity mask of the same leading shape
    with one channel (``(B,1,H,W)`` / ``(1,H,W)``) or none (all valid). ``EPE = ||pred - gt||``; Out-N is the
    percentage of pixels with ``EPE > N`` px (the DF-VO paper's Out-1); KITTI's Fl (flow outlier) is the
    percentage with ``EPE > 3`` px **and** ``EPE > 5 %`` of the true flow magnitude (the KITTI 2015 devkit).
    Flow files (``.flo``, ``.pfm``, KITTI PNG) are read and written by :mod:`dfvo.data.flow_io`.
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["compute_flow_metrics", "flow_error_sums", "metrics_from_sums", "kitti_fill_invalid"]


def _epe_and_mag(flow_pred: torch.Tensor, flow_gt: torch.Tensor, valid: torch.Tensor | None):
    if flow_pred.shape != flow_gt.shape or flow_pred.dim() not in (3, 4) or flow_pred.shape[-3] != 2:
        raise ValueError(f"flows must both be (B,2,H,W) or (2,H,W), got {tuple(flow_pred.shape)} and "
                         f"{tuple(flow_gt.shape)}")
    epe = torch.linalg.vector_norm(flow_pred.double() - flow_gt.double(), dim=-3)
    mag = torch.linalg.vector_norm(flow_gt.double(), dim=-3)
    if valid is None:
        mask = torch.ones_like(epe, dtype=torch.bool)
    else:
        if valid.shape[-3] != 1 or valid.shape[:-3] + valid.shape[-2:] != epe.shape:
            raise ValueError(f"valid must be {tuple(epe.shape[:-2])}+(1,)+{tuple(epe.shape[-2:])}, got "
                             f"{tuple(valid.shape)}")
        mask = valid.squeeze(-3).bool().to(epe.device)
    return epe[mask], mag[mask]


def flow_error_sums(flow_pred: torch.Tensor, flow_gt: torch.Tensor, valid: torch.Tensor | None = None,
                    thresholds: tuple[float, ...] = (1.0, 3.0, 5.0)) -> dict[str, float]:
    """Sums to pool flow metrics over many images: ``{"epe_sum", "out_<N>_count", "fl_count", "num_pixels"}``.

    A mask that selects no pixel gives zero sums (``num_pixels = 0``)."""
    epe, mag = _epe_and_mag(flow_pred, flow_gt, valid)
    out = {"epe_sum": float(epe.sum()), "num_pixels": int(epe.numel())}
    for t in thresholds:
        out[f"out_{t:g}_count"] = int((epe > t).sum())
    out["fl_count"] = int(((epe > 3.0) & (epe > 0.05 * mag)).sum())
    return out


def metrics_from_sums(sums: dict[str, float]) -> dict[str, float | int | None]:
    """``{"aepe", "out_<N>" (%), "fl" (%), "num_pixels"}`` from (pooled) :func:`flow_error_sums`; None when the
    sums hold no pixel."""
    n = int(sums["num_pixels"])
    out: dict[str, float | int | None] = {"aepe": sums["epe_sum"] / n if n else None}
    for key, value in sums.items():
        if key.startswith("out_") and key.endswith("_count"):
            out[key[: -len("_count")]] = 100.0 * value / n if n else None
    out["fl"] = 100.0 * sums["fl_count"] / n if n else None
    out["num_pixels"] = n
    return out


def compute_flow_metrics(flow_pred: torch.Tensor, flow_gt: torch.Tensor, valid: torch.Tensor | None = None,
                         thresholds: tuple[float, ...] = (1.0, 3.0, 5.0)) -> dict[str, float]:
    """AEPE, Out-N and KITTI Fl over the valid pixels of all images together.

    Returns:
        ``{"aepe", "out_<N>" (% of pixels with EPE > N px) for each threshold, "fl" (% of pixels with
        EPE > 3 px and EPE > 5 % of |flow_gt|), "num_pixels"}``.

    Raises:
        ValueError: shapes differ, or the mask selects no pixel.
    """
    sums = flow_error_sums(flow_pred, flow_gt, valid, thresholds)
    if sums["num_pixels"] == 0:
        raise ValueError("flow metrics: the validity mask selects no pixel")
    return metrics_from_sums(sums)


def _fill_rows(flow: np.ndarray, valid: np.ndarray) -> None:
    """Row pass of :func:`kitti_fill_invalid` (in place on ``flow`` (H,W,2), ``valid`` (H,W))."""
    H, W = valid.shape
    for v in range(H):
        cols = np.flatnonzero(valid[v])
        if cols.size == 0:
            continue
        row = flow[v]
        gaps = np.flatnonzero(np.diff(cols) > 1)  # interior holes between valid cols[g] and cols[g+1]
        for g in gaps:
            a, b = cols[g], cols[g + 1]
            row[a + 1:b] = np.minimum(row[a], row[b])
        row[: cols[0]] = row[cols[0]]
        row[cols[-1] + 1:] = row[cols[-1]]
        valid[v] = True


def kitti_fill_invalid(flow: torch.Tensor, valid: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Fill the invalid pixels of a predicted flow the way the KITTI devkit does before scoring a sparse result.

    Per row, a run of invalid pixels between two valid ones takes the component-wise minimum of their two flows
    (the background is assumed to be the smaller motion); pixels left of the first / right of the last valid pixel
    take that pixel's flow. Then per column, pixels above the first / below the last valid pixel (rows that had
    no valid pixel) take that pixel's flow.

    Args:
        flow: ``(2,H,W)`` predicted flow.
        valid: ``(1,H,W)`` bool, which pixels the prediction defines.

    Returns:
        ``(flow (2,H,W), valid (1,H,W))``: every pixel filled except rows without any valid pixel that lie between
        rows with one (flow 0 and invalid there, as in the devkit); unchanged when no pixel or every pixel is
        valid.
    """
    if flow.dim() != 3 or flow.shape[0] != 2 or valid.shape != (1, *flow.shape[1:]):
        raise ValueError(f"kitti_fill_invalid: expected flow (2,H,W) and valid (1,H,W), got {tuple(flow.shape)} and "
                         f"{tuple(valid.shape)}")
    f = flow.detach().cpu().double().permute(1, 2, 0).numpy().copy()
    m = valid[0].detach().cpu().numpy().astype(bool).copy()
    if m.all() or not m.any():
        return flow, valid
    f[~m] = 0.0  # the devkit's reader gives invalid pixels flow 0; rows without any valid pixel keep it
    _fill_rows(f, m)
    # columns: extrapolate the first / last valid row upwards / downwards (interior empty rows stay 0, invalid)
    rows = np.flatnonzero(m.any(axis=1))
    f[: rows[0]] = f[rows[0]]
    f[rows[-1] + 1:] = f[rows[-1]]
    m[: rows[0]] = True
    m[rows[-1] + 1:] = True
    return (torch.from_numpy(f.transpose(2, 0, 1).astype(np.float32)).to(flow.device),
            torch.from_numpy(m[None]).to(valid.device))
