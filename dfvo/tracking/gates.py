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
from dfvo.tracking.ground_plane import MAD_TO_STD

__all__ = ["image_parallax_px", "check_support", "check_length", "check_direction", "angle_deg", "MotionSpread"]


def angle_deg(a: torch.Tensor, b: torch.Tensor) -> float:
    """The angle (degrees) between the vectors ``a`` and ``b`` (3,)."""
    a, b = a.to(torch.float64), b.to(torch.float64)
    cos = float((a @ b) / (a.norm() * b.norm()).clamp_min(1e-12))
    return math.degrees(math.acos(max(-1.0, min(1.0, cos))))


class MotionSpread:
    """The sequence's own frame-to-frame changes of motion, and the gate limits they allow.

    Over the last ``cfg.adaptive_window`` frames it keeps each tracked step's length and direction and whether it
    was a stop (at most ``cfg.stop_length`` while the image shows at most ``cfg.stop_flow_px`` of parallax), None for
    a frame that was not tracked; the changes are those between consecutive tracked steps that are not both stops
    (a car waiting at a light: its lengths are noise): ``log(L_k / L_k-1)``, and the angle between their directions
    when both are longer than ``cfg.stop_length`` (as the direction gate judges). Their
    robust standard deviations (1.4826 x the median absolute log ratio about its median; 1.4826 x the median angle,
    a half-normal's) times ``k = cfg.adaptive_sigmas`` widen the fixed limits, once ``cfg.adaptive_min_changes``
    changes are known: ``length_ratio = max(cfg.max_length_ratio, exp(k sigma_log))``, ``direction_deg =
    max(cfg.max_direction_change_deg, min(180, k sigma_deg))``.
    """

    def __init__(self, cfg: GateConfig) -> None:
        self.cfg = cfg
        self.reset()

    def reset(self) -> None:
        self.steps: list[tuple[float, torch.Tensor, bool] | None] = []  # (length, direction, a stop)
        self.length_ratio = self.cfg.max_length_ratio  # the length ratio the gate allows
        self.direction_deg = self.cfg.max_direction_change_deg  # the direction change it allows (at most 180)

    def add(self, length: float | None, direction: torch.Tensor | None, parallax_px: float | None = None) -> None:
        """This frame's tracked step (``length`` m, unit ``direction`` (3,), the image's parallax beyond the rotation
        in pixels, None: unknown), or None for an untracked frame; updates :attr:`length_ratio` and
        :attr:`direction_deg`."""
        ok = length is not None and direction is not None and length > 0 and math.isfinite(length)
        stop = ok and length <= self.cfg.stop_length and (parallax_px is None or parallax_px <= self.cfg.stop_flow_px)
        self.steps = (self.steps + [(float(length), direction.to(torch.float64), stop) if ok else None])[
            -int(self.cfg.adaptive_window):]
        logs, angles = [], []
        for a, b in zip(self.steps[:-1], self.steps[1:]):
            if a is None or b is None or (a[2] and b[2]):  # two stops in a row: both lengths are noise
                continue
            logs.append(math.log(b[0] / a[0]))
            if min(a[0], b[0]) > self.cfg.stop_length:  # the direction gate judges longer motions only
                angles.append(angle_deg(a[1], b[1]))
        k = self.cfg.adaptive_sigmas * MAD_TO_STD
        log_spread = self._spread(logs, centred=True)
        self.length_ratio = self.cfg.max_length_ratio if log_spread is None else \
            max(self.cfg.max_length_ratio, math.exp(min(k * log_spread, 20.0)))
        angle_spread = self._spread(angles, centred=False)
        self.direction_deg = self.cfg.max_direction_change_deg if angle_spread is None else \
            max(self.cfg.max_direction_change_deg, min(180.0, k * angle_spread))

    def _spread(self, values: list[float], centred: bool) -> float | None:
        """The median absolute deviation of ``values`` about their median (``centred``) or about 0 (angles, a
        half-normal's); None while there are fewer than ``cfg.adaptive_min_changes`` or the limits are fixed."""
        if self.cfg.adaptive_sigmas <= 0 or len(values) < int(self.cfg.adaptive_min_changes):
            return None
        t = torch.tensor(values, dtype=torch.float64)
        return float(((t - t.median()) if centred else t).abs().median())


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
                 image_motion_px: float | None = None, settled: bool = True,
                 max_ratio: float | None = None) -> str | None:
    """Why a translation of ``length`` metres from tracker ``kind`` is implausible given the ``expected`` length
    (None: no expectation yet, nothing is judged): more than ``cfg.max_length_ratio`` times ``max(expected,
    cfg.min_reference_length)``, or shorter than ``expected / cfg.max_length_ratio``, unless it is a stop: at most
    ``cfg.stop_length`` while the image shows no parallax either (``image_motion_px``, :func:`image_parallax_px` of
    the selected correspondences, at most ``cfg.stop_flow_px``; None: not known, the length alone decides). A tracker
    locked onto a vehicle moving with the camera reports a "stop" while the static scene still streams past.
    ``settled``: false while the expectation rests on fewer than ``cfg.length_window`` lengths (a sequence's first
    frames, whose scale may be far off): the wider ``cfg.warmup_length_ratio`` applies. ``max_ratio``: the ratio
    allowed instead of ``cfg.max_length_ratio`` (the sequence's own, :class:`MotionSpread`). None when plausible (or
    the gates are off)."""
    if not cfg.enabled or expected is None or not expected > 0:
        return None
    base = cfg.max_length_ratio if max_ratio is None else max_ratio
    ratio = base if settled else max(base, cfg.warmup_length_ratio)
    if length > ratio * max(expected, cfg.min_reference_length):
        return f"gate: {kind} translation {length:.3g} m > {ratio:g} x the expected {expected:.3g} m"
    still = image_motion_px is None or image_motion_px <= cfg.stop_flow_px
    if length * ratio < expected and (length > cfg.stop_length or not still):
        moving = "" if still else f" (not a stop: {image_motion_px:.3g} px of parallax)"
        return f"gate: {kind} translation {length:.3g} m < the expected {expected:.3g} m / {ratio:g}{moving}"
    return None


def check_direction(kind: str, direction: torch.Tensor, expected: torch.Tensor | None, length: float,
                    cfg: GateConfig, max_deg: float | None = None) -> str | None:
    """Why a translation along ``direction`` (3,) (``T_prev_cur``'s, in the earlier camera) is implausible given the
    previous frame's ``expected`` direction (3,): more than ``cfg.max_direction_change_deg`` (``max_deg`` when given:
    the sequence's own, :class:`MotionSpread`) apart while both motions are longer than ``cfg.stop_length`` (a vehicle
    cannot reverse or turn its motion that much between frames; an E-tracker locked onto a large moving object does).
    None when plausible, unknown or the gates are off."""
    if not cfg.enabled or expected is None or length <= cfg.stop_length:
        return None
    limit = cfg.max_direction_change_deg if max_deg is None else max_deg
    angle = angle_deg(direction, expected)
    if angle > limit:
        return f"gate: {kind} translation turns {angle:.0f} deg from the previous frame's (> {limit:.3g})"
    return None
