"""How the camera moves: a car's inertia or a hand's (``tracker.motion``), judged from the first frames with ``auto``.

A car moves along its optical axis (forward, or back when it reverses); a hand, a head or a small robot's arm moves
the camera sideways, up and down as much as forward. So ``auto`` measures the angle between each early frame's
translation and the optical axis: on ground truth the median over the first ten steps is 0.2-8.7 deg on every road
we have (KITTI 06, 07, raw 0005, the four synthetic driving worlds; 13 deg at most on any one step) and 33-70 deg on
the hand-held cases (``handheld_markers``, the synthetic hand-held world's seeds 1000-1003): docs/robots.md.

Until the judgement the tracker runs a car's settings, so a car's poses are those of ``tracker.motion=car`` frame for
frame; a hand-held judgement switches to :class:`dfvo.tracking.config.HandheldConfig`'s for the rest of the
sequence (it is made once: a car does not become a hand).

Convention: a direction is ``T_prev_cur``'s translation (3,) in the earlier camera (x right, y down, z forward),
any length.
"""

from __future__ import annotations

import statistics
from dataclasses import asdict, dataclass

import torch

from dfvo.tracking.config import ModelSelectionMethod, MotionModel, PlanarMotion, TrackerConfig
from dfvo.tracking.gates import angle_deg

__all__ = ["MotionSettings", "MotionJudge", "motion_settings", "may_use_homography", "off_axis_deg"]


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


class MotionJudge:
    """The motion model in force, frame by frame: ``tracker.motion`` itself, or with ``auto`` a car's until
    ``motion_auto.frames`` frames have measured a direction, then the judgement (made once per sequence).

    Args:
        cfg: the tracker's configuration (``motion``, ``motion_auto``).
    """

    def __init__(self, cfg: TrackerConfig) -> None:
        self.cfg = cfg
        self.reset()

    def reset(self) -> None:
        """Forget the sequence: no direction measured, no judgement."""
        self.angles: list[float] = []
        self.judged_at: int | None = None  # the frame whose observation completed the judgement
        self.reason: str | None = None
        setting = self.cfg.motion
        self.motion = MotionModel.car if setting == MotionModel.auto else setting

    @property
    def settings(self) -> MotionSettings:
        """The settings of the motion in force."""
        return motion_settings(self.cfg, self.motion)

    @property
    def may_use_homography(self) -> bool:
        """Whether the frames to come may take the homography's decomposition: the motion in force uses it, or
        ``auto`` has not judged yet and either motion's settings would."""
        motions = [MotionModel.car, MotionModel.handheld] if self.deciding else [self.motion]
        return any(motion_settings(self.cfg, m).planar == PlanarMotion.homography for m in motions)

    @property
    def deciding(self) -> bool:
        """``auto`` and not judged yet."""
        return self.cfg.motion == MotionModel.auto and self.judged_at is None

    def observe(self, frame: int, direction: torch.Tensor | None, parallax_px: float | None) -> str | None:
        """Count frame ``frame``'s measured translation ``direction`` (3,) (None: none measured), taken when its image
        moved ``parallax_px`` or more beyond the rotation (``motion_auto.min_parallax_px``); returns the judgement's
        message on the frame that makes it, else None. Does nothing once judged or unless ``tracker.motion=auto``."""
        a = self.cfg.motion_auto
        if not self.deciding or direction is None or parallax_px is None or not parallax_px >= a.min_parallax_px:
            return None
        angle = off_axis_deg(direction)
        if angle != angle:
            return None
        self.angles.append(angle)
        if len(self.angles) < int(a.frames):
            return None
        median = statistics.median(self.angles)
        self.judged_at = frame
        self.motion = MotionModel.handheld if median > float(a.off_axis_deg) else MotionModel.car
        side = ">" if self.motion == MotionModel.handheld else "<="
        self.reason = (f"tracker.motion=auto: {self.motion.value} from frame {frame + 1} on (the median angle between "
                       f"the translation and the optical axis over {len(self.angles)} frames is {median:.1f} deg "
                       f"{side} motion_auto.off_axis_deg={float(a.off_axis_deg):g})")
        return self.reason

    def report(self) -> dict[str, object]:
        """``summary.json``'s ``motion``: the setting, the motion the run ended with and its settings (``planar`` is
        ``pnp`` for a hand too where no homography is fitted, ``model_selection.method=flow``), and how ``auto`` judged
        it."""
        return {"setting": self.cfg.motion.value, "motion": self.motion.value,
                "settings": {k: (v.value if hasattr(v, "value") else v) for k, v in asdict(self.settings).items()},
                "judged_from_frame": None if self.judged_at is None else self.judged_at + 1,
                "frames_measured": len(self.angles),
                "median_off_axis_deg": round(statistics.median(self.angles), 2) if self.angles else None,
                "off_axis_deg": [round(a, 1) for a in self.angles],
                "reason": self.reason if self.reason is not None else (
                    f"tracker.motion={self.cfg.motion.value}" if self.cfg.motion != MotionModel.auto else
                    f"tracker.motion=auto: not judged ({len(self.angles)} of {int(self.cfg.motion_auto.frames)} "
                    "frames measured a direction); a car's settings throughout")}


def may_use_homography(cfg: TrackerConfig) -> bool:
    """Whether a sequence tracked with ``cfg`` may take the homography's decomposition on its first frames (so the
    batched E-tracker computes it): :attr:`MotionJudge.may_use_homography` of a new sequence."""
    return MotionJudge(cfg).may_use_homography
