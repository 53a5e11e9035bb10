"""The DF-VO odometry loop: streaming ``step`` and batched ``run`` with identical results.

Convention:
    Pairs are (prev=i, cur=j): ``flow_fwd`` i->j and ``flow_bwd`` j->i (B,2,H,W) in pixels, ``depth`` of frame
    i (B,1,H,W) in metres (and ``depth_next`` of frame j, needed when ``tracker.scale.depth_views=2``), intrinsics
    ``K`` (B,3,3). Trackers estimate ``T_cur_prev`` (prev points into the
    current camera); the loop returns ``T_prev_cur = inv(T_cur_prev)`` and accumulates
    ``T_w_cur = T_w_prev @ T_prev_cur`` from ``T_w_0 = I``. Poses are float64.

Fallback order per frame (paper): (1) correspondence selection fails -> constant motion (the previous
``T_prev_cur``; identity at the start); (2) E invalid (too few rows, GRIC prefers H, cheirality) or the scale
fails -> PnP (tracker="hybrid"; tracker="e" falls back to constant motion); (3) otherwise R from E and
``t = s * t_unit``. With ``tracker.model_selection.planar=homography`` a pair GRIC gives to H tries the homography's
decomposition first (R and the direction, scaled as in (3)), then PnP. When PnP itself fails the frame also uses
constant motion (the official code used identity).

Our additions, each one switch away from the paper: the scale ``s`` may fuse the CNN-depth scale with the
camera-height prior and, over time, the three-frame relative scale (:mod:`dfvo.tracking.scale_fusion`;
``tracker.scale.camera_height``, ``tracker.scale.temporal``); with the temporal filter a frame whose scale
observations all fail keeps the filter's prediction (``scale_source="prediction"``) instead of going to PnP. The
plausibility gates (:mod:`dfvo.tracking.gates`, ``tracker.gate.enabled``) reject an E or PnP result with too few
inliers, a translation far longer or shorter than the previous frame's, or one whose direction turns too far; E
then falls to PnP (hybrid), PnP to constant motion, flagged in ``fallback_reason`` and ``gate_rejected``.
With ``tracker.window.enabled`` (opt-in) the step each frame emits is a sliding-window bundle adjustment's
refinement of the tracker's step (:mod:`dfvo.tracking.window_refinement`); the tracker's own state keeps its step.

Batched == streaming: the selection, E/H RANSAC, GRIC and simple scale run on the whole batch; frame k of the
sequence always draws from ``torch.Generator().manual_seed(cfg.seed + k)``; the iterative scale, PnP, the scale
fusion (its filter state, the previous pair's middle-frame depths, the gates' expected motion) and the pose
composition run frame by frame in order. ``run`` is causal like ``step`` (no smoothing over the sequence), so both
give the same poses whatever the batch size.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field, replace
from functools import cached_property

import torch
from kornia.color import rgb_to_grayscale
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE

from dfvo.geometry.se3 import pose_from_rt, se3_inverse
from dfvo.geometry.two_view import decompose_essential, find_essential_ransac, normalised_rays
from dfvo.matching.consistency import forward_backward_inconsistency
from dfvo.matching.flow_refinement import FlowRefinementConfig
from dfvo.matching.image_ops import shi_tomasi
from dfvo.matching.pyramid_refinement import PyramidRefinementConfig
from dfvo.matching.selection import select_correspondences
from dfvo.tracking.config import PlanarMotion, ScaleMethod, TrackerConfig, TrackerMode
from dfvo.tracking.covariance import length_log_variance, step_covariance
from dfvo.tracking.diagnostics import FrameDiagnostics, TrackerUsed
from dfvo.tracking.e_tracker import ETrackerResult, essential_scale, track_essential
from dfvo.tracking.gates import angle_deg, check_direction, check_length, check_support, image_parallax_px
from dfvo.tracking.motion_model import MotionJudge
from dfvo.tracking.pnp_tracker import track_pnp
from dfvo.tracking.scale import has_depth, iterative_scale, sample_depth
from dfvo.tracking.scale_filter import ScaleEstimate
from dfvo.tracking.scale_fusion import ScaleFusion
from dfvo.tracking.window_refinement import WindowRefiner

__all__ = ["FrameMatches", "FrameResult", "VisualOdometry"]

_REFINE = FlowRefinementConfig()  # its window and smoothing score the texture of tracker.correspondence.min_texture


@dataclass
class FrameMatches:
    """The correspondences a frame was tracked with: ``pts_prev``/``pts_cur`` (N,2) pixels of the selected rows and
    ``inliers`` (N,) bool of the model used (None when no model was fitted)."""

    pts_prev: torch.Tensor
    pts_cur: torch.Tensor
    inliers: torch.Tensor | None = None


@dataclass
class FrameResult:
    """One tracked frame: ``T_w_cur`` (4,4), ``T_prev_cur`` (4,4) float64, its :class:`FrameDiagnostics`, the
    :class:`FrameMatches` it used and ``covariance`` (6,6) float64 of ``T_prev_cur``'s error (order and frame:
    :mod:`dfvo.tracking.covariance`)."""

    T_w_cur: torch.Tensor
    T_prev_cur: torch.Tensor
    diagnostics: FrameDiagnostics
    matches: FrameMatches | None = None
    covariance: torch.Tensor | None = None


@dataclass
class FrameState:
    """One frame's working state inside :class:`VisualOdometry`: what its batch computed for it (batch size 1
    slices of pair b) and what the frame decides while it is finished. Passed explicitly to the private steps, so
    no per-frame value lives on the tracker between calls.

    Attributes:
        pts_prev, pts_cur: (1,N,2) float64 pixels of the padded correspondences; mask: (1,N) bool real rows.
        selection_failed, selection_reason: the correspondence selection's verdict on this pair.
        depth: (1,1,H,W) metres of the earlier frame; depth_next: (1,1,H,W) of the later frame (two-view scale) or
            None. K: (1,3,3) float64 intrinsics. flow: (1,2,H,W) forward flow, inconsistency: (1,1,H,W) its
            forward-backward inconsistency in pixels.
        generator: this frame's seeded generator (``cfg.seed + frame index``).
        essential: the E-tracker's result for this pair (None with ``tracker=pnp``); scale, scale_ok: its simple
            scale from CNN depth and whether it succeeded (None with ``tracker=pnp``).
        grey_pair: the pair's grey images (1,1,H,W) each, for the photometric road scale (None: not given).
        diagnostics: the frame's record, filled as it is decided.
        estimate: the fused scale the E pose used (None: no fusion, or not an E pose).
        gate_overruled: a gate's rejection was overruled (after ``gate.max_consecutive`` gated frames in a row).
        gated_direction: the direction (3,) of this frame's result that the direction gate rejected (None: none).
        rejected_directions: the directions (3,) of this frame's results that were rejected, by tracker: ``E``'s by
            the direction gate (a rejection that stands), ``PnP``'s by the direction or the length gate (not by its
            support).
        direction_confirmed: PnP's result confirmed E's rejected turn (``gate.confirm_direction_by_pnp_deg``): the
            retry's E direction is accepted if it agrees with PnP's too.
        gated_length: the length (metres) of this frame's first result that the length gate rejected (None: none).
        confirmed_lengths: the earlier frames' rejected lengths that this frame's length confirmed
            (``confirm_length_frames``): the gate's expectation restarts from them and this frame's length, when the
            frame's pose is the result of the tracker that confirmed them (``confirmed_by``: ``E`` or ``PnP``).
        measured_direction: the first translation direction (3,) a tracker measured on this frame, accepted or not
            (what ``tracker.motion=auto`` judges from); measured_parallax: the image's median motion (pixels) beyond
            that result's rotation where no E-tracker ran (``tracker.mode=pnp``; else E's parallax is used).
    """

    pts_prev: torch.Tensor
    pts_cur: torch.Tensor
    mask: torch.Tensor
    selection_failed: bool
    selection_reason: str | None
    depth: torch.Tensor
    depth_next: torch.Tensor | None
    K: torch.Tensor
    flow: torch.Tensor
    inconsistency: torch.Tensor
    generator: torch.Generator
    essential: ETrackerResult | None
    scale: float | None
    scale_ok: bool | None
    grey_pair: tuple[torch.Tensor, torch.Tensor] | None
    diagnostics: FrameDiagnostics
    estimate: ScaleEstimate | None = None
    gate_overruled: bool = False
    gated_direction: torch.Tensor | None = None
    rejected_directions: dict[str, torch.Tensor] = field(default_factory=dict)
    direction_confirmed: bool = False
    gated_length: float | None = None
    confirmed_lengths: list[float] | None = None
    confirmed_by: str | None = None
    measured_direction: torch.Tensor | None = None
    measured_parallax: float | None = None

    @property
    def rows(self) -> torch.Tensor:
        """(N,) bool: the real correspondence rows."""
        return self.mask[0]

    @cached_property
    def pnp_backwards(self) -> bool:
        """The earlier frame has no depth but the later one has (``depth.every``): PnP lifts the later frame's
        points and inverts its pose."""
        return not has_depth(self.depth) and has_depth(self.depth_next)

    @property
    def plane_depth(self) -> torch.Tensor:
        """(1,1,H,W) the depth the network's road plane is fitted to: the earlier frame's, or the later frame's when
        only that one has depth (the road lies the same way below the camera one frame on)."""
        return self.depth_next if self.pnp_backwards else self.depth


class VisualOdometry:
    """Monocular visual odometry from flows and depths (see the module docstring for conventions).

    Args:
        cfg: :class:`TrackerConfig` (official defaults when omitted).
        point_refinement: the pyramidal Lucas–Kanade settings of ``tracker.scale_filter.refine_points`` (infer.py
            passes the flow refinement's, ``flow.refine.pyramid``); None: their defaults.
    """

    def __init__(self, cfg: TrackerConfig | None = None,
                 point_refinement: PyramidRefinementConfig | None = None) -> None:
        self.cfg = cfg if cfg is not None else TrackerConfig()
        self.point_refinement = point_refinement
        self._warned_texture = False
        self.reset()

    def reset(self) -> None:
        """Forget the trajectory: the next frame starts at identity, frame counter 0, no motion model."""
        self.frame = 0
        self.T_w = torch.eye(4, dtype=torch.float64)
        self.last_motion = torch.eye(4, dtype=torch.float64)
        self.last_scale = 0.0
        self.plane_normal: torch.Tensor | None = None  # (3,) the last homography frame's plane, in its later camera
        if (getattr(self, "fusion", None) is None or self.fusion.cfg is not self.cfg
                or self.fusion.point_refinement is not self.point_refinement):
            self.fusion = ScaleFusion(self.cfg, self.point_refinement)
        self.fusion.reset()
        self.motion = MotionJudge(self.cfg)  # the motion model in force (tracker.motion; auto: judged)
        w = self.cfg.window
        self.window = (WindowRefiner(w, self.cfg.covariance.inflation, self.cfg.scale.max_depth,
                                     self.cfg.scale.depth_crop_top) if w.enabled else None)

    # ------------------------------------------------------------------------------------------ public
    def step(self, flow_fwd: torch.Tensor, flow_bwd: torch.Tensor, depth_prev: torch.Tensor,
             K: torch.Tensor, depth_cur: torch.Tensor | None = None, image_prev: torch.Tensor | None = None,
             image_cur: torch.Tensor | None = None) -> FrameResult:
        """Track one new frame: flows (1,2,H,W) prev->cur and cur->prev, depth (1,1,H,W) of prev, K (1,3,3);
        ``depth_cur`` (1,1,H,W) of cur when ``scale_depth_views=2``; the two images (1,C,H,W) in [0,1] for the
        photometric road scale (``tracker.road_alignment``; without them it is not used)."""
        KORNIA_CHECK(flow_fwd.shape[0] == 1, f"VisualOdometry.step takes one pair (B=1); got flow_fwd "
                                             f"{tuple(flow_fwd.shape)} (use run for batches)")
        images = None if image_prev is None or image_cur is None else torch.cat([image_prev, image_cur])
        return self._batch(flow_fwd, flow_bwd, depth_prev, K.reshape(1, 3, 3), depth_cur, images)[0]

    def run(self, flows_fwd: torch.Tensor, flows_bwd: torch.Tensor, depths: torch.Tensor, K: torch.Tensor,
            batch_size: int = 8, depths_next: torch.Tensor | None = None,
            images: torch.Tensor | None = None) -> list[FrameResult]:
        """Track a whole sequence: (N-1,2,H,W) flows, (N-1,1,H,W) depths of the earlier frame of each pair,
        K (3,3) or (N-1,3,3); ``depths_next`` (N-1,1,H,W) of the later frame of each pair when
        ``scale_depth_views=2``; ``images`` (N,C,H,W) in [0,1], the frames themselves (for the photometric road
        scale). Returns N-1 results (frame 0 is identity), identical to calling :meth:`step`."""
        KORNIA_CHECK_SHAPE(flows_fwd, ["M", "2", "H", "W"])
        M = flows_fwd.shape[0]
        Ks = K.reshape(1, 3, 3).expand(M, 3, 3) if K.dim() == 2 else K
        KORNIA_CHECK(Ks.shape == (M, 3, 3), f"VisualOdometry.run: K {tuple(K.shape)}; expected (3,3) or ({M},3,3)")
        out: list[FrameResult] = []
        for s in range(0, M, max(1, int(batch_size))):
            e = min(M, s + max(1, int(batch_size)))
            out.extend(self._batch(flows_fwd[s:e], flows_bwd[s:e], depths[s:e], Ks[s:e],
                                   None if depths_next is None else depths_next[s:e],
                                   None if images is None else images[s:e + 1]))
        return out

    # ------------------------------------------------------------------------------------------ internals
    def _batch(self, flow_fwd: torch.Tensor, flow_bwd: torch.Tensor, depth: torch.Tensor,
               K: torch.Tensor, depth_next: torch.Tensor | None = None,
               images: torch.Tensor | None = None) -> list[FrameResult]:
        cfg = self.cfg
        KORNIA_CHECK_SHAPE(flow_fwd, ["B", "2", "H", "W"])
        KORNIA_CHECK_SHAPE(flow_bwd, ["B", "2", "H", "W"])
        KORNIA_CHECK_SHAPE(depth, ["B", "1", "H", "W"])
        KORNIA_CHECK_SHAPE(K, ["B", "3", "3"])
        B = flow_fwd.shape[0]
        same = depth.shape[0] == B and depth.shape[-2:] == flow_fwd.shape[-2:] and K.shape[0] == B
        KORNIA_CHECK(flow_bwd.shape == flow_fwd.shape and same,
                     f"VisualOdometry: flow_fwd {tuple(flow_fwd.shape)}, flow_bwd "
                     f"{tuple(flow_bwd.shape)}, depth {tuple(depth.shape)}, K {tuple(K.shape)} must share B, H, W")
        if cfg.scale.depth_views == 2 and cfg.mode != TrackerMode.pnp:  # PnP uses the earlier frame's depth only
            if depth_next is None or depth_next.shape != depth.shape:
                raise ValueError(f"VisualOdometry: tracker.scale.depth_views=2 needs the later frame's depth of each "
                                 f"pair (run(depths_next=...) / step(depth_cur=...)) shaped like depth "
                                 f"{tuple(depth.shape)}; got {None if depth_next is None else tuple(depth_next.shape)}")
        else:
            depth_next = None  # the paper's one-view scale: a given next depth is not used
        KORNIA_CHECK(images is None or (images.shape[0] == B + 1 and images.shape[-2:] == flow_fwd.shape[-2:]),
                     f"VisualOdometry: images {None if images is None else tuple(images.shape)}; expected "
                     f"({B + 1},C,{flow_fwd.shape[-2]},{flow_fwd.shape[-1]}): the frames of the {B} pairs")
        grey = None
        if images is not None and cfg.road_alignment.enabled:
            grey = images.to(torch.float32)
            grey = rgb_to_grayscale(grey) if grey.shape[1] == 3 else grey
        gens = [torch.Generator().manual_seed(cfg.seed + self.frame + b) for b in range(B)]
        t0 = time.perf_counter()
        sel = cfg.correspondence
        incon = forward_backward_inconsistency(flow_fwd, flow_bwd)
        min_texture = sel.min_texture if images is not None else 0.0
        if sel.min_texture > 0 and images is None and not self._warned_texture:
            self._warned_texture = True
            warnings.warn(f"tracker.correspondence.min_texture={sel.min_texture} needs the frames (images=...); "
                          "selecting without the texture test", stacklevel=3)
        texture = shi_tomasi(images[:-1], _REFINE.window, _REFINE.sigma) if min_texture > 0 else None

        corr = select_correspondences(flow_fwd, incon, method=sel.method.value, num=sel.num_correspondences,
                                      grid=tuple(sel.grid), max_inconsistency=sel.max_inconsistency,
                                      min_valid_fraction=sel.min_valid_fraction,
                                      min_region_fraction=sel.min_region_fraction, crop_top=sel.crop_top,
                                      texture=texture, min_texture=min_texture,
                                      relaxed_inconsistency=sel.relaxed_inconsistency)
        pi, pj, mask = corr.pts_i.to(torch.float64), corr.pts_j.to(torch.float64), corr.mask
        Kd = K.to(torch.float64)
        t1 = time.perf_counter()
        e_res, scale, scale_ok = None, None, None
        if cfg.mode != TrackerMode.pnp:
            e_res = track_essential(pi, pj, mask, Kd, cfg, gens, homography=self.motion.may_use_homography)
            scale, scale_ok = essential_scale(e_res.R, e_res.t, pi, pj, mask, depth, Kd, cfg, gens, depth_next)
        t2 = time.perf_counter()
        results = []
        for b in range(B):
            tb = time.perf_counter()
            sl = slice(b, b + 1)
            state = FrameState(
                pts_prev=pi[sl], pts_cur=pj[sl], mask=mask[sl], selection_failed=bool(corr.failed[b]),
                selection_reason=corr.reasons[b], depth=depth[sl],
                depth_next=None if depth_next is None else depth_next[sl], K=Kd[sl], flow=flow_fwd[sl],
                inconsistency=incon[sl], generator=gens[b], essential=None if e_res is None else e_res.pair(b),
                scale=None if scale is None else float(scale[b]),
                scale_ok=None if scale_ok is None else bool(scale_ok[b]),
                grey_pair=None if grey is None else (grey[b:b + 1], grey[b + 1:b + 2]),
                diagnostics=FrameDiagnostics(frame=self.frame + 1, num_correspondences=int(mask[b].sum()),
                                             selection_failed=bool(corr.failed[b]),
                                             selection_max_inconsistency=corr.relaxed_bound[b]))
            res = self._finish_frame(state)
            res.diagnostics.time_selection = (t1 - t0) / B
            res.diagnostics.time_e_tracker = (t2 - t1) / B
            res.diagnostics.time_sequential = time.perf_counter() - tb
            results.append(res)
        return results

    def _finish_frame(self, st: FrameState) -> FrameResult:
        """Decide the frame's pose (E, PnP or constant motion), advance the trajectory and the scale fusion."""
        cfg = self.cfg
        diag, e_res = st.diagnostics, st.essential
        if e_res is not None:
            gric_e, gric_h = float(e_res.gric_e[0]), float(e_res.gric_h[0])
            diag.gric_e = gric_e if gric_e == gric_e else None  # NaN: GRIC not computed
            diag.gric_h = gric_h if gric_h == gric_h else None
            diag.cheirality_fraction = float(e_res.cheirality_fraction[0])
            parallax = float(e_res.parallax_px[0])
            diag.parallax_px = parallax if parallax == parallax else None
        T_cur_prev: torch.Tensor | None = None
        if st.selection_failed:
            diag.fallback_reason = f"selection failed: {st.selection_reason}"
        elif cfg.mode == TrackerMode.pnp:
            T_cur_prev = self._pnp(st)
        else:
            T_cur_prev, reason = self._epipolar_pose(st)
            e_res = st.essential
            if T_cur_prev is None:
                diag.add_reason(reason)
                if cfg.mode == TrackerMode.hybrid:
                    T_cur_prev = self._pnp(st)
                if T_cur_prev is None and self._trackers_agree_on_turn(st):
                    T_cur_prev, retry = self._epipolar_pose(st)
                    e_res = st.essential
                    if T_cur_prev is None and retry is not None and retry != reason:
                        diag.add_reason(retry)
        if T_cur_prev is None:
            T_prev_cur = self.last_motion.clone()
            diag.tracker = TrackerUsed.constant_motion
        else:
            T_prev_cur = se3_inverse(T_cur_prev)
        self.last_motion = T_prev_cur
        self.last_scale = float(T_prev_cur[:3, 3].norm())
        if not diag.homography_motion or T_cur_prev is None:
            self.plane_normal = None
        self.frame += 1
        rows = st.rows
        used_e = e_res is not None and diag.tracker == TrackerUsed.essential
        if diag.tracker != TrackerUsed.essential and diag.tracker != TrackerUsed.pnp:
            st.estimate = None  # an estimate of a tracker result that was not used
        # the image's motion beyond the rotation, as the length gate measures it: tells a stop from a slow step
        parallax = None if T_cur_prev is None else image_parallax_px(st.pts_prev[0][rows], st.pts_cur[0][rows],
                                                                     T_cur_prev[:3, :3], st.K[0])
        pace_confirmed = (st.confirmed_lengths is not None and T_cur_prev is not None
                          and str(diag.tracker) == st.confirmed_by)
        if pace_confirmed:  # a new pace: the gate expects it from now on
            self.fusion.expect_lengths(st.confirmed_lengths)
        self.fusion.end_frame(T_cur_prev, T_prev_cur, diag.tracker, st.estimate, st.pts_prev[0], st.pts_cur[0],
                              rows & e_res.inliers[0] if used_e else rows, st.K[0], parallax)
        gated_out = diag.gate_rejected and diag.tracker == TrackerUsed.constant_motion
        self.fusion.rejections = self.fusion.rejections + 1 if gated_out else 0
        # the directions the direction gate rejected on consecutive constant-motion frames: the last
        # confirm_direction_frames - 1 of them (a direction is only recorded when that setting is on)
        self.fusion.gated_directions = (
            [*self.fusion.gated_directions, st.gated_direction][1 - int(self.motion.settings.confirm_direction_frames):]
            if gated_out and st.gated_direction is not None else [])
        # the lengths the length gate rejected on consecutive frames, whatever each frame ended as (E may have gone
        # on with the filter's predicted length): the last confirm_length_frames - 1 of them
        n_length = self.motion.settings.confirm_length_frames
        self.fusion.gated_lengths = (
            [*self.fusion.gated_lengths, st.gated_length][1 - int(n_length):]
            if n_length and st.gated_length is not None and not pace_confirmed else [])
        if st.gate_overruled and T_cur_prev is not None:  # accepted against the gates: it may be wrong itself
            self.fusion.forget_motion()
        inliers = e_res.inliers[0][rows] if used_e else None
        matches = FrameMatches(st.pts_prev[0][rows], st.pts_cur[0][rows], inliers)
        log_var = length_log_variance(st.estimate, self.fusion._prior.pxx, self.last_scale, cfg)
        cov = step_covariance(diag.tracker, T_cur_prev, T_prev_cur, matches.pts_prev, matches.pts_cur, st.K[0],
                              st.depth, cfg, log_var, st.depth_next if st.pnp_backwards else None)
        if self.window is not None:  # the emitted step only: the tracker's state above keeps its own
            T_prev_cur = self._window_step(st, T_prev_cur, T_cur_prev is not None, cov, matches)
        measured = self.motion.observe(diag.frame, st.measured_direction,  # the next frames' motion (auto)
                                       diag.parallax_px if diag.parallax_px is not None else st.measured_parallax)
        if measured is not None:
            diag.off_axis_deg, diag.elevation_deg = measured
        self.T_w = self.T_w @ T_prev_cur
        return FrameResult(self.T_w.clone(), T_prev_cur, diag, matches, cov)

    def _window_step(self, st: FrameState, T_prev_cur: torch.Tensor, tracked: bool, cov: torch.Tensor | None,
                     matches: FrameMatches) -> torch.Tensor:
        """The step the trajectory takes with ``tracker.window``: the window's refinement of the tracker's step
        ``T_prev_cur`` (4,4), or the step itself (not refined, or the refinement rejected: noted)."""
        pts_prev, pts_cur = matches.pts_prev, matches.pts_cur
        if matches.inliers is not None:
            pts_prev, pts_cur = pts_prev[matches.inliers], pts_cur[matches.inliers]
        res = self.window.update(T_prev_cur, cov, tracked, pts_prev, pts_cur, st.flow, st.inconsistency, st.depth,
                                 st.K[0])
        diag = st.diagnostics
        diag.window_tracks = res.num_tracks or None
        diag.window_length_ratio = res.length_ratio if res.T_prev_cur is not None else None
        diag.window_rejected = res.rejected
        return T_prev_cur if res.T_prev_cur is None else res.T_prev_cur

    def _epipolar_pose(self, st: FrameState) -> tuple[torch.Tensor | None, str | None]:
        """The pose ``T_cur_prev`` (4,4) from the pair's two-view geometry: the E-tracker's, or the homography's where
        model selection prefers a plane (``model_selection.planar=homography``); or None and why not."""
        e_res, diag = st.essential, st.diagnostics
        reason = e_res.reasons[0]
        if reason is None:
            return self._essential_pose(st)
        if (e_res.homography_model is not None and self.motion.settings.planar == PlanarMotion.homography
                and reason.startswith("model selection prefers PnP (GRIC")):
            # decomposed with its batch, or now: the motion turned hand-held after the batch was tracked
            st.essential = e_res.with_homography(st.pts_prev, st.pts_cur, st.K)
            T, planar = self._homography_pose(st)
            if planar is not None:
                diag.add_reason(planar)
            return T, reason if T is None else None
        return None, reason

    def _trackers_agree_on_turn(self, st: FrameState) -> bool:
        """Whether the direction gate rejected the two-view result while PnP's result, itself rejected by a gate (its
        turn or its length, not its support), agrees with it within ``gate.confirm_direction_by_pnp_deg`` (two
        trackers, the epipolar geometry alone and the depth network's points, find the same new direction in the
        same frame: the motion turned; off by default; PnP runs in ``tracker.mode=hybrid`` only). Marks the frame so
        that the gate accepts the two-view direction on the next try if that try's direction agrees with PnP's too
        (its length is still gated)."""
        limit = self.motion.settings.confirm_direction_by_pnp_deg
        e_dir, pnp_dir = st.rejected_directions.get("E"), st.rejected_directions.get("PnP")
        if limit is None or e_dir is None or pnp_dir is None or st.direction_confirmed:
            return False
        st.direction_confirmed = angle_deg(e_dir, pnp_dir) <= limit
        return st.direction_confirmed

    def _essential_pose(self, st: FrameState, refine: bool = True) -> tuple[torch.Tensor | None, str | None]:
        """The E-tracker's pose ``T_cur_prev`` (4,4) with its scale (iterative scale, fusion, gates), or None and
        the reason it was not usable (``refine``: the iterative scale may re-estimate E; not for a homography's
        motion)."""
        cfg = self.cfg
        e_res, diag, gen = st.essential, st.diagnostics, st.generator
        pi, pj, mask, depth, K = st.pts_prev, st.pts_cur, st.mask, st.depth, st.K
        R, t = e_res.R, e_res.t
        s, ok = st.scale, st.scale_ok
        diag.num_inliers = int(e_res.num_inliers[0])
        if cfg.scale.method == ScaleMethod.iterative and refine:
            z_cnn, z_ok = sample_depth(depth, pi, cfg.scale.max_depth, cfg.scale.depth_crop_top)

            def estimate(rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
                if int(rows.sum()) <= cfg.essential.min_correspondences:
                    return R, t, torch.zeros(1, dtype=torch.float64), torch.zeros(1, dtype=torch.bool)
                r = find_essential_ransac(pi, pj, rows, K, threshold_px=cfg.essential.threshold_px,
                                          iterations=cfg.essential.iterations, repeats=cfg.essential.repeats,
                                          generators=[gen])
                R2, t2, _ = decompose_essential(r.model, K, pi, pj, rows)
                s2, ok2 = essential_scale(R2, t2, pi, pj, rows, depth, K, cfg, [gen], st.depth_next)
                return R2, t2, s2, ok2 & r.success

            R0, t0, s0 = R, t, 0.0
            if self.last_scale > 0:
                # start from the motion model (previous R and t direction and scale): its rigid flow re-selects
                # the static scene even when E itself locked onto a large moving object
                T_prev = se3_inverse(self.last_motion)[None]
                R0, t0, s0 = T_prev[:, :3, :3], T_prev[:, :3, 3] / self.last_scale, self.last_scale
            s_it, R_it, t_it, ok_it, iters = iterative_scale(
                pi, pj, mask, z_cnn, z_ok, K, R0, t0, s0, estimate,
                max_iters=cfg.scale.iterative_max_iters, tol=cfg.scale.iterative_tol,
                flow_threshold_px=cfg.scale.iterative_flow_threshold_px)
            diag.scale_iterations = iters
            if ok_it:
                R, t, s, ok = R_it, t_it, s_it, True
        rows = st.rows
        direction = -(R[0].transpose(0, 1) @ t[0])  # T_prev_cur's translation direction (E is never a stop: judged)
        if st.measured_direction is None:
            st.measured_direction = direction
        support = self._gate(st, check_support("E", diag.num_inliers, int(rows.sum()), cfg.gate)
                             or self._new_direction(st, "E", direction, check_direction(
                                 "E", direction, self.fusion.expected_direction, 1.0, cfg.gate,
                                 self.fusion.motion.direction_deg)))
        if support is not None:
            return None, support
        failed = f"scale recovery failed (<= {cfg.scale.min_points} usable depth points)"
        diag.scale_cnn = s if ok else None
        if self.fusion.uses_fusion:
            est = self.fusion.estimate(R, t, s if ok else None, pi, pj, (rows & e_res.inliers[0])[None],
                                       K, st.flow, st.inconsistency, st.plane_depth, gen, diag, st.grey_pair)
            if est.scale is None:
                return None, failed
            if est.source == "prediction":
                diag.add_reason("scale: no observation; the temporal filter's prediction is used")
            s, st.estimate = est.scale, est
        elif not ok:
            return None, failed
        too_far = self._gate(st, self._new_length(st, "E", s, check_length(
            "E", s, self.fusion.expected_length, cfg.gate, image_parallax_px(pi[0][rows], pj[0][rows], R[0], K[0]),
            self.fusion.expectation_settled, self.fusion.motion.length_ratio)))
        if too_far is not None:
            predicted = None if st.estimate is None else st.estimate.predicted
            if predicted is None or not cfg.scale.temporal:
                return None, too_far
            diag.add_reason(f"{too_far}; the temporal filter's prediction is used")
            diag.scale_source = "prediction|gated"
            s = predicted
        diag.tracker, diag.scale = TrackerUsed.essential, s
        return pose_from_rt(R, s * t)[0], None

    def _homography_pose(self, st: FrameState) -> tuple[torch.Tensor | None, str | None]:
        """A planar pair's pose ``T_cur_prev`` (4,4) from the homography (``model_selection.planar=homography``): R
        and the translation's direction of the decomposition that puts most of the plane in front of the camera and
        whose plane best explains the shape of the CNN depth at the homography's inliers (:meth:`_depth_agreement`;
        without usable depth, the one nearest the previous homography frame's plane), scaled and gated as the
        E-tracker's (:meth:`_essential_pose`), or None and why not."""
        cfg, e_res = self.cfg, st.essential
        h, rows = e_res.homography, e_res.homography_inliers[0]
        # of each pair of opposite signs the one that puts most inliers in front (distant points that fit any
        # homography, e.g. above a road's horizon, put some behind the true plane)
        moved = h.t_over_d[0].norm(dim=-1) > 1e-9
        if not bool(moved.any()):
            return None, "homography: no translation (a rotation or a stop)"
        ok = (h.in_front[0] > 0.5) & moved
        if not bool(ok.any()):
            return None, "homography: no decomposition puts the plane in front of the camera"
        score = self._depth_agreement(st, rows, h.n[0])
        if score is None:  # no usable depth: the previous homography frame's plane, else the most points in front
            score = h.n[0] @ self.plane_normal if self.plane_normal is not None else h.in_front[0]
        m = int(torch.where(ok, score, torch.full_like(score, -float("inf"))).argmax())
        R, t = h.R[0, m], h.t_over_d[0, m] / h.t_over_d[0, m].norm()
        parallax = image_parallax_px(st.pts_prev[0][rows], st.pts_cur[0][rows], R, st.K[0], quantile=0.5)
        min_px = cfg.model_selection.min_parallax_px
        if parallax is None or (min_px is not None and parallax < min_px):
            return None, f"homography: translation not visible ({parallax or 0.0:.2f} px beyond the rotation)"
        s, s_ok = essential_scale(R[None], t[None], st.pts_prev, st.pts_cur, rows[None], st.depth, st.K, cfg,
                                  [st.generator], st.depth_next)
        diag = st.diagnostics
        # what a failed attempt must not leave to the PnP fallback: the frame's state and the E-path diagnostics
        kept_state = (st.scale, st.scale_ok, st.estimate, st.gate_overruled, st.gated_direction)
        kept_diag = {k: getattr(diag, k) for k in ("gate_rejected", "num_inliers", "scale_cnn", "scale_height",
                                                    "scale_homography", "road_alignment_cost", "scale_temporal",
                                                    "scale_predicted", "cnn_bias", "scale_source", "plane_inliers",
                                                    "camera_height_fit")}
        st.essential = replace(e_res, R=R[None], t=t[None], inliers=rows[None], num_inliers=rows.sum()[None],
                               reasons=[None])
        st.scale, st.scale_ok = float(s[0]), bool(s_ok[0])
        diag.homography_motion = True
        T, reason = self._essential_pose(st, refine=False)
        if T is None:
            st.essential = e_res
            st.scale, st.scale_ok, st.estimate, st.gate_overruled, st.gated_direction = kept_state
            for k, v in kept_diag.items():
                setattr(diag, k, v)
            diag.homography_motion = False
            return None, f"homography: {reason}"
        self.plane_normal = R @ h.n[0, m]
        return T, None

    def _depth_agreement(self, st: FrameState, rows: torch.Tensor, normals: torch.Tensor) -> torch.Tensor | None:
        """(M,) how well each candidate plane (unit ``normals`` (M,3) in the earlier camera) explains the earlier
        frame's CNN depth at the correspondence ``rows`` (N,) bool: a plane ``n^T X = d`` puts a pixel's inverse depth
        at ``n^T x / d``, so 1 minus the fraction of the CNN inverse depths' energy left unexplained by the best
        multiple of ``n^T x`` (the network's scale does not matter, only the plane's shape; -1 when that multiple is
        not positive, a plane behind the camera); None with fewer than 8 usable points."""
        z, usable = sample_depth(st.depth, st.pts_prev, self.cfg.scale.max_depth, self.cfg.scale.depth_crop_top)
        use = usable[0] & rows
        if int(use.sum()) < 8:
            return None
        a = normalised_rays(st.pts_prev[0][use][None], st.K)[0] @ normals.T  # (P,M): n^T x per point and plane
        b = (1.0 / z[0][use])[:, None]
        k = (a * b).sum(0) / (a * a).sum(0).clamp_min(1e-30)
        explained = 1.0 - ((b - k * a) ** 2).sum(0) / (b * b).sum(0).clamp_min(1e-30)
        return torch.where(k > 0, explained, torch.full_like(explained, -1.0))  # a plane behind the camera: none

    def _new_direction(self, st: FrameState, kind: str, direction: torch.Tensor, reason: str | None) -> str | None:
        """The direction gate's verdict ``reason`` on the ``kind`` (``E``, ``PnP``) tracker's ``direction`` (3,),
        overruled when the results of the last ``confirm_direction_frames - 1`` frames (the motion's settings:
        ``tracker.gate``'s for a car, ``tracker.handheld``'s for a hand), each rejected by this gate, agree with it
        (within ``gate.max_direction_change_deg`` of it): the motion turned for good (a hand, not a car; off for a
        car by default); or, for ``E``, when PnP's result of this frame confirmed it
        (:meth:`_trackers_agree_on_turn`)."""
        if reason is None:
            return None
        if st.direction_confirmed and kind == "E":
            # the retry's direction (its RANSAC draws anew) must itself agree with PnP's
            apart = angle_deg(direction, st.rejected_directions["PnP"])
            if apart <= self.motion.settings.confirm_direction_by_pnp_deg:
                st.diagnostics.add_reason(f"{reason}: accepted, PnP's result points the same way ({apart:.0f} deg "
                                          "apart)")
                return None
        n = self.motion.settings.confirm_direction_frames
        if not n:
            st.rejected_directions[kind] = direction
            return reason
        recent = self.fusion.gated_directions[1 - int(n):]  # the last n - 1 (a car's n may have kept more)
        if len(recent) == int(n) - 1 and all(angle_deg(direction, d) <= self.cfg.gate.max_direction_change_deg
                                             for d in recent):
            st.diagnostics.add_reason(f"{reason}: accepted, {int(n)} frames in a row agree on the new direction")
            return None
        st.gated_direction = direction
        st.rejected_directions[kind] = direction  # the rejection stands
        return reason

    def _new_length(self, st: FrameState, kind: str, length: float, reason: str | None) -> str | None:
        """The length gate's verdict ``reason`` on the ``kind`` (``E``, ``PnP``) tracker's ``length`` (metres),
        overruled when each of the last ``confirm_length_frames - 1`` frames (the motion's settings: off for a car by
        default, 2 for a hand) had a result rejected by this gate and all those lengths and this one agree (each pair
        within the gate's ratio): the pace changed for good (:meth:`_finish_frame` restarts the expectation from
        them)."""
        if reason is None:
            return None
        n = self.motion.settings.confirm_length_frames
        recent = self.fusion.gated_lengths[1 - int(n):] if n else []
        ratio = self.fusion.motion.length_ratio  # the gate's own: max_length_ratio, or the sequence's wider one
        confirmed = bool(n) and len(recent) == int(n) - 1 and all(max(length, g) <= ratio * min(length, g)
                                                                  for g in recent)
        if st.gated_length is None:  # kept for the next frames should this result still fall (another gate)
            st.gated_length = length
        if not confirmed:
            return reason
        st.diagnostics.add_reason(f"{reason}: accepted, {int(n)} frames in a row agree on the new length")
        st.confirmed_lengths, st.confirmed_by = list(recent), kind
        return None

    def _gate(self, st: FrameState, reason: str | None) -> str | None:
        """A gate's verdict on this frame: None (accepted) or the reason; after ``gate.max_consecutive`` frames in a
        row that fell back to constant motion by a gate, the result is accepted (and the reason noted), and the next
        frame is judged by no expectation (the overruled result may be wrong itself)."""
        if reason is None:
            return None
        if self.fusion.rejections >= self.cfg.gate.max_consecutive:
            st.diagnostics.add_reason(f"{reason}: accepted after {self.fusion.rejections} gated frames in a row")
            st.gate_overruled = True
            return None
        st.diagnostics.gate_rejected = True
        return reason

    def _pnp(self, st: FrameState) -> torch.Tensor | None:
        """The PnP-tracker's pose ``T_cur_prev`` (4,4) after its gates, or None (the reason noted)."""
        cfg, diag = self.cfg, st.diagnostics
        pi, pj, mask, depth, K = st.pts_prev, st.pts_cur, st.mask, st.depth, st.K
        if st.pnp_backwards:  # the earlier frame has no depth (depth.every): the later frame's points, inverted
            T, ok, nin = track_pnp(pj, pi, mask, st.depth_next, K, cfg, [st.generator])
            T = se3_inverse(T)  # identity where it failed, as before
        else:
            T, ok, nin = track_pnp(pi, pj, mask, depth, K, cfg, [st.generator])
        diag.pnp_success, diag.num_inliers = bool(ok[0]), int(nin[0])
        if not bool(ok[0]):
            diag.add_reason("PnP failed")
            return None
        length = float(T[0, :3, 3].norm())
        if self.fusion.uses_fusion and cfg.scale.fuse_pnp and length >= cfg.scale_filter.min_length:
            # PnP's length is the depth network's scale: one more observation of the filter (with its bias, the
            # three-frame relative scale and the road), not the frame's length as it is
            R_p, t_p = T[:, :3, :3], T[:, :3, 3] / length
            est = self.fusion.estimate(R_p, t_p, length, pi, pj, mask, K, st.flow, st.inconsistency, st.plane_depth,
                                       st.generator, diag, st.grey_pair)
            if est.scale is not None:
                st.estimate = est
                length = est.scale
                T = pose_from_rt(R_p, length * t_p)
        direction = -(T[0, :3, :3].transpose(0, 1) @ T[0, :3, 3])
        if st.measured_direction is None:
            st.measured_direction = direction
            if st.essential is None:  # tracker.mode=pnp: no E parallax; the image's motion beyond PnP's rotation
                st.measured_parallax = image_parallax_px(pi[mask], pj[mask], T[0, :3, :3], K, quantile=0.5)
        if cfg.gate.enabled:
            lifted = (st.depth_next, pj) if st.pnp_backwards else (depth, pi)
            _, usable = sample_depth(*lifted, cfg.scale.max_depth, cfg.scale.depth_crop_top)
            support = check_support("PnP", int(nin[0]), int((usable & mask).sum()), cfg.gate)
            reason = self._gate(st, support
                                or self._new_length(st, "PnP", length, check_length(
                                    "PnP", length, self.fusion.expected_length, cfg.gate,
                                    image_parallax_px(pi[mask], pj[mask], T[0, :3, :3], K),
                                    self.fusion.expectation_settled, self.fusion.motion.length_ratio))
                                or self._new_direction(st, "PnP", direction, check_direction(
                                    "PnP", direction, self.fusion.expected_direction, length, cfg.gate,
                                    self.fusion.motion.direction_deg)))
            if reason is not None:
                diag.add_reason(reason)
                # a well-supported direction, rejected for its turn or its length (the length gate rejects no stop:
                # its image shows the translation's parallax)
                if support is None:
                    st.rejected_directions.setdefault("PnP", direction)
                return None
        diag.tracker, diag.scale = TrackerUsed.pnp, length
        return T[0]
