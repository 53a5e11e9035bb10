"""Trackers and the odometry loop: E-tracker with GRIC, PnP-tracker, scale recovery, VisualOdometry."""

from dfvo.tracking.config import TrackerConfig
from dfvo.tracking.odometry import FrameResult, VisualOdometry

__all__ = ["TrackerConfig", "VisualOdometry", "FrameResult"]
