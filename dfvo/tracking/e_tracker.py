"""E-tracker: essential matrix RANSAC, GRIC against a homography, decomposition with cheirality, and the
simple scale from CNN depth, all batched over frame pairs.

Convention:
    Inputs are padded correspondences of pairs (prev=i, cur=j): ``pts_i``/``pts_j`` (B,N,2) pixels,
    ``mask`` (B,N), intrinsics ``K`` (B,3,3), depth of frame i (B,1,H,W). ``R, t`` are ``T_cur_prev`` (maps
    frame-i points into camera j) with unit ``t``; the metric translation is ``scale * t``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch

from dfvo.geometry.gric import gric_essential, gric_homography
from dfvo.geometry.homography import HomographyDecomposition, decompose_homography
from dfvo.geometry.two_view import decompose_essential, find_essential_ransac, find_homography_ransac
from dfvo.tracking.config import ModelSelectionMethod, TrackerConfig
from dfvo.tracking.model_selection import (
    homography_to_essential_residual,
    prefer_pnp_flow,
    prefer_pnp_gric,
    rotation_compensated_parallax,
)
from dfvo.tracking.motion_model import may_use_homography
from dfvo.tracking.scale import sample_depth, simple_scale, triangulated_depths

__all__ = ["ETrackerResult", "track_essential", "essential_scale"]


@dataclass
class ETrackerResult:
    """Per-frame (B,) results of :func:`track_essential`.

    Attributes:
        R: (B,3,3), t: (B,3) unit ``T_cur_prev``. E: (B,3,3). inliers: (B,N) RANSAC inliers.
        num_inliers: (B,) long. cheirality_fraction: (B,) of valid rows in front of both cameras.
        gric_e, gric_h: (B,) float64 (NaN when model_selection is not "gric").
        parallax_px: (B,) float64 median image motion of E's inliers beyond the rotation (pixels; NaN without
            inliers): what the translation shows in the image.
        valid: (B,) bool, E usable. reasons: why a frame's E is not usable (None when valid).
        homography: the decompositions of the GRIC homography (when a motion the run may use has ``planar=
            homography``: :func:`dfvo.tracking.motion_model.may_use_homography`; else None, and
            :meth:`with_homography` decomposes it when needed), homography_inliers: (B,N) its RANSAC inliers among
            the valid rows; homography_model: (B,3,3) the homography itself (both None unless model selection is
            GRIC).
    """

    R: torch.Tensor
    t: torch.Tensor
    E: torch.Tensor
    inliers: torch.Tensor
    num_inliers: torch.Tensor
    cheirality_fraction: torch.Tensor
    gric_e: torch.Tensor
    gric_h: torch.Tensor
    parallax_px: torch.Tensor
    valid: torch.Tensor
    reasons: list[str | None]
    homography: HomographyDecomposition | None = None
    homography_inliers: torch.Tensor | None = None
    homography_model: torch.Tensor | None = None

    def pair(self, b: int) -> ETrackerResult:
        """Pair ``b`` of the batch as a result of batch size 1 (views of the tensors, no copy)."""
        sl = slice(b, b + 1)
        h = self.homography
        return ETrackerResult(self.R[sl], self.t[sl], self.E[sl], self.inliers[sl], self.num_inliers[sl],
                              self.cheirality_fraction[sl], self.gric_e[sl], self.gric_h[sl], self.parallax_px[sl],
                              self.valid[sl], [self.reasons[b]],
                              None if h is None else HomographyDecomposition(h.R[sl], h.t_over_d[sl], h.n[sl],
                                                                              h.in_front[sl]),
                              None if self.homography_inliers is None else self.homography_inliers[sl],
                              None if self.homography_model is None else self.homography_model[sl])

    def with_homography(self, pts_i: torch.Tensor, pts_j: torch.Tensor, K: torch.Tensor) -> ETrackerResult:
        """This result with the homography decomposed (:func:`dfvo.geometry.homography.decompose_homography` of
        ``homography_model`` on the same rows ``pts_i``, ``pts_j`` (B,N,2) float64, ``K`` (B,3,3)): for a pair
        whose motion turned planar-capable after its batch was tracked (``tracker.motion=auto``'s revision).
        Unchanged when it is decomposed already or no homography was fitted."""
        if self.homography is not None or self.homography_model is None:
            return self
        return replace(self, homography=decompose_homography(self.homography_model, K, pts_i, pts_j,
                                                             self.homography_inliers))


def track_essential(pts_i: torch.Tensor, pts_j: torch.Tensor, mask: torch.Tensor, K: torch.Tensor,
                    cfg: TrackerConfig, generators: list[torch.Generator] | None,
                    homography: bool | None = None) -> ETrackerResult:
    """Essential-matrix tracking with validity rules: more than ``min_correspondences`` rows, a RANSAC model,
    E preferred by model selection (GRIC_E <= GRIC_H, or enough flow; with ``model_selection.min_parallax_px``
    also any pair whose inliers move at least that far beyond the camera's rotation, see
    :func:`dfvo.tracking.model_selection.rotation_compensated_parallax`), and at least ``min_cheirality_fraction``
    of the rows passing cheirality. ``homography``: decompose the GRIC homography of each pair (for the planar path);
    None: whenever a motion the configuration may run uses it (:func:`dfvo.tracking.motion_model.
    may_use_homography`; the odometry loop passes its judged motion's need)."""
    B = pts_i.shape[0]
    ess, sel = cfg.essential, cfg.model_selection
    n = mask.sum(-1)
    enough = n > ess.min_correspondences
    ransac = find_essential_ransac(pts_i, pts_j, mask, K, threshold_px=ess.threshold_px,
                                   iterations=ess.iterations, repeats=ess.repeats, generators=generators)
    R, t, front = decompose_essential(ransac.model, K, pts_i, pts_j, mask)
    cheir = front.sum(-1).to(torch.float64) / n.clamp_min(1).to(torch.float64)
    nan = torch.full((B,), float("nan"), dtype=torch.float64, device=pts_i.device)
    if sel.method == ModelSelectionMethod.gric:
        H = find_homography_ransac(pts_i, pts_j, mask, threshold_px=sel.h_threshold_px,
                                   iterations=sel.h_iterations, generators=generators)
        g_e = gric_essential(ransac.model, K, pts_i, pts_j, mask, sigma=sel.gric_sigma)
        g_h = gric_homography(H.model, pts_i, pts_j, mask, sigma=sel.gric_sigma)
        pnp_wanted = prefer_pnp_gric(g_e, g_h)
    else:
        g_e, g_h = nan, nan.clone()
        pnp_wanted = prefer_pnp_flow(pts_i, pts_j, mask, sel.flow_magnitude_threshold)
    parallax = rotation_compensated_parallax(pts_i, pts_j, mask & ransac.inliers, R, K)
    if sel.min_parallax_px is not None:  # the translation is visible: E's direction is measurable (parallax rule)
        visible = parallax >= sel.min_parallax_px
        if sel.method == ModelSelectionMethod.gric:
            # ... and the scene is not a plane: the homography explains E's inliers clearly worse than E does (on a
            # planar scene with a translation H fits them as well as E, and E's decomposition is ambiguous)
            visible = visible & (homography_to_essential_residual(H.model, ransac.model, K, pts_i, pts_j,
                                                                  mask & ransac.inliers, sel.residual_floor_px)
                                 >= sel.min_homography_residual_ratio)
        pnp_wanted = pnp_wanted & ~visible
    decomposition, h_inliers, h_model = None, None, None
    if homography is None:
        homography = may_use_homography(cfg)
    if sel.method == ModelSelectionMethod.gric:
        h_inliers, h_model = mask & H.inliers, H.model
        if homography:
            decomposition = decompose_homography(H.model, K, pts_i, pts_j, h_inliers)
    reasons: list[str | None] = []
    valid = torch.zeros(B, dtype=torch.bool, device=pts_i.device)
    for b in range(B):
        if not bool(enough[b]):
            reasons.append(f"E invalid: {int(n[b])} correspondences <= {ess.min_correspondences}")
        elif not bool(ransac.success[b]):
            reasons.append("E invalid: RANSAC found no model")
        elif bool(pnp_wanted[b]):
            reasons.append("model selection prefers PnP (GRIC_E > GRIC_H)" if sel.method == ModelSelectionMethod.gric
                           else f"model selection prefers PnP (median flow <= {sel.flow_magnitude_threshold} px)")
        elif float(cheir[b]) < ess.min_cheirality_fraction:
            reasons.append(f"E invalid: {float(cheir[b]):.1%} of points pass cheirality")
        else:
            reasons.append(None)
            valid[b] = True
    return ETrackerResult(R, t, ransac.model, ransac.inliers, ransac.num_inliers, cheir, g_e, g_h, parallax, valid,
                         reasons, decomposition, h_inliers, h_model)


def essential_scale(R: torch.Tensor, t: torch.Tensor, pts_i: torch.Tensor, pts_j: torch.Tensor, mask: torch.Tensor,
                    depth_i: torch.Tensor, K: torch.Tensor, cfg: TrackerConfig,
                    generators: list[torch.Generator] | None,
                    depth_j: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Simple scale (1-D RANSAC on CNN / triangulated depth ratios) of unit ``T_cur_prev`` motions.

    ``depth_i`` (B,1,H,W) is the CNN depth of the earlier frame. With ``depth_j`` (the later frame's, given when
    ``cfg.scale.depth_views == 2``) a second scale comes from the ratios in camera j at ``pts_j``, and the result
    is the geometric mean of the two when they agree within ``cfg.scale.views_max_ratio`` (else the earlier
    frame's scale, as in the paper; the one that succeeded when only one did).

    Returns:
        scale (B,) float64 and success (B,) bool (needs more than ``cfg.scale.min_points`` usable rows).
    """
    sc = cfg.scale
    z_tri_i, z_tri_j, front = triangulated_depths(R, t, K, pts_i, pts_j)

    def one_view(depth: torch.Tensor, pts: torch.Tensor, z_tri: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        z_cnn, ok = sample_depth(depth, pts, sc.max_depth, sc.depth_crop_top)
        s, _, success = simple_scale(z_cnn, z_tri, mask & ok & front, trials=sc.ransac_trials,
                                     samples=sc.ransac_samples, threshold=sc.inlier_threshold,
                                     min_points=sc.min_points, generators=generators)
        return s, success

    s_i, ok_i = one_view(depth_i, pts_i, z_tri_i)
    if depth_j is None:
        return s_i, ok_i
    s_j, ok_j = one_view(depth_j, pts_j, z_tri_j)
    agree = (s_i.clamp_min(1e-12) / s_j.clamp_min(1e-12)).log().abs() <= math.log(sc.views_max_ratio)
    both = ok_i & ok_j & agree
    s = torch.where(both, (s_i.clamp_min(0) * s_j.clamp_min(0)).sqrt(), torch.where(ok_i, s_i, s_j))
    return s, ok_i | ok_j
