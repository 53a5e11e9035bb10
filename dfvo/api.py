"""The Python API: :class:`Odometry` (frames in one at a time, poses with covariances out) and :class:`StepResult`,
implemented in :mod:`dfvo.inference.api` (this module only gives them their short public home; ``dfvo.Odometry`` is
the same class). See ``docs/robots.md``."""

from dfvo.inference.api import SIZE_CHANGE, Odometry, StepResult

__all__ = ["Odometry", "StepResult", "SIZE_CHANGE"]
