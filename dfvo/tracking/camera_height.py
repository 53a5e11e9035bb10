"""The camera's height above the road: given (the dataset or ``tracker.scale.camera_height``) or estimated.

A metric-scale prior needs the camera's height in metres. KITTI states it (1.65 m); a user's own video does not.
When it is not given it is estimated from the depth network's road plane (:func:`dfvo.tracking.scale_fusion.
depth_road_height`) over the frames seen so far: the median of the per-frame heights, available once
``min_frames`` frames have a plane and their robust spread (1.4826 MAD / median) is at most ``max_spread`` and the
value lies in ``height_range``. The estimate inherits the network's metric scale near the road (its absolute
length can be no better than the network's), but it is the same ruler on every frame, so the road observations keep
the scale consistent over time. A camera that sees no road (indoors, hand-held, a car's interior) gives no plane or
a wildly varying one: the height is then unavailable with the reason, and the scale falls back to the depth network
alone, flagged per frame.

Plain Python floats; causal (the estimate at frame k uses frames 0..k only), identical in ``step`` and ``run``.
"""

from __future__ import annotations

import statistics

from dfvo.tracking.config import CameraHeightConfig

__all__ = ["CameraHeight"]

MAD_TO_STD = 1.4826


class CameraHeight:
    """The camera height used by the road observations (see the module docstring).

    Args:
        given: the height in metres when known (None: estimate it when ``cfg.estimate``).
        cfg: :class:`CameraHeightConfig`.
    """

    def __init__(self, given: float | None, cfg: CameraHeightConfig) -> None:
        self.given, self.cfg = given, cfg
        self.reset()

    def reset(self) -> None:
        """Forget the observed road heights (a new sequence)."""
        self.heights: list[float] = []
        self.frames = 0

    def observe(self, network_height: float | None) -> None:
        """One frame's road-plane height of the depth network (metres; None: no plane this frame)."""
        self.frames += 1
        if network_height is not None and network_height > 0:
            self.heights.append(float(network_height))

    @property
    def enabled(self) -> bool:
        """A height is given, or may be estimated."""
        return self.given is not None or self.cfg.estimate

    @property
    def source(self) -> str | None:
        """``given``, ``estimated`` or None (unavailable now)."""
        if self.given is not None:
            return "given"
        return "estimated" if self.value is not None else None

    @property
    def estimate(self) -> float | None:
        """The median of the observed network road heights (metres), whatever its spread; None without any."""
        return statistics.median(self.heights) if self.heights else None

    @property
    def spread(self) -> float | None:
        """Robust relative spread of the observed heights (1.4826 MAD / median); None with fewer than two."""
        if len(self.heights) < 2:
            return None
        med = statistics.median(self.heights)
        return MAD_TO_STD * statistics.median(abs(h - med) for h in self.heights) / med

    @property
    def unavailable_reason(self) -> str | None:
        """Why there is no height now (None when there is one)."""
        if self.given is not None:
            return None
        if not self.cfg.estimate:
            return "no camera height given and tracker.camera_height.estimate=false"
        lo, hi = self.cfg.height_range
        if len(self.heights) < self.cfg.min_frames:
            return (f"camera height not estimated yet: a road plane on {len(self.heights)} of {self.frames} frames "
                    f"(needs {self.cfg.min_frames})")
        h, spread = self.estimate, self.spread
        if spread is not None and spread > self.cfg.max_spread:
            return (f"estimated camera height {h:.2f} m varies by {spread:.0%} between frames (> "
                    f"{self.cfg.max_spread:.0%}): no steady road in view")
        if not lo <= h <= hi:
            return f"estimated camera height {h:.2f} m outside [{lo:g}, {hi:g}] m: not a road below the camera"
        return None

    @property
    def value(self) -> float | None:
        """The camera height in metres to use now: the given one, or the estimate when it is plausible."""
        if self.given is not None:
            return float(self.given)
        return self.estimate if self.unavailable_reason is None else None

    def report(self) -> dict:
        """``summary.json``'s ``camera_height`` entry: value, source, spread, frames with a road plane, reason."""
        return {"value_m": None if self.value is None else round(self.value, 4), "source": self.source,
                "estimate_m": None if self.estimate is None else round(self.estimate, 4),
                "spread": None if self.spread is None else round(self.spread, 4),
                "frames_with_plane": len(self.heights), "frames": self.frames,
                "unavailable_reason": self.unavailable_reason}
