"""Relative scale of consecutive frame pairs from the points seen in three frames.

Pair (i, j) was tracked with a metric pose; its points triangulated with that pose have metric depths in the
shared middle frame j (:class:`MiddleDepths`). The next pair (j, k) has a unit-translation pose from the E-tracker;
the same points, carried from image j to image k by the flow j->k, triangulate to depths in frame j in units of
the new translation's length. The same physical depth in both gives that length: ``s_jk = z_metric / z_unit``
(median over the shared points). On exact flow it is exact; it needs no depth network, only the previous pair's
scale, so the per-frame scale noise of the depth network can be averaged over time (:mod:`dfvo.tracking.scale_filter`).

Convention:
    ``T_cur_prev = [R | t]`` maps frame-i (prev) points into camera j (cur). Pixels (N,2) / (B,N,2), flow
    (1,2,H,W) in pixels prev->cur, inconsistency (1,1,H,W) pixels, intrinsics (1,3,3). Depths are z in metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE

from dfvo.geometry.two_view import normalised_rays
from dfvo.matching.flow_warp import inside_image, sample_at_pixels
from dfvo.matching.pyramid_refinement import PyramidRefinementConfig, build_pyramid, lucas_kanade
from dfvo.tracking.config import ScaleFilterConfig
from dfvo.tracking.ground_plane import parallax_deg
from dfvo.tracking.scale import triangulated_depths

__all__ = ["MiddleDepths", "middle_depths", "RelativeScale", "relative_scale"]

MAD_TO_STD = 1.4826


@dataclass
class MiddleDepths:
    """Points of a tracked pair in its later image: ``pts`` (M,2) pixels and ``depth`` (M,) metres (float64)."""

    pts: torch.Tensor
    depth: torch.Tensor


def middle_depths(T_cur_prev: torch.Tensor, K: torch.Tensor, pts_prev: torch.Tensor, pts_cur: torch.Tensor,
                  rows: torch.Tensor,
                  min_parallax_deg: float = ScaleFilterConfig.min_parallax_deg) -> MiddleDepths | None:
    """The metric depths in the later image of the rows ``rows`` (N,) of a tracked pair, triangulated with its
    metric ``T_cur_prev`` (4,4); rows in front of both cameras with at least ``min_parallax_deg`` of parallax.
    None when the pose has (almost) no translation.

    Args:
        T_cur_prev: (4,4). K: (3,3) or (1,3,3). pts_prev, pts_cur: (N,2) pixels. rows: (N,) bool.
    """
    KORNIA_CHECK_SHAPE(pts_prev, ["N", "2"])
    T = T_cur_prev.to(torch.float64)
    length = float(T[:3, 3].norm())
    if not length > 1e-9:
        return None
    Kb = K.reshape(1, 3, 3).to(torch.float64)
    R, t = T[None, :3, :3], T[None, :3, 3] / length
    z_i, z_j, front = triangulated_depths(R, t, Kb, pts_prev[None], pts_cur[None])
    X_i = normalised_rays(pts_prev[None], Kb) * z_i[..., None]
    keep = rows[None] & front & torch.isfinite(z_j) & (parallax_deg(X_i, t, R) >= min_parallax_deg)
    keep = keep[0]
    return MiddleDepths(pts_cur.to(torch.float64)[keep].clone(), (length * z_j[0][keep]).clone())


@dataclass
class RelativeScale:
    """The scale of pair (j, k) from the previous pair's points: ``scale`` (metres, the length of the unit
    translation), ``log_std`` the standard error of log(scale) (robust spread / sqrt(n)), ``num_points`` used.
    ``scale`` is None when fewer than the required points were shared."""

    scale: float | None
    log_std: float | None
    num_points: int


def _refined_motion(pts_j: torch.Tensor, flow: torch.Tensor, grey_pair: tuple[torch.Tensor, torch.Tensor],
                    ok: torch.Tensor, cfg: PyramidRefinementConfig | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The points' positions in image k and their forward-backward inconsistency (px), both from the pyramidal
    Lucas–Kanade of :mod:`dfvo.matching.pyramid_refinement` at the points themselves (forward from the dense flow,
    backward from minus the result; ``cfg`` its settings, None: the defaults), not from the dense fields: (M,2)
    float64, (M,) float64 (inf where it failed)."""
    cfg = cfg or PyramidRefinementConfig()
    pyramid = build_pyramid(torch.cat([grey_pair[0], grey_pair[1]]).to(torch.float32), cfg.levels, cfg.sigma)
    j, k = torch.zeros(1, dtype=torch.long), torch.ones(1, dtype=torch.long)
    p = pts_j.to(torch.float32)[None]
    u, ok_f = lucas_kanade(pyramid, j, k, p, sample_at_pixels(flow, pts_j).T.to(torch.float32)[None], ok[None], cfg)
    v, ok_b = lucas_kanade(pyramid, k, j, p + u, -u, ok_f, cfg, cfg.backward_iterations)
    incon = torch.where(ok_f & ok_b, (u + v).norm(dim=-1), torch.full_like(u[..., 0], float("inf")))
    return pts_j + u[0].to(torch.float64), incon[0].to(torch.float64)


def relative_scale(prev: MiddleDepths | None, flow: torch.Tensor, inconsistency: torch.Tensor, K: torch.Tensor,
                   R: torch.Tensor, t: torch.Tensor, max_inconsistency: float = ScaleFilterConfig.max_inconsistency,
                   min_parallax_deg: float = ScaleFilterConfig.min_parallax_deg,
                   min_points: int = ScaleFilterConfig.min_points,
                   grey_pair: tuple[torch.Tensor, torch.Tensor] | None = None,
                   point_refinement: PyramidRefinementConfig | None = None) -> RelativeScale:
    """Metric length of the unit translation ``t`` of pair (j, k) from the depths ``prev`` of pair (i, j).

    The points ``prev.pts`` of image j are carried to image k by ``flow`` (j->k, sampled bilinearly); those whose
    forward-backward inconsistency is within ``max_inconsistency`` px, which stay inside image k, lie in front of
    both cameras and have ``min_parallax_deg`` of parallax are triangulated with ``[R | t]``; the scale is
    ``median(prev.depth / z_unit)`` (in log space, with a 3-MAD trim). With ``grey_pair`` (images j and k, (1,1,H,W)
    each) the points' motion and inconsistency come from a photometric refinement at the points themselves
    (:func:`_refined_motion`) instead of the dense flow and inconsistency fields: for a flow refined only at its own
    candidates (``flow.refine.mode=pyramid``), where the dense flow at these points is the network's raw flow;
    ``point_refinement`` are its settings (the flow refinement's own, ``flow.refine.pyramid``; None: the defaults).

    Args:
        prev: the previous pair's middle-frame depths (None: no previous pair; the result is empty).
        flow: (1,2,H,W) j->k. inconsistency: (1,1,H,W). K: (1,3,3). R: (1,3,3), t: (1,3) unit ``T_k_j``.
    """
    if prev is None or prev.pts.shape[0] == 0:
        return RelativeScale(None, None, 0)
    KORNIA_CHECK_SHAPE(flow, ["1", "2", "H", "W"])
    KORNIA_CHECK(inconsistency.shape[-2:] == flow.shape[-2:], "relative_scale: flow and inconsistency sizes differ")
    H, W = flow.shape[-2:]
    pts_j = prev.pts
    inside_j = inside_image(pts_j, H, W)
    if grey_pair is None:
        pts_k = pts_j + sample_at_pixels(flow, pts_j).T
        incon = sample_at_pixels(inconsistency.reshape(1, 1, H, W), pts_j)[0]
    else:
        pts_k, incon = _refined_motion(pts_j, flow, grey_pair, inside_j, point_refinement)
    inside_k = inside_image(pts_k, H, W)
    Kd, Rd, td = K.reshape(1, 3, 3).to(torch.float64), R.to(torch.float64), t.to(torch.float64)
    z_j, _, front = triangulated_depths(Rd, td, Kd, pts_j[None], pts_k[None])
    X_j = normalised_rays(pts_j[None], Kd) * z_j[..., None]
    ok = (inside_j & inside_k & (incon <= max_inconsistency))[None] & front & \
        (parallax_deg(X_j, td, Rd) >= min_parallax_deg) & (prev.depth[None] > 0)
    ok = ok[0]
    n = int(ok.sum())
    if n < max(3, int(min_points)):
        return RelativeScale(None, None, n)
    log_ratio = (prev.depth[ok] / z_j[0][ok]).log()
    med = log_ratio.median()
    mad = (log_ratio - med).abs().median()
    keep = (log_ratio - med).abs() <= 3 * MAD_TO_STD * mad + 1e-12
    log_ratio = log_ratio[keep]
    med = log_ratio.median()
    spread = MAD_TO_STD * (log_ratio - med).abs().median()
    return RelativeScale(float(med.exp()), float(spread) / max(1, log_ratio.numel()) ** 0.5, int(log_ratio.numel()))
