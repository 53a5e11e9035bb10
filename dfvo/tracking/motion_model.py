"""How the camera moves: a car's inertia or a hand's (``tracker.motion``), judged from the first frames with ``auto``.

A car moves along its optical axis (forward, or back when it reverses); a hand, a head or a small robot's arm moves
the camera sideways, up and down as much as forward. So ``auto`` measures the angle between each early frame's
translation and the optical axis: on ground truth the median over the first ten steps is 0.2-8.7 deg on every road
we have (KITTI 06, 07, raw 0005, the four synthetic driving worlds; 13 deg at most on any one step) and 33-70 deg on
the hand-held cases (``handheld_markers``, the synthetic hand-held world's seeds 1000-1003): docs/robots.md.

Until the judgement the tracker runs a car's settings, so a car's poses are those of ``tracker.motion=car`` frame for
frame; a hand-held judgement switches to :class:`dfvo.tracking.config.HandheldConfig`'s for the rest of the
sequence (a car does not become a hand). A car's verdict is revised (``motion_auto.revise_frames``): a hand whose
first moves ran along the optical axis (or were measured so), judged a car, turns hand-held when its latest measured
translations leave both the optical axis and the camera's horizontal plane; a car's never leave the plane (a car
may move off its optical axis: the synthetic drive world's sideways steps, 73-86 deg off it, lie in that plane).

Convention: a direction is ``T_prev_cur``'s translation (3,) in the earlier camera (x right, y down, z forward),
any length.
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from dataclasses import asdict, dataclass

import torch

from dfvo.tracking.config import ModelSelectionMethod, MotionModel, PlanarMotion, TrackerConfig
from dfvo.tracking.gates import angle_deg

__all__ = ["MotionSettings", "MotionJudge", "motion_settings", "may_use_homography", "off_axis_deg",
           "elevation_deg"]


@dataclass(frozen=True)
class MotionSettings:
    """The settings a motion model decides (the tracker reads them here, not from ``tracker.gate`` /
    ``tracker.model_selection`` directly): see :class:`dfvo.tracking.config.GateConfig` and
    :class:`dfvo.tracking.config.HandheldConfig`."""

    confirm_direction_frames: int | None
    confirm_direction_by_pnp_deg: float | None
    planar: PlanarMotion
    confirm_length_frames: int | None = None


def motion_settings(cfg: TrackerConfig, motion: MotionModel) -> MotionSettings:
    """The settings in force for ``motion`` (``car`` or ``handheld``): a car's are ``tracker.gate``'s and
    ``tracker.model_selection``'s, a hand's ``tracker.handheld``'s (its planar path only where GRIC fits the
    homography)."""
    if motion == MotionModel.handheld:
        h = cfg.handheld
        planar = h.planar if cfg.model_selection.method == ModelSelectionMethod.gric else PlanarMotion.pnp
        return MotionSettings(h.confirm_direction_frames, h.confirm_direction_by_pnp_deg, planar,
                              h.confirm_length_frames)
    g = cfg.gate
    return MotionSettings(g.confirm_direction_frames, g.confirm_direction_by_pnp_deg, cfg.model_selection.planar,
                          g.confirm_length_frames)


def off_axis_deg(direction: torch.Tensor) -> float:
    """Angle (degrees, 0-90) between a translation ``direction`` (3,) and the optical axis, either way along it; NaN
    for a zero vector."""
    if not float(direction.norm()) > 0.0:
        return float("nan")
    angle = angle_deg(direction, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    return min(angle, 180.0 - angle)


def elevation_deg(direction: torch.Tensor) -> float:
    """Angle (degrees, 0-90) between a translation ``direction`` (3,) and the camera's horizontal plane (x-z), up or
    down; NaN for a zero vector."""
    norm = float(direction.norm())
    if not norm > 0.0:
        return float("nan")
    return math.degrees(math.asin(min(1.0, abs(float(direction[1])) / norm)))


class MotionJudge:
    """The motion model in force, frame by frame: ``tracker.motion`` itself, or with ``auto`` a car's until
    ``motion_auto.frames`` frames have measured a direction, then the judgement; a car's judgement is revised on
    every later frame that counts a measured direction, from the last ``motion_auto.revise_frames`` of them, until
    they say hand-held.

    Args:
        cfg: the tracker's configuration (``motion``, ``motion_auto``).
    """

    def __init__(self, cfg: TrackerConfig) -> None:
        self.cfg = cfg
        self.reset()

    def reset(self) -> None:
        """Forget the sequence: no direction measured, no judgement."""
        self.angles: list[float] = []  # the first judgement's angles to the optical axis
        self.latest: deque[tuple[float, float]] = deque(maxlen=int(self.cfg.motion_auto.revise_frames or 1))
        self.judged_at: int | None = None  # the frame whose observation completed the judgement
        self.revised_at: int | None = None  # the frame whose direction turned a car's judgement hand-held
        self.reason: str | None = None
        setting = self.cfg.motion
        self.motion = MotionModel.car if setting == MotionModel.auto else setting

    @property
    def settings(self) -> MotionSettings:
        """The settings of the motion in force."""
        return motion_settings(self.cfg, self.motion)

    @property
    def may_use_homography(self) -> bool:
        """Whether the next batch's E-tracker decomposes the homography up front: the motion in force uses it, or
        ``auto`` has not judged yet and either motion's settings would. After a car's verdict it does not, though a
        revision may come: a pair that needs the decomposition then gets it on demand
        (:meth:`dfvo.tracking.e_tracker.ETrackerResult.with_homography`)."""
        motions = [MotionModel.car, MotionModel.handheld] if self.deciding else [self.motion]
        return any(motion_settings(self.cfg, m).planar == PlanarMotion.homography for m in motions)

    @property
    def deciding(self) -> bool:
        """``auto`` and not judged yet."""
        return self.cfg.motion == MotionModel.auto and self.judged_at is None

    @property
    def revisable(self) -> bool:
        """``auto`` judged a car, and ``motion_auto.revise_frames`` may still turn it hand-held."""
        return (self.cfg.motion == MotionModel.auto and self.judged_at is not None and self.motion == MotionModel.car
                and self.cfg.motion_auto.revise_frames is not None)

    def observe(self, frame: int, direction: torch.Tensor | None,
                parallax_px: float | None) -> tuple[float, float] | None:
        """Count frame ``frame``'s measured translation ``direction`` (3,) (the first result a tracker measured,
        accepted or not; None: none), taken when its image moved ``parallax_px`` or more beyond the rotation
        (``motion_auto.min_parallax_px``). With ``tracker.motion=auto`` it judges the motion when this frame completes
        ``motion_auto.frames`` (the median angle to the optical axis), and after a car's verdict revises it on every
        frame from the last ``motion_auto.revise_frames`` counted directions (their median angles to the optical axis
        and to the camera's horizontal plane); the verdict and any revision in ``reason``.

        Returns:
            The direction's angles (degrees, 0-90) to the optical axis and to the camera's horizontal plane when it
            counts (any ``tracker.motion``; the frame's diagnostics ``off_axis_deg``, ``elevation_deg``), else None.
        """
        a = self.cfg.motion_auto
        if direction is None or parallax_px is None or not parallax_px >= a.min_parallax_px:
            return None
        angle, elevation = off_axis_deg(direction), elevation_deg(direction)
        if angle != angle:
            return None
        limit = float(a.off_axis_deg)
        self.latest.append((angle, elevation))  # the last revise_frames measured directions' angles
        if self.deciding:
            self.angles.append(angle)
            if len(self.angles) == int(a.frames):
                median = statistics.median(self.angles)
                self.judged_at = frame
                self.motion = MotionModel.handheld if median > limit else MotionModel.car
                side = ">" if self.motion == MotionModel.handheld else "<="
                self.reason = (f"tracker.motion=auto: {self.motion.value} from frame {frame + 1} on (the median angle "
                               f"between the translation and the optical axis over {len(self.angles)} frames is "
                               f"{median:.1f} deg {side} motion_auto.off_axis_deg={limit:g})")
        elif self.revisable and len(self.latest) == self.latest.maxlen:
            off = statistics.median(off_axis for off_axis, _ in self.latest)
            up = statistics.median(rise for _, rise in self.latest)
            if off > limit and up > float(a.revise_elevation_deg):
                self.revised_at = frame
                self.motion = MotionModel.handheld
                self.reason = (f"{self.reason}; revised: handheld from frame {frame + 1} on (over the last "
                               f"{len(self.latest)} translations the median angle to the optical axis is {off:.1f} "
                               f"deg > motion_auto.off_axis_deg={limit:g} and to the camera's horizontal plane "
                               f"{up:.1f} deg > motion_auto.revise_elevation_deg={float(a.revise_elevation_deg):g})")
        return angle, elevation

    def report(self) -> dict[str, object]:
        """``summary.json``'s ``motion``: the setting, the motion the run ended with and its settings (``planar`` is
        ``pnp`` for a hand too where no homography is fitted, ``model_selection.method=flow``), and how ``auto`` judged
        it."""
        return {"setting": self.cfg.motion.value, "motion": self.motion.value,
                "settings": {k: (v.value if hasattr(v, "value") else v) for k, v in asdict(self.settings).items()},
                "judged_from_frame": None if self.judged_at is None else self.judged_at + 1,
                "revised_from_frame": None if self.revised_at is None else self.revised_at + 1,
                "frames_measured": len(self.angles),
                "median_off_axis_deg": round(statistics.median(self.angles), 2) if self.angles else None,
                "off_axis_deg": [round(a, 1) for a in self.angles],
                "latest_off_axis_elevation_deg": [[round(a, 1), round(e, 1)] for a, e in self.latest],
                "reason": self.reason if self.reason is not None else (
                    f"tracker.motion={self.cfg.motion.value}" if self.cfg.motion != MotionModel.auto else
                    f"tracker.motion=auto: not judged ({len(self.angles)} of {int(self.cfg.motion_auto.frames)} "
                    "frames measured a direction); a car's settings throughout")}


def may_use_homography(cfg: TrackerConfig) -> bool:
    """Whether a sequence tracked with ``cfg`` may take the homography's decomposition on its first frames (so the
    batched E-tracker computes it): :attr:`MotionJudge.may_use_homography` of a new sequence."""
    return MotionJudge(cfg).may_use_homography
