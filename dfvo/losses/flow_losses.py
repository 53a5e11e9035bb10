"""Optical-flow training losses: supervised multi-scale end-point error and the self-supervised loss.

Convention:
    - Flows (B,2,H,W) in pixels of the images they come with (dfvo convention: ``flow_i→j(x)`` = position
      in image j of pixel x of image i, minus x). Multi-scale flows are lists, finest first, all already
      upsampled to the image size (``FlowNet(..., all_scales=True)``); list index ``k`` is scale ``s = k + 1``
      and its term is divided by ``2**s`` (official DF-VO flow-loss weighting) unless weights are given.
    - Masks (B,1,H,W) bool. Images (B,3,H,W) in [0,1].

Self-supervised loss (DF-VO eq. for the flow network, with UnFlow-style occlusion handling), per scale and
for both directions:
    ``L = mean_visible[ alpha*(1-SSIM)/2 + (1-alpha)*|I_i - I_j(x+F)| ]
        + lambda_fs * edge_aware_smoothness(||F||, I_i) + lambda_fc * mean_visible ||F_fwd + F_bwd(x+F_fwd)||``
    where "visible" = target inside image j and not occluded. A pixel is occluded when
    ``||F_fwd + F_bwd(x+F_fwd)||^2 > occ_alpha1 * (||F_fwd||^2 + ||F_bwd(x+F_fwd)||^2) + occ_alpha2``
    (Meister et al., UnFlow), computed without gradient.
"""

from __future__ import annotations

import torch
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE

from dfvo.losses.photometric import ssim_l1_error, ssim_moments
from dfvo.losses.smoothness import edge_aware_smoothness
from dfvo.matching.consistency import inconsistency_at
from dfvo.matching.flow_warp import flow_magnitude, warp_by_flow


def scale_weights(num_scales: int) -> list[float]:
    """Official per-scale weighting: scale ``s = 1..S`` (finest first) weighted by ``1 / 2**s``."""
    return [1.0 / 2 ** (k + 1) for k in range(num_scales)]


def _as_list(flows: torch.Tensor | list[torch.Tensor]) -> list[torch.Tensor]:
    return [flows] if isinstance(flows, torch.Tensor) else list(flows)


def _masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    m = mask.to(x.dtype).expand_as(x)
    return (x * m).sum() / m.sum().clamp(min=1.0)


def endpoint_error(flow: torch.Tensor, flow_gt: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
    """Average end-point error ``mean ||flow - flow_gt||`` over valid pixels (scalar, pixels).

    Args:
        flow: (B,2,H,W) estimate.
        flow_gt: (B,2,H,W) ground truth.
        valid: (B,1,H,W) bool mask of pixels with ground truth (all pixels when None).
    """
    KORNIA_CHECK_SHAPE(flow, ["B", "2", "H", "W"])
    KORNIA_CHECK(flow.shape == flow_gt.shape,
                 f"endpoint_error: flow {tuple(flow.shape)} and flow_gt {tuple(flow_gt.shape)} differ")
    err = flow_magnitude(flow - flow_gt)
    if valid is None:
        return err.mean()
    KORNIA_CHECK_SHAPE(valid, ["B", "1", "H", "W"])
    return _masked_mean(err, valid)


def multiscale_epe(flows: torch.Tensor | list[torch.Tensor], flow_gt: torch.Tensor, valid: torch.Tensor | None = None,
                   weights: list[float] | None = None) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """Supervised multi-scale EPE loss.

    Args:
        flows: list of (B,2,H,W) flows, finest first, at the ground truth's resolution.
        flow_gt: (B,2,H,W) true flow.
        valid: (B,1,H,W) bool visibility mask (non-occluded, inside the other image).
        weights: per-scale weights (default ``1/2**s``).

    Returns:
        ``(total, per_scale_epe)``: weighted sum (scalar) and the unweighted EPE of each scale.
    """
    flows = _as_list(flows)
    weights = scale_weights(len(flows)) if weights is None else weights
    KORNIA_CHECK(len(weights) == len(flows), f"multiscale_epe: {len(weights)} weights for {len(flows)} scales")
    per_scale = [endpoint_error(f, flow_gt, valid) for f in flows]
    total = sum(w * e for w, e in zip(weights, per_scale))
    return total, per_scale


@torch.no_grad()
def occlusion_mask(flow_fwd: torch.Tensor, flow_bwd: torch.Tensor, alpha1: float = 0.01,
                   alpha2: float = 0.5) -> tuple[torch.Tensor, torch.Tensor]:
    """Visibility of image i's pixels from forward-backward consistency (no gradient).

    Args:
        flow_fwd: (B,2,H,W) flow i→j on image i.
        flow_bwd: (B,2,H,W) flow j→i on image j.
        alpha1: relative threshold on the squared inconsistency.
        alpha2: absolute threshold (pixels^2).

    Returns:
        ``(visible, inconsistency)``: (B,1,H,W) bool (target inside image j and consistent) and the
        (B,1,H,W) inconsistency in pixels (+inf outside image j).
    """
    bwd_at, inside = warp_by_flow(flow_bwd, flow_fwd)
    return _occlusion_from_warp(flow_fwd, bwd_at, inside, alpha1, alpha2)


@torch.no_grad()
def _occlusion_from_warp(flow_fwd: torch.Tensor, bwd_at: torch.Tensor, inside: torch.Tensor, alpha1: float,
                         alpha2: float) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`occlusion_mask` from the backward flow already sampled at the forward targets (``bwd_at``, (B,2,H,W))
    and the targets' ``inside`` mask (B,1,H,W): the inconsistency is
    :func:`~dfvo.matching.consistency.forward_backward_inconsistency`'s, computed from the same warp."""
    diff = inconsistency_at(flow_fwd, bwd_at, inside)
    finite = torch.isfinite(diff)
    mag2 = flow_fwd.pow(2).sum(1, keepdim=True) + bwd_at.pow(2).sum(1, keepdim=True)
    visible = inside & finite & (torch.where(finite, diff, torch.zeros_like(diff)).pow(2) <= alpha1 * mag2 + alpha2)
    return visible, diff


def _direction_terms(img_i: torch.Tensor, img_j: torch.Tensor, flow_ij: torch.Tensor, flow_ji: torch.Tensor,
                     alpha: float, occlusion: bool, occ_alpha1: float, occ_alpha2: float,
                     moments_i: tuple[torch.Tensor, torch.Tensor] | None = None
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    # one warp per direction: image j and the backward flow sampled together at x + F_ij(x) (grid_sample treats
    # channels independently, so this equals two warps; its gradient w.r.t. the flow is their sum)
    both, inside = warp_by_flow(torch.cat([img_j, flow_ji.to(img_j.dtype)], 1), flow_ij)
    warped, bwd_at = both[:, :3], both[:, 3:]
    if occlusion:
        visible, _ = _occlusion_from_warp(flow_ij.detach(), bwd_at.detach(), inside, occ_alpha1, occ_alpha2)
    else:
        visible = inside
    photo = _masked_mean(ssim_l1_error(img_i, warped, alpha=alpha, target_moments=moments_i), visible)
    # ||F|| in pixels, not mean-normalised (a still scene has ||F|| ~ 0; the paper regularises ||F|| itself).
    smooth = edge_aware_smoothness(flow_magnitude(flow_ij), img_i, normalise=False)
    # sqrt with a small epsilon: same value as the consistency module's norm, finite gradient at 0.
    fc_map = ((flow_ij + bwd_at).pow(2).sum(1, keepdim=True) + 1e-6).sqrt()
    fc = _masked_mean(fc_map, visible)
    return photo, smooth, fc, visible


def self_supervised_flow_loss(img1: torch.Tensor, img2: torch.Tensor,
                              flows_fwd: torch.Tensor | list[torch.Tensor],
                              flows_bwd: torch.Tensor | list[torch.Tensor], alpha: float = 0.85,
                              w_smooth: float = 0.1, w_consistency: float = 5e-3, occlusion: bool = True,
                              occ_alpha1: float = 0.01, occ_alpha2: float = 0.5,
                              weights: list[float] | None = None) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Self-supervised flow loss over scales and both directions.

    Args:
        img1: (B,3,H,W) image i. img2: (B,3,H,W) image j.
        flows_fwd: list of (B,2,H,W) flows i→j, finest first (or a single tensor).
        flows_bwd: same for j→i.
        alpha: SSIM weight of the photometric error (0.85).
        w_smooth: edge-aware smoothness weight on the flow magnitude, lambda_fs (0.1).
        w_consistency: forward-backward consistency weight, lambda_fc (5e-3).
        occlusion: mask photometric and consistency terms with the fb occlusion mask.
        occ_alpha1, occ_alpha2: occlusion thresholds (see :func:`occlusion_mask`).
        weights: per-scale weights (default ``1/2**s``).

    Returns:
        ``(total, terms)``: scalar loss and a dict of detached terms ``photometric``, ``smoothness``,
        ``consistency`` (summed over scales with weights) and ``visible_fraction`` (finest scale).
    """
    KORNIA_CHECK_SHAPE(img1, ["B", "3", "H", "W"])
    KORNIA_CHECK(img1.shape == img2.shape, f"self_supervised_flow_loss: images {tuple(img1.shape)} vs "
                                           f"{tuple(img2.shape)} differ")
    flows_fwd, flows_bwd = _as_list(flows_fwd), _as_list(flows_bwd)
    KORNIA_CHECK(len(flows_fwd) == len(flows_bwd), "self_supervised_flow_loss: fwd and bwd scale counts differ")
    weights = scale_weights(len(flows_fwd)) if weights is None else weights
    KORNIA_CHECK(len(weights) == len(flows_fwd),
                 f"self_supervised_flow_loss: {len(weights)} weights for {len(flows_fwd)} scales")
    photo_t = smooth_t = fc_t = img1.new_zeros(())
    visible_fraction = img1.new_zeros(())
    moments1, moments2 = ssim_moments(img1), ssim_moments(img2)  # each image's SSIM moments serve every scale
    for k, (w, ff, fb) in enumerate(zip(weights, flows_fwd, flows_bwd)):
        KORNIA_CHECK(ff.shape[-2:] == img1.shape[-2:],
                     f"self_supervised_flow_loss: scale {k + 1} flow {tuple(ff.shape)} is not at image size "
                     f"{tuple(img1.shape[-2:])}; upsample it first (FlowNet all_scales=True does)")
        p1, s1, c1, v1 = _direction_terms(img1, img2, ff, fb, alpha, occlusion, occ_alpha1, occ_alpha2, moments1)
        p2, s2, c2, _ = _direction_terms(img2, img1, fb, ff, alpha, occlusion, occ_alpha1, occ_alpha2, moments2)
        photo_t = photo_t + w * (p1 + p2) / 2
        smooth_t = smooth_t + w * (s1 + s2) / 2
        fc_t = fc_t + w * (c1 + c2) / 2
        if k == 0:
            visible_fraction = v1.float().mean()
    total = photo_t + w_smooth * smooth_t + w_consistency * fc_t
    terms = {"photometric": photo_t.detach(), "smoothness": smooth_t.detach(), "consistency": fc_t.detach(),
             "visible_fraction": visible_fraction.detach()}
    return total, terms
