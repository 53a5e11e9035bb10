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
``t = s * t_unit``. When PnP itself fails the frame also uses constant motion (the official code used identity).

Our additions, each one switch away from the paper: the scale ``s`` may fuse the CNN-depth scale with the
camera-height prior and, over time, the three-frame relative scale (:mod:`dfvo.tracking.scale_fusion`;
``tracker.scale.camera_height``, ``tracker.scale.temporal``); with the temporal filter a frame whose scale
observations all fail keeps the filter's prediction (``scale_source="prediction"``) instead of going to PnP. The
plausibility gates (:mod:`dfvo.tracking.gates`, ``tracker.gate.enabled``) reject an E or PnP result with too few
inliers, a translation far longer or shorter than the previous frame's, or one whose direction turns too far; E
then falls to PnP (hybrid), PnP to constant motion, flagged in ``fallback_reason`` and ``gate_rejected``.

Batched == streaming: the selection, E/H RANSAC, GRIC and simple scale run on the whole batch; frame k of the
sequence always draws from ``torch.Generator().manual_seed(cfg.seed + k)``; the iterative scale, PnP, the scale
fusion (its filter state, the previous pair's middle-frame depths, the gates' expected motion) and the pose
composition run frame by frame in order. ``run`` is causal like ``step`` (no smoothing over the sequence), so both
give the same poses whatever the batch size.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import torch
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE

from dfvo.geometry.se3 import pose_from_rt
from dfvo.geometry.two_view import decompose_essential, find_essential_ransac
from dfvo.matching.consistency import forward_backward_inconsistency
from dfvo.matching.selection import select_correspondences
from dfvo.tracking.config import ScaleMethod, TrackerConfig, TrackerMode
from dfvo.tracking.covariance import length_log_variance, step_covariance
from dfvo.tracking.diagnostics import FrameDiagnostics, TrackerUsed
from dfvo.tracking.e_tracker import essential_scale, track_essential
from dfvo.tracking.gates import check_direction, check_length, check_support, image_parallax_px
from dfvo.tracking.pnp_tracker import track_pnp
from dfvo.tracking.scale import iterative_scale, sample_depth
from dfvo.tracking.scale_filter import ScaleEstimate
from dfvo.tracking.scale_fusion import ScaleFusion

__all__ = ["FrameMatches", "FrameResult", "VisualOdometry"]


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


def _inv(T: torch.Tensor) -> torch.Tensor:
    R, t = T[..., :3, :3], T[..., :3, 3:]
    out = torch.eye(4, dtype=T.dtype, device=T.device).expand_as(T).clone()
    out[..., :3, :3] = R.transpose(-1, -2)
    out[..., :3, 3:] = -R.transpose(-1, -2) @ t
    return out


class VisualOdometry:
    """Monocular visual odometry from flows and depths (see the module docstring for conventions).

    Args:
        cfg: :class:`TrackerConfig` (official defaults when omitted).
    """

    def __init__(self, cfg: TrackerConfig | None = None) -> None:
        self.cfg = cfg if cfg is not None else TrackerConfig()
        self.reset()

    def reset(self) -> None:
        """Forget the trajectory: the next frame starts at identity, frame counter 0, no motion model."""
        self.frame = 0
        self.T_w = torch.eye(4, dtype=torch.float64)
        self.last_motion = torch.eye(4, dtype=torch.float64)
        self.last_scale = 0.0
        if getattr(self, "fusion", None) is None or self.fusion.cfg is not self.cfg:
            self.fusion = ScaleFusion(self.cfg)
        self.fusion.reset()

    # ------------------------------------------------------------------------------------------ public
    def step(self, flow_fwd: torch.Tensor, flow_bwd: torch.Tensor, depth_prev: torch.Tensor,
             K: torch.Tensor, depth_cur: torch.Tensor | None = None) -> FrameResult:
        """Track one new frame: flows (1,2,H,W) prev->cur and cur->prev, depth (1,1,H,W) of prev, K (1,3,3);
        ``depth_cur`` (1,1,H,W) of cur when ``scale_depth_views=2``."""
        KORNIA_CHECK(flow_fwd.shape[0] == 1, f"VisualOdometry.step takes one pair (B=1); got flow_fwd "
                                             f"{tuple(flow_fwd.shape)} (use run for batches)")
        return self._batch(flow_fwd, flow_bwd, depth_prev, K.reshape(1, 3, 3), depth_cur)[0]

    def run(self, flows_fwd: torch.Tensor, flows_bwd: torch.Tensor, depths: torch.Tensor, K: torch.Tensor,
            batch_size: int = 8, depths_next: torch.Tensor | None = None) -> list[FrameResult]:
        """Track a whole sequence: (N-1,2,H,W) flows, (N-1,1,H,W) depths of the earlier frame of each pair,
        K (3,3) or (N-1,3,3); ``depths_next`` (N-1,1,H,W) of the later frame of each pair when
        ``scale_depth_views=2``. Returns N-1 results (frame 0 is identity), identical to calling :meth:`step`."""
        KORNIA_CHECK_SHAPE(flows_fwd, ["M", "2", "H", "W"])
        M = flows_fwd.shape[0]
        Ks = K.reshape(1, 3, 3).expand(M, 3, 3) if K.dim() == 2 else K
        KORNIA_CHECK(Ks.shape == (M, 3, 3), f"VisualOdometry.run: K {tuple(K.shape)}; expected (3,3) or ({M},3,3)")
        out: list[FrameResult] = []
        for s in range(0, M, max(1, int(batch_size))):
            e = min(M, s + max(1, int(batch_size)))
            out.extend(self._batch(flows_fwd[s:e], flows_bwd[s:e], depths[s:e], Ks[s:e],
                                   None if depths_next is None else depths_next[s:e]))
        return out

    # ------------------------------------------------------------------------------------------ internals
    def _batch(self, flow_fwd: torch.Tensor, flow_bwd: torch.Tensor, depth: torch.Tensor,
               K: torch.Tensor, depth_next: torch.Tensor | None = None) -> list[FrameResult]:
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
        gens = [torch.Generator().manual_seed(cfg.seed + self.frame + b) for b in range(B)]
        t0 = time.perf_counter()
        sel = cfg.correspondence
        incon = forward_backward_inconsistency(flow_fwd, flow_bwd)
        corr = select_correspondences(flow_fwd, incon, method=sel.method.value, num=sel.num_correspondences,
                                      grid=tuple(sel.grid), max_inconsistency=sel.max_inconsistency,
                                      min_valid_fraction=sel.min_valid_fraction,
                                      min_region_fraction=sel.min_region_fraction, crop_top=sel.crop_top)
        pi, pj, mask = corr.pts_i.to(torch.float64), corr.pts_j.to(torch.float64), corr.mask
        Kd = K.to(torch.float64)
        t1 = time.perf_counter()
        e_res, scale, scale_ok = None, None, None
        if cfg.mode != TrackerMode.pnp:
            e_res = track_essential(pi, pj, mask, Kd, cfg, gens)
            scale, scale_ok = essential_scale(e_res.R, e_res.t, pi, pj, mask, depth, Kd, cfg, gens, depth_next)
        t2 = time.perf_counter()
        results = []
        for b in range(B):
            tb = time.perf_counter()
            res = self._finish_frame(b, corr, pi, pj, mask, depth, depth_next, Kd, e_res, scale, scale_ok, gens[b],
                                     flow_fwd, incon)
            res.diagnostics.time_selection = (t1 - t0) / B
            res.diagnostics.time_e_tracker = (t2 - t1) / B
            res.diagnostics.time_sequential = time.perf_counter() - tb
            results.append(res)
        return results

    def _finish_frame(self, b: int, corr: Any, pi: torch.Tensor, pj: torch.Tensor, mask: torch.Tensor,
                      depth: torch.Tensor, depth_next: torch.Tensor | None, K: torch.Tensor, e_res: Any,
                      scale: torch.Tensor | None, scale_ok: torch.Tensor | None, gen: torch.Generator,
                      flow: torch.Tensor, incon: torch.Tensor) -> FrameResult:
        cfg = self.cfg
        sl = slice(b, b + 1)
        self._estimate: ScaleEstimate | None = None  # the fused scale an E pose used
        self._gate_overruled = False
        diag = FrameDiagnostics(frame=self.frame + 1, num_correspondences=int(mask[b].sum()),
                                selection_failed=bool(corr.failed[b]))
        if e_res is not None:
            gric_e, gric_h = float(e_res.gric_e[b]), float(e_res.gric_h[b])
            diag.gric_e = gric_e if gric_e == gric_e else None  # NaN: GRIC not computed
            diag.gric_h = gric_h if gric_h == gric_h else None
            diag.cheirality_fraction = float(e_res.cheirality_fraction[b])
        T_cur_prev: torch.Tensor | None = None
        if bool(corr.failed[b]):
            diag.fallback_reason = f"selection failed: {corr.reasons[b]}"
        elif cfg.mode == TrackerMode.pnp:
            T_cur_prev = self._pnp(sl, pi, pj, mask, depth, K, gen, diag)
        else:
            reason = e_res.reasons[b]
            if reason is None:
                T_cur_prev, reason = self._essential_pose(b, pi, pj, mask, depth, depth_next, K, e_res, scale,
                                                          scale_ok, gen, diag, flow, incon)
            if T_cur_prev is None:
                diag.add_reason(reason)
                if cfg.mode == TrackerMode.hybrid:
                    T_cur_prev = self._pnp(sl, pi, pj, mask, depth, K, gen, diag)
        if T_cur_prev is None:
            T_prev_cur = self.last_motion.clone()
            diag.tracker = TrackerUsed.constant_motion
        else:
            T_prev_cur = _inv(T_cur_prev)
        self.T_w = self.T_w @ T_prev_cur
        self.last_motion = T_prev_cur
        self.last_scale = float(T_prev_cur[:3, 3].norm())
        self.frame += 1
        rows = mask[b]
        used_e = e_res is not None and diag.tracker == TrackerUsed.essential
        self.fusion.end_frame(T_cur_prev, T_prev_cur, diag.tracker, self._estimate, pi[b], pj[b],
                              rows & e_res.inliers[b] if used_e else rows, K[b])
        gated_out = diag.gate_rejected and diag.tracker == TrackerUsed.constant_motion
        self.fusion.rejections = self.fusion.rejections + 1 if gated_out else 0
        if self._gate_overruled and T_cur_prev is not None:  # accepted against the gates: it may be wrong itself
            self.fusion.forget_motion()
        inliers = e_res.inliers[b][rows] if used_e else None
        matches = FrameMatches(pi[b][rows], pj[b][rows], inliers)
        log_var = length_log_variance(self._estimate, self.fusion._prior.pxx, self.last_scale, cfg)
        cov = step_covariance(diag.tracker, T_cur_prev, T_prev_cur, matches.pts_prev, matches.pts_cur, K[b], depth[sl],
                              cfg, log_var)
        return FrameResult(self.T_w.clone(), T_prev_cur, diag, matches, cov)

    def _essential_pose(self, b: int, pi: torch.Tensor, pj: torch.Tensor, mask: torch.Tensor, depth: torch.Tensor,
                        depth_next: torch.Tensor | None, K: torch.Tensor, e_res: Any, scale: torch.Tensor,
                        scale_ok: torch.Tensor, gen: torch.Generator, diag: FrameDiagnostics, flow: torch.Tensor,
                        incon: torch.Tensor) -> tuple[torch.Tensor | None, str | None]:
        cfg = self.cfg
        sl = slice(b, b + 1)
        R, t = e_res.R[sl], e_res.t[sl]
        s, ok = float(scale[b]), bool(scale_ok[b])
        diag.num_inliers = int(e_res.num_inliers[b])
        if cfg.scale.method == ScaleMethod.iterative:
            z_cnn, z_ok = sample_depth(depth[sl], pi[sl], cfg.scale.max_depth, cfg.scale.depth_crop_top)

            def estimate(rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
                if int(rows.sum()) <= cfg.essential.min_correspondences:
                    return R, t, torch.zeros(1, dtype=torch.float64), torch.zeros(1, dtype=torch.bool)
                r = find_essential_ransac(pi[sl], pj[sl], rows, K[sl], threshold_px=cfg.essential.threshold_px,
                                          iterations=cfg.essential.iterations, repeats=cfg.essential.repeats,
                                          generators=[gen])
                R2, t2, _ = decompose_essential(r.model, K[sl], pi[sl], pj[sl], rows)
                s2, ok2 = essential_scale(R2, t2, pi[sl], pj[sl], rows, depth[sl], K[sl], cfg, [gen],
                                          None if depth_next is None else depth_next[sl])
                return R2, t2, s2, ok2 & r.success

            R0, t0, s0 = R, t, 0.0
            if self.last_scale > 0:
                # start from the motion model (previous R and t direction and scale): its rigid flow re-selects
                # the static scene even when E itself locked onto a large moving object
                T_prev = _inv(self.last_motion)[None]
                R0, t0, s0 = T_prev[:, :3, :3], T_prev[:, :3, 3] / self.last_scale, self.last_scale
            s_it, R_it, t_it, ok_it, iters = iterative_scale(
                pi[sl], pj[sl], mask[sl], z_cnn, z_ok, K[sl], R0, t0, s0, estimate,
                max_iters=cfg.scale.iterative_max_iters, tol=cfg.scale.iterative_tol,
                flow_threshold_px=cfg.scale.iterative_flow_threshold_px)
            diag.scale_iterations = iters
            if ok_it:
                R, t, s, ok = R_it, t_it, s_it, True
        direction = -(R[0].transpose(0, 1) @ t[0])  # T_prev_cur's translation direction (E is never a stop: judged)
        support = self._gate(check_support("E", diag.num_inliers, int(mask[b].sum()), cfg.gate)
                             or check_direction("E", direction, self.fusion.expected_direction, 1.0, cfg.gate), diag)
        if support is not None:
            return None, support
        failed = f"scale recovery failed (<= {cfg.scale.min_points} usable depth points)"
        diag.scale_cnn = s if ok else None
        if self.fusion.uses_fusion:
            est = self.fusion.estimate(R, t, s if ok else None, pi[sl], pj[sl], (mask[b] & e_res.inliers[b])[None],
                                       K[sl], flow[sl], incon[sl], depth[sl], gen, diag)
            if est.scale is None:
                return None, failed
            if est.source == "prediction":
                diag.add_reason("scale: no observation; the temporal filter's prediction is used")
            s, self._estimate = est.scale, est
        elif not ok:
            return None, failed
        too_far = self._gate(check_length("E", s, self.fusion.expected_length, cfg.gate,
                                                 image_parallax_px(pi[b][mask[b]], pj[b][mask[b]], R[0], K[b])), diag)
        if too_far is not None:
            predicted = None if self._estimate is None else self._estimate.predicted
            if predicted is None or not cfg.scale.temporal:
                return None, too_far
            diag.add_reason(f"{too_far}; the temporal filter's prediction is used")
            diag.scale_source = "prediction|gated"
            s = predicted
        diag.tracker, diag.scale = TrackerUsed.essential, s
        return pose_from_rt(R, s * t)[0], None

    def _gate(self, reason: str | None, diag: FrameDiagnostics) -> str | None:
        """A gate's verdict on this frame: None (accepted) or the reason; after ``gate.max_consecutive`` frames in a
        row that fell back to constant motion by a gate, the result is accepted (and the reason noted), and the next
        frame is judged by no expectation (the overruled result may be wrong itself)."""
        if reason is None:
            return None
        if self.fusion.rejections >= self.cfg.gate.max_consecutive:
            diag.add_reason(f"{reason}: accepted after {self.fusion.rejections} gated frames in a row")
            self._gate_overruled = True
            return None
        diag.gate_rejected = True
        return reason

    def _pnp(self, sl: slice, pi: torch.Tensor, pj: torch.Tensor, mask: torch.Tensor, depth: torch.Tensor,
             K: torch.Tensor, gen: torch.Generator, diag: FrameDiagnostics) -> torch.Tensor | None:
        T, ok, nin = track_pnp(pi[sl], pj[sl], mask[sl], depth[sl], K[sl], self.cfg, [gen])
        diag.pnp_success, diag.num_inliers = bool(ok[0]), int(nin[0])
        if not bool(ok[0]):
            diag.add_reason("PnP failed")
            return None
        length = float(T[0, :3, 3].norm())
        if self.cfg.gate.enabled:
            _, usable = sample_depth(depth[sl], pi[sl], self.cfg.scale.max_depth, self.cfg.scale.depth_crop_top)
            direction = -(T[0, :3, :3].transpose(0, 1) @ T[0, :3, 3])
            reason = self._gate(check_support("PnP", int(nin[0]), int((usable & mask[sl]).sum()), self.cfg.gate)
                                or check_length("PnP", length, self.fusion.expected_length, self.cfg.gate,
                                             image_parallax_px(pi[sl][mask[sl]], pj[sl][mask[sl]], T[0, :3, :3],
                                                               K[sl]))
                                or check_direction("PnP", direction, self.fusion.expected_direction, length,
                                                   self.cfg.gate), diag)
            if reason is not None:
                diag.add_reason(reason)
                return None
        diag.tracker, diag.scale = TrackerUsed.pnp, length
        return T[0]
