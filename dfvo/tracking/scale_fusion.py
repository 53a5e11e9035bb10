"""The odometry loop's scale state: observations of each E-tracked pair's scale and what carries to the next frame.

Per E-tracked frame (:meth:`ScaleFusion.estimate`): the CNN-depth scale (given), the camera-height scale from the
road plane among the triangulated points (``tracker.scale.camera_height``), the three-frame relative scale
(``tracker.scale.temporal``), fused by :class:`dfvo.tracking.scale_filter.ScaleFilter`. After the frame's pose is
decided (:meth:`ScaleFusion.end_frame`): the filter keeps the length used, and the pair's metric depths in its later
image are kept for the next frame's relative scale. The plausibility gates' expected length is the median of the
last ``gate.length_window`` tracked (not constant-motion) translation lengths (:attr:`ScaleFusion.expected_length`),
their expected direction the last one's; the limits they are judged by widen with the sequence's own frame-to-frame
changes (:class:`dfvo.tracking.gates.MotionSpread`, :attr:`ScaleFusion.motion`).

Convention:
    One frame (B=1) at a time, in sequence order: ``R`` (1,3,3), ``t`` (1,3) unit ``T_cur_prev``; pixels (1,N,2)
    of the earlier (``pts_prev``) and later (``pts_cur``) image; ``rows`` (1,N) bool; ``K`` (1,3,3); flow (1,2,H,W)
    prev->cur and inconsistency (1,1,H,W) in pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch

from dfvo.geometry.two_view import normalise_points
from dfvo.matching.pyramid_refinement import PyramidRefinementConfig
from dfvo.tracking.camera_height import CameraHeight
from dfvo.tracking.config import RoadPoints, TrackerConfig
from dfvo.tracking.diagnostics import FrameDiagnostics, TrackerUsed
from dfvo.tracking.gates import MotionSpread
from dfvo.tracking.ground_plane import fit_road_plane, parallax_deg, road_candidates, road_grid
from dfvo.tracking.road_scale import align_road
from dfvo.tracking.scale import triangulated_depths
from dfvo.tracking.scale_filter import FilterState, ScaleEstimate, ScaleFilter
from dfvo.tracking.temporal_scale import MiddleDepths, middle_depths, relative_scale

__all__ = ["HeightObservation", "camera_height_scale", "depth_road_height", "ScaleFusion"]


@dataclass
class HeightObservation:
    """The camera-height scale of one frame: ``scale`` (None when the plane fit failed), ``height_unit`` (the
    fitted height in the points' unit), ``inliers`` (plane inliers), ``normal`` (3,) the plane's unit normal (down)
    in the camera frame (None when the fit failed)."""

    scale: float | None
    height_unit: float | None
    inliers: int
    normal: torch.Tensor | None = None


def camera_height_scale(R: torch.Tensor, t: torch.Tensor, K: torch.Tensor, pts_prev: torch.Tensor,
                        pts_cur: torch.Tensor, rows: torch.Tensor, image_hw: tuple[int, int], cfg: TrackerConfig,
                        generator: torch.Generator | None, camera_height: float) -> HeightObservation:
    """``camera_height / fitted height`` of the road plane among the rows' points triangulated with the unit pose
    (see :mod:`dfvo.tracking.ground_plane`); settings ``cfg.road_plane``, ``camera_height`` in metres."""
    rp = cfg.road_plane
    z_i, _, front = triangulated_depths(R, t, K, pts_prev, pts_cur)
    x = normalise_points(pts_prev.to(torch.float64), K.to(torch.float64))
    X = torch.cat([x, torch.ones_like(x[..., :1])], -1) * z_i[..., None]
    H, W = image_hw
    cand = rows & front & road_candidates(pts_prev, H, W, rp.min_row_fraction, rp.max_col_offset_fraction,
                                          rp.max_row_fraction)
    cand = cand & (parallax_deg(X, t.to(torch.float64), R.to(torch.float64)) >= rp.min_parallax_deg)
    plane = fit_road_plane(X, cand, threshold=rp.threshold, max_tilt_deg=rp.max_tilt_deg, min_inliers=rp.min_inliers,
                           trials=rp.trials, quantile=rp.quantile,
                           generators=None if generator is None else [generator])
    if not bool(plane.success[0]):
        return HeightObservation(None, None, int(plane.num_inliers[0]))
    h = float(plane.height[0])
    return HeightObservation(float(camera_height) / h, h, int(plane.num_inliers[0]), plane.normal[0])


def depth_road_height(depth: torch.Tensor, K: torch.Tensor, cfg: TrackerConfig,
                      generator: torch.Generator | None, camera_height: float | None = None) -> HeightObservation:
    """The camera height above the road plane of the depth network's own points (depth (1,1,H,W) metres of the
    earlier frame, K (1,3,3)) on a grid of the road band; ``scale`` is ``fitted height / camera_height``: the
    network's scale factor near the road (1 when its road is metric; None without ``camera_height``)."""
    rp = cfg.road_plane
    H, W = depth.shape[-2:]
    px = road_grid(H, W, rp.min_row_fraction, rp.max_row_fraction, rp.max_col_offset_fraction, rp.grid_step)
    z = depth[0, 0][px[:, 1].long(), px[:, 0].long()].to(torch.float64)
    x = normalise_points(px[None], K.to(torch.float64))
    X = torch.cat([x, torch.ones_like(x[..., :1])], -1) * z[None, :, None]
    ok = (z > 0) & torch.isfinite(z) & (z <= cfg.scale.max_depth)
    plane = fit_road_plane(X, ok[None], threshold=rp.threshold, max_tilt_deg=rp.max_tilt_deg,
                           min_inliers=rp.min_inliers, trials=rp.trials, quantile=rp.quantile,
                           generators=None if generator is None else [generator])
    if not bool(plane.success[0]):
        return HeightObservation(None, None, int(plane.num_inliers[0]))
    h = float(plane.height[0])
    return HeightObservation(None if camera_height is None else h / float(camera_height), h,
                             int(plane.num_inliers[0]), plane.normal[0])


class ScaleFusion:
    """Scale observations and the state carried between frames (see the module docstring)."""

    def __init__(self, cfg: TrackerConfig, point_refinement: PyramidRefinementConfig | None = None) -> None:
        self.cfg = cfg
        self.point_refinement = point_refinement  # the pyramid LK of ``scale_filter.refine_points`` (None: defaults)
        sc, sf = cfg.scale, cfg.scale_filter
        self.camera_height = CameraHeight(sc.camera_height, cfg.camera_height)
        self.filter = ScaleFilter.from_config(sf, temporal=sc.temporal, height_log_std=cfg.road_plane.log_std)
        self.motion = MotionSpread(cfg.gate)  # the sequence's own changes of motion: the gates' widened limits
        self.reset()

    def reset(self) -> None:
        """Forget everything (a new sequence)."""
        self.filter.state = None
        self.filter.reset()
        self.middle: MiddleDepths | None = None
        self.expected_length: float | None = None
        self.expectation_settled = False
        self._recent: list[float] = []
        self.expected_direction: torch.Tensor | None = None
        self.rejections = 0
        self.gated_directions: list[torch.Tensor] = []  # rejected by the direction gate, consecutive frames
        self.gated_lengths: list[float] = []  # rejected by the length gate, consecutive frames
        self.motion.reset()
        self._height_unit: float | None = None
        self._prior = FilterState()
        self._height_observed = False
        self.camera_height.reset()

    @property
    def uses_fusion(self) -> bool:
        """Anything beyond the CNN-depth scale is on."""
        return self.camera_height.enabled or self.cfg.scale.temporal

    def estimate(self, R: torch.Tensor, t: torch.Tensor, cnn_scale: float | None, pts_prev: torch.Tensor,
                 pts_cur: torch.Tensor, rows: torch.Tensor, K: torch.Tensor, flow: torch.Tensor,
                 inconsistency: torch.Tensor, depth: torch.Tensor, generator: torch.Generator | None,
                 diag: FrameDiagnostics, grey_pair: tuple[torch.Tensor, torch.Tensor] | None = None) -> ScaleEstimate:
        """This frame's fused scale from its observations (``R`` (1,3,3), unit ``t`` (1,3) of ``T_cur_prev``;
        ``depth`` (1,1,H,W): the earlier frame's CNN depth, for the road plane; ``grey_pair``: the earlier and later
        grey images (1,1,H,W) for the photometric road scale, None: not used); fills the scale fields of ``diag``."""
        cfg, sf = self.cfg, self.cfg.scale_filter
        diag.scale_cnn = cnn_scale
        temporal_scale, temporal_std = None, None
        if cfg.scale.temporal:
            rel = relative_scale(self.middle, flow, inconsistency, K, R, t, max_inconsistency=sf.max_inconsistency,
                                 min_parallax_deg=sf.min_parallax_deg, min_points=sf.min_points,
                                 grey_pair=grey_pair if sf.refine_points else None,
                                 point_refinement=self.point_refinement)
            temporal_scale, temporal_std = rel.scale, rel.log_std
            if temporal_std is not None and sf.temporal_rotation_log_std > 0:
                # the relative scale re-triangulates the previous pair's points with this pair's pose: its error
                # grows with the rotation (turns), which the points' own spread does not show
                angle = math.degrees(math.acos(max(-1.0, min(1.0, (float(R[0].trace()) - 1) / 2))))
                temporal_std = math.hypot(temporal_std, sf.temporal_rotation_log_std * angle)
            diag.scale_temporal = temporal_scale
        height, road_bias, homography = None, None, None
        self._height_unit = None
        network_plane = None
        ra = cfg.road_alignment
        needs_plane = (self.camera_height.given is None or cfg.road_plane.points == RoadPoints.depth
                       or (ra.enabled and grey_pair is not None))
        if self.camera_height.enabled and needs_plane:
            network_plane = depth_road_height(depth, K, cfg, generator)  # the network's road, metres
            if self.camera_height.given is None and not self._height_observed:  # once per frame (E, then PnP)
                self.camera_height.observe(network_plane.height_unit)
                self._height_observed = True
            diag.plane_inliers = network_plane.inliers
            if network_plane.height_unit is not None:
                diag.camera_height_fit = network_plane.height_unit
        h_m = self.camera_height.value
        diag.camera_height = h_m
        if h_m is None and self.camera_height.enabled:  # flagged per frame: the scale is the depth network's alone
            diag.camera_height_unavailable = self.camera_height.unavailable_reason
        if (h_m is not None and cfg.road_plane.points == RoadPoints.depth and network_plane is not None
                and network_plane.height_unit is not None):
            road_bias = network_plane.height_unit / h_m
        elif h_m is not None and cfg.road_plane.points == RoadPoints.triangulated:
            obs = camera_height_scale(R, t, K, pts_prev, pts_cur, rows, tuple(flow.shape[-2:]), cfg, generator, h_m)
            height, diag.plane_inliers = obs.scale, obs.inliers
            diag.scale_height = height
            self._height_unit = obs.height_unit
        prior = self.filter.prior(temporal_scale, temporal_std)
        if (ra.enabled and h_m is not None and grey_pair is not None and network_plane is not None
                and network_plane.normal is not None):
            # the expected travel moves the patch ahead: the filter's prediction, or before it knows a scale the
            # network's own (its bias unknown: searched 2x either way of it, then the whole range as before); a patch
            # not moved ahead left one road block in view at 3.6 m a frame (KITTI 06 every third frame, docs/scale.md)
            travel = math.exp(prior.x) if prior.known else cnn_scale
            expected = h_m / travel if travel is not None and travel > 0 and math.isfinite(travel) else None
            # the patch is placed on the network's road, or at the camera height in metres (given or estimated) when
            # the network's road is implausibly far from it (a network of another scale: its patch would miss the
            # road ahead; docs/scale.md)
            placed = float(network_plane.height_unit)
            if not (math.isfinite(placed) and 1.0 / ra.max_height_ratio <= placed / h_m <= ra.max_height_ratio):
                placed = float(h_m)
            found = align_road(grey_pair[0], grey_pair[1], K[0], R[0], t[0], network_plane.normal, placed, ra,
                               expected)
            diag.road_alignment_cost = found.cost
            if found.unit_height is not None:
                homography = h_m / found.unit_height
                diag.scale_homography = homography
        if road_bias is not None or height is not None or homography is not None:
            # an observation of the metric scale other than the network's own: its bias is observable from now on
            # (without one it is not, and a wrong frame's CNN scale would stay in it for the rest of the run)
            prior = self.filter.start_bias_estimate(prior)
        est = self.filter.estimate(prior, cnn_scale, height, road_bias,
                                   temporal_used=temporal_scale is not None and self.filter.state.known,
                                   homography=homography, homography_log_std=ra.log_std)
        if road_bias is not None and cnn_scale is not None:
            diag.scale_height = cnn_scale / est.bias  # the CNN-depth scale corrected by the estimated factor
        diag.scale_predicted = est.predicted
        if self.camera_height.enabled:
            diag.cnn_bias = est.bias
        diag.scale_source = est.source + (f"|rejected:{'+'.join(est.rejected)}" if est.rejected else "")
        if h_m is not None and est.scale is not None and self._height_unit is not None:
            diag.camera_height_fit = self._height_unit * est.scale
        self._prior = prior
        return est

    def end_frame(self, T_cur_prev: torch.Tensor | None, T_prev_cur: torch.Tensor, tracker: TrackerUsed | None,
                  estimate: ScaleEstimate | None, pts_prev: torch.Tensor, pts_cur: torch.Tensor, rows: torch.Tensor,
                  K: torch.Tensor, parallax_px: float | None = None) -> None:
        """After the frame's pose: ``T_cur_prev`` (4,4) tracked (None: constant motion), ``T_prev_cur`` the motion
        used; ``estimate`` the fused scale when the E-tracker's pose was used with it; rows (N,) of (N,2) pixels;
        ``parallax_px`` the image's motion beyond the rotation (None: unknown; tells a stop for the gates' spread)."""
        self._height_observed = False
        length = float(T_prev_cur[:3, 3].norm())
        if tracker in (TrackerUsed.essential, TrackerUsed.pnp) and estimate is not None and estimate.scale is not None:
            self.filter.commit(estimate.state if abs(estimate.scale - length) <= 1e-9 * max(1.0, length)
                               else self._state_at(length), estimate.all_rejected)
        elif tracker == TrackerUsed.constant_motion:
            prior = self.filter.prior()
            self.filter.commit_length(length, prior.pxx ** 0.5 if prior.known else 1e3, prior)
        else:
            self.filter.commit_length(length, self.cfg.scale_filter.cnn_log_std, self.filter.prior())
        self.motion.add(length if T_cur_prev is not None else None,
                        T_prev_cur[:3, 3] / length if T_cur_prev is not None and length > 0 else None, parallax_px)
        if T_cur_prev is not None:
            self._recent = (self._recent + [length])[-int(self.cfg.gate.length_window):]
            # median of the last tracked lengths; until the window is full the gate judges it with its wider warm-up
            # ratio, so one wrong first length (the network's scale before anything else is known) cannot make the
            # correct lengths after it "implausible", while an absurd one is still caught
            self.expected_length = sorted(self._recent)[len(self._recent) // 2]
            self.expectation_settled = len(self._recent) >= int(self.cfg.gate.length_window)
            self.expected_direction = T_prev_cur[:3, 3] / length if length > self.cfg.gate.stop_length else None
        self.middle = None
        if T_cur_prev is not None and self.cfg.scale.temporal and length >= self.cfg.scale_filter.min_length:
            self.middle = middle_depths(T_cur_prev, K, pts_prev, pts_cur, rows, self.cfg.scale_filter.min_parallax_deg)

    def expect_lengths(self, lengths: list[float]) -> None:
        """A new pace confirmed by consecutive frames (``gate.confirm_length_frames``): the gate's expected length
        restarts from ``lengths`` (metres; :meth:`end_frame` then adds this frame's), as a sequence's first frames
        (its warm-up ratio until ``gate.length_window`` lengths are known)."""
        self._recent = [float(v) for v in lengths][-int(self.cfg.gate.length_window):]

    def forget_motion(self) -> None:
        """After a result accepted against the gates (it may be wrong itself): the gates judge the next frame by no
        expectation, the filter forgets the scale, the CNN bias estimate is the one from before this frame (the
        result's own CNN scale is not learnt) and no relative scale is taken from this frame's points."""
        self.expected_length, self.expected_direction, self._recent = None, None, []
        self.expectation_settled = False
        self.filter.reset(bias_from=self._prior)
        self.middle = None

    def _state_at(self, length: float) -> FilterState:
        """The prior with its scale moved to ``length`` (the frame used the prediction instead of the posterior)."""
        p = self._prior
        return replace(p, x=math.log(max(length, 1e-12))) if p.known else p
