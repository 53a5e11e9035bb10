"""Plausibility gates: a tracker's result that the motion model or its own support cannot back is not used.

A pose from the E-tracker or the PnP-tracker is rejected when its translation length is far from the length the
motion model expects (the last tracked frame's): more than ``max_length_ratio`` times longer (the expectation taken
as at least ``min_reference_length``, so starts from standstill pass), or shorter by that factor unless it is a stop
(at most ``stop_length`` while the image shows no parallax either: a tracker locked onto a truck that moves with the
camera reports a "stop" while the static scene streams past); when its direction turns too far from the previous
frame's; or when it rests on too few inliers. The frame then falls back (E: to the temporal filter's prediction for a
length-gated scale, else to PnP in the hybrid tracker; PnP: to constant motion) with the reason in
``fallback_reason``. After ``max_consecutive`` constant-motion frames in a row caused by a gate the next result is
accepted (flagged), so a wrong expectation cannot lock the trajectory; the motion model and the scale filter then
start afresh.
"""

from __future__ import annotations

import math

import torch

from dfvo.tracking.config import GateConfig

__all__ = ["image_parallax_px", "check_support", "check_length", "check_direction"]


def image_parallax_px(pts_prev: torch.Tensor, pts_cur: torch.Tensor, R: torch.Tensor, K: torch.Tensor,
                      quantile: float = 0.9) -> float | None:
    """How far the image moves beyond the camera's rotation: the ``quantile`` of the distances (pixels) between
    ``pts_cur`` (N,2) and ``pts_prev`` (N,2) carried by the rotation ``R`` (3,3) of ``T_cur_prev`` alone (the
    infinite homography ``K R K^-1``, K (3,3)). Near zero when the camera stands still or only rotates; None
    without points."""
    if pts_prev.shape[0] == 0:
        return None
    Kd, Rd = K.reshape(3, 3).to(torch.float64), R.reshape(3, 3).to(torch.float64)
    x = torch.cat([pts_prev.to(torch.float64), torch.ones_like(pts_prev[:, :1], dtype=torch.float64)], -1)
    y = x @ (Kd @ Rd @ torch.linalg.inv(Kd)).T
    warped = y[:, :2] / y[:, 2:].clamp_min(1e-12)
    return float((pts_cur.to(torch.float64) - warped).norm(dim=-1).quantile(quantile))


def check_support(kind: str, num_inliers: int, num_rows: int, cfg: GateConfig) -> str | None:
    """Why the model of tracker ``kind`` ("E", "PnP") with ``num_inliers`` of ``num_rows`` usable rows rests on too
    few inliers (fewer than ``max(cfg.min_inliers, cfg.min_inlier_fraction * num_rows)``); None when enough (or the
    gates are off)."""
    if not cfg.enabled:
        return None
    need = max(int(cfg.min_inliers), int(cfg.min_inlier_fraction * num_rows))
    if num_inliers < need:
        return f"gate: {kind} rests on {num_inliers} inliers of {num_rows} rows (< {need})"
    return None


def check_length(kind: str, length: float, expected: float | None, cfg: GateConfig,
                 image_motion_px: float | None = None, settled: bool = True) -> str | None:
    """Why a translation of ``length`` metres from tracker ``kind`` is implausible given the ``expected`` length
    (None: no expectation yet, nothing is judged): more than ``cfg.max_length_ratio`` times ``max(expected,
    cfg.min_reference_length)``, or shorter than ``expected / cfg.max_length_ratio``, unless it is a stop: at most
    ``cfg.stop_length`` while the image shows no parallax either (``image_motion_px``, :func:`image_parallax_px` of
    the selected correspondences, at most ``cfg.stop_flow_px``; None: not known, the length alone decides). A tracker
    locked onto a vehicle moving with the camera reports a "stop" while the static scene still streams past.
    ``settled``: false while the expectation rests on fewer than ``cfg.length_window`` lengths (a sequence's first
    frames, whose scale may be far off): the wider ``cfg.warmup_length_ratio`` applies. None when plausible (or the
    gates are off)."""
    if not cfg.enabled or expected is None or not expected > 0:
        return None
    ratio = cfg.max_length_ratio if settled else max(cfg.max_length_ratio, cfg.warmup_length_ratio)
    if length > ratio * max(expected, cfg.min_reference_length):
        return f"gate: {kind} translation {length:.3g} m > {ratio:g} x the expected {expected:.3g} m"
    still = image_motion_px is None or image_motion_px <= cfg.stop_flow_px
    if length * ratio < expected and (length > cfg.stop_length or not still):
        moving = "" if still else f" (not a stop: {image_motion_px:.3g} px of parallax)"
        return f"gate: {kind} translation {length:.3g} m < the expected {expected:.3g} m / {ratio:g}{moving}"
    return None


def check_direction(kind: str, direction: torch.Tensor, expected: torch.Tensor | None, length: float,
                    cfg: GateConfig) -> str | None:
    """Why a translation along ``direction`` (3,) (``T_prev_cur``'s, in the earlier camera) is implausible given the
    previous frame's ``expected`` direction (3,): more than ``cfg.max_direction_change_deg`` apart while both motions
    are longer than ``cfg.stop_length`` (a vehicle cannot reverse or turn its motion that much between frames; an
    E-tracker locked onto a large moving object does). None when plausible, unknown or the gates are off."""
    if not cfg.enabled or expected is None or length <= cfg.stop_length:
        return None
    a, b = direction.to(torch.float64), expected.to(torch.float64)
    cos = float((a @ b) / (a.norm() * b.norm()).clamp_min(1e-12))
    angle = math.degrees(math.acos(max(-1.0, min(1.0, cos))))
    if angle > cfg.max_direction_change_deg:
        return f"gate: {kind} translation turns {angle:.0f} deg from the previous frame's (> " \
               f"{cfg.max_direction_change_deg:g})"
    return None
