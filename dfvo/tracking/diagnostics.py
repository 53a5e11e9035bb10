"""Per-frame diagnostics of the odometry loop: one schema read by ``frames.csv``, TensorBoard, the viewer and
``summary.json`` alike."""

from __future__ import annotations

from dataclasses import dataclass, fields
from enum import StrEnum
from typing import Any

__all__ = ["TrackerUsed", "FrameDiagnostics", "DIAGNOSTIC_FIELDS"]


class TrackerUsed(StrEnum):
    """How a frame's pose was obtained. ``init``: frame 0 (identity); ``E``: essential matrix + scale; ``PnP``:
    PnP on the earlier frame's depth; ``constant_motion``: the previous relative motion repeated (a fallback)."""

    init = "init"
    essential = "E"
    pnp = "PnP"
    constant_motion = "constant_motion"


@dataclass
class FrameDiagnostics:
    """What the tracker did on one frame (frame index ``frame`` of its sequence; pairs are (frame-1, frame)).

    Attributes:
        tracker: :class:`TrackerUsed` (None while the frame is being tracked).
        num_correspondences: selected correspondences; num_inliers: inliers of the model that was used.
        gric_e, gric_h: GRIC scores of E and H (None when model selection is not GRIC or E did not run).
        cheirality_fraction: fraction of the selected rows in front of both cameras under E's pose.
        parallax_px: median image motion of E's inliers beyond the camera's rotation (pixels): what the translation
            shows (model selection keeps E above ``tracker.model_selection.min_parallax_px``).
        scale: length of the translation used (metres for metric depth).
        scale_iterations: iterations of Algorithm 2 (iterative scale only).
        scale_cnn: the scale from CNN depth (None when it failed or E did not run).
        scale_height: the camera-height scale (``tracker.scale.camera_height``): with ``road_plane.points=
            triangulated`` the camera height over the road plane's height among the triangulated points; with
            ``depth`` the CNN-depth scale divided by the network's estimated scale factor. plane_inliers: road-plane
            inliers. camera_height_fit: the fitted camera height in metres (triangulated: at the scale used; depth:
            the network's own road height).
        camera_height: the camera height (metres) the road observations used (given or estimated; None: none).
        camera_height_unavailable: why there is no camera height on this frame (an own video's first frames, no
            steady road in view): the scale is then the depth network's alone.
        scale_homography: the photometric road scale (``tracker.road_alignment``): the camera height over the
            road's distance in the unit translation's unit. road_alignment_cost: its 1 - ZNCC at the optimum.
        scale_temporal: this pair's length from the three-frame relative scale (``tracker.scale.temporal``).
        scale_predicted: the temporal filter's prediction before this frame's observations. cnn_bias: the
            estimated scale factor of the depth network (with the camera height).
        scale_source: what the E-tracker's scale came from (``cnn``, ``height``, ``temporal``, ``+``-joined, or
            ``prediction`` when every observation failed), with rejected observations after ``|rejected:``.
        gate_rejected: a plausibility gate rejected a tracker's result on this frame (reason in fallback_reason).
        pnp_success: PnP's result (None when PnP did not run).
        homography_motion: the E-tracker's R and direction came from the homography's decomposition (a planar scene,
            ``tracker.model_selection.planar=homography``).
        off_axis_deg: the angle (degrees, 0-90) between the first translation a tracker measured on this frame
            (accepted or not) and the optical axis, when the image moved ``tracker.motion_auto.min_parallax_px`` or
            more beyond the rotation (None: not measured): what ``tracker.motion=auto`` judges from.
        elevation_deg: the same translation's angle (degrees, 0-90) to the camera's horizontal plane (x-z): what
            ``tracker.motion=auto`` revises a car's verdict from.
        selection_failed: too few consistent correspondences (constant motion).
        selection_max_inconsistency: the forward-backward bound (pixels) the correspondences were selected under
            when the pair failed the selection at ``tracker.correspondence.max_inconsistency`` and passed at a
            relaxed one (``relaxed_inconsistency``); None: selected as usual.
        fallback_reason: why the E-tracker's result was not used (None when it was), including the plausibility gates'
            reasons; on an E frame whose scale is the temporal filter's prediction, why.
        window_tracks: tracks in the sliding-window refinement of this step (``tracker.window``; None: not run).
        window_length_ratio: the refined step's length over the tracker's (None: the step was not refined).
        window_rejected: why the window did not refine this step (too few tracks, a refinement beyond its limits).
        time_selection, time_e_tracker, time_sequential: seconds spent on this frame by each tracker stage.
    """

    frame: int
    tracker: TrackerUsed | None = None
    num_correspondences: int = 0
    num_inliers: int = 0
    gric_e: float | None = None
    gric_h: float | None = None
    cheirality_fraction: float | None = None
    parallax_px: float | None = None
    scale: float | None = None
    scale_iterations: int | None = None
    scale_cnn: float | None = None
    scale_height: float | None = None
    plane_inliers: int | None = None
    camera_height_fit: float | None = None
    camera_height: float | None = None
    camera_height_unavailable: str | None = None
    scale_homography: float | None = None
    road_alignment_cost: float | None = None
    scale_temporal: float | None = None
    scale_predicted: float | None = None
    cnn_bias: float | None = None
    scale_source: str | None = None
    gate_rejected: bool = False
    pnp_success: bool | None = None
    homography_motion: bool = False
    off_axis_deg: float | None = None
    elevation_deg: float | None = None
    selection_failed: bool = False
    selection_max_inconsistency: float | None = None
    fallback_reason: str | None = None
    window_tracks: int | None = None
    window_length_ratio: float | None = None
    window_rejected: str | None = None
    time_selection: float = 0.0
    time_e_tracker: float = 0.0
    time_sequential: float = 0.0

    @property
    def constant_motion(self) -> bool:
        """The frame repeated the previous motion (no tracker gave a pose)."""
        return self.tracker == TrackerUsed.constant_motion

    @property
    def pnp_failed(self) -> bool:
        """PnP ran and failed."""
        return self.pnp_success is False

    def add_reason(self, reason: str) -> None:
        """Append ``reason`` to ``fallback_reason`` ("; "-separated)."""
        self.fallback_reason = f"{self.fallback_reason}; {reason}" if self.fallback_reason else reason

    def as_row(self) -> dict[str, Any]:
        """A flat dict of every field plus ``constant_motion`` and ``pnp_failed`` (enums as their values)."""
        row = {f.name: getattr(self, f.name) for f in fields(self)}
        row["tracker"] = self.tracker.value if self.tracker is not None else None
        row["constant_motion"] = self.constant_motion
        row["pnp_failed"] = self.pnp_failed
        return row


DIAGNOSTIC_FIELDS = [f.name for f in fields(FrameDiagnostics)] + ["constant_motion", "pnp_failed"]
