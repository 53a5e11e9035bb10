"""Photometric sub-pixel refinement of a dense optical flow field (dense Lucas–Kanade, Gauss–Newton).

A flow network that is a pixel or two off everywhere is useless to DF-VO's forward-backward test (0.1 px) even
when it is in the right basin. This stage computes what can be computed from the images: starting from the
network's flow, each pixel's flow is moved to where the brightness of a window around it agrees best, so
well-textured pixels become sub-pixel accurate (and their forward and backward flows agree), while pixels the
images cannot pin down (flat regions, edges with the aperture problem) keep the network's flow and stay
inconsistent, so the selection drops them.

Model (per pixel x, window W(x) of ``window``x``window`` pixels): the flow ``u`` is constant over the window and
brightness is constant, ``I2(y + u) = I1(y)`` for ``y`` in W(x). Each pixel y of the window was last warped with
its own flow ``u(y)``; linearising ``I2(y + u) ~ I2(y + u(y)) + g(y)^T (u - u(y))`` makes one Gauss–Newton step

    A(x) u_new(x) = sum_y g g^T u(y)  -  sum_y g r(y),      A(x) = sum_y g g^T,   r = I2(y + u(y)) - I1(y),

with the sums box filters (running sums: O(1) per pixel whatever the window). (Using the centre's flow in the
whole window is what makes the update stable: the plain per-pixel LK update lets checkerboard patterns in the
flow grow, because a box filter cannot see them.) A pixel is updated only where the smaller eigenvalue of the
window's mean structure tensor exceeds ``min_eigenvalue`` (intensities in [0,1], gradients per pixel); a step
is clamped to ``max_step`` pixels per component. Images are converted to grey and smoothed by a Gaussian of
``sigma`` pixels first (it widens the basin of convergence and suppresses aliasing).

Schedule: ``coarse_iterations`` at half resolution (frames and flows area-averaged; the correction they find is
upsampled bilinearly and added), then ``iterations`` at the working resolution. A network's flow error is mostly
smooth, and a half-resolution pass removes it at a quarter of the cost per iteration with twice the basin; the
full-resolution iterations bring the textured pixels to the sub-pixel accuracy the forward-backward test needs.

Methods (``flow.refine.method``), both dense (every pixel of both flows):
    - ``inverse_compositional`` (default): ``g = grad I1(y)``, the template's own gradient. ``A`` and its inverse
      depend on the template image only, so they are computed once per *frame* (a frame is the template of one
      pair's forward flow and of the other's backward flow; :func:`refine_consecutive` prepares each frame once),
      and an iteration warps one grey channel and box-filters two. A window pixel whose target lies outside
      image 2 has ``r := 0``: it votes for keeping its own current flow. A pixel whose own target is outside
      image 2 is not moved (it cannot pass the forward-backward test anyway).
    - ``symmetric``: ``g = (grad I1(y) + grad I2(y + u(y))) / 2`` re-evaluated every iteration (a second-order
      step: fewer iterations), ``A`` re-accumulated each iteration, window pixels whose target is outside image 2
      left out of ``A`` and of the sums (and, as above, not moved themselves). About three times the work per
      iteration. ``method=symmetric iterations=5 coarse_iterations=0`` is the refinement this project used before
      (5 iterations at the working resolution).

The default (inverse compositional, 3 coarse + 2 full iterations) was chosen by measurement against the former
``symmetric`` x5: more accurate correspondences at a fraction of its CPU time (docs/speed.md, "Flow refinement",
``benchmarks/refine_schedules.py``). Refining only the candidates the selection could pick (an 11x11 window per
candidate, gathered and summed) does not pay: the selection ranks every pixel by its forward-backward
inconsistency, so it needs the forward flow at each candidate and the backward flow at the 4 pixels around each
candidate's target, well over 5000 windows per pair, which cost more than a dense iteration over both flows (the
dense box sums are O(1) per pixel; measured in docs/speed.md), and the ranking would see only the candidates.

Modes (``flow.refine.mode``): ``dense`` is the above; ``pyramid`` replaces it by the coarse-to-fine sparse
refinement at the candidates the selection can use (:mod:`dfvo.matching.pyramid_refinement`: errors of several
pixels, where a single-level window reaches ~2 px); ``dense_pyramid`` runs the dense refinement and then the pyramid
on its result. ``iterations=0`` turns every mode off.

Convention:
    Images (B,3,H,W) or (B,1,H,W) float in [0,1]; flow (B,2,H,W) in pixels, ``flow_1->2(x)`` = position in
    image 2 of pixel x of image 1 minus x (:mod:`dfvo.matching.flow_warp` sampling convention: pixel centres at
    integer coordinates, ``grid_sample(align_corners=True)``). Computation in float32 on the inputs' device;
    the result has the flow's dtype. Non-finite flow vectors are returned unchanged and constrain nothing.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from enum import StrEnum
from functools import lru_cache

import torch
import torch.nn.functional as F
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE

from dfvo.matching.image_ops import box_mean, gradient, smaller_eigenvalue, smooth
from dfvo.matching.image_ops import grey as to_grey
from dfvo.matching.pyramid_refinement import PyramidRefinementConfig, refine_pairs_pyramid, refine_pyramid
from dfvo.validation import choice

__all__ = ["RefinementMethod", "RefinementMode", "FlowRefinementConfig", "refine_flow", "refine_forward_backward",
           "refine_consecutive"]


class RefinementMethod(StrEnum):
    """See the module docstring."""

    inverse_compositional = "inverse_compositional"
    symmetric = "symmetric"


class RefinementMode(StrEnum):
    """What refines a network's flow (``flow.refine.mode``)."""

    dense = "dense"  # the dense photometric refinement of this module (every pixel)
    pyramid = "pyramid"  # only the sparse coarse-to-fine refinement at the candidates (pyramid_refinement)
    dense_pyramid = "dense_pyramid"  # the dense refinement, then the pyramid one at its candidates


@dataclass
class FlowRefinementConfig:
    """Settings of :func:`refine_flow` (``flow.refine`` in ``infer.py``'s config).

    Attributes:
        iterations: Gauss–Newton iterations at the working resolution (0: no refinement at all).
        coarse_iterations: iterations at half the resolution first (the flows' low-frequency error, where most of a
            network's error lies, converges there at a quarter of the cost; their correction is upsampled and
            added); 0: none.
        method: ``inverse_compositional`` (default) or ``symmetric`` (see the module docstring).
        window: side of the square window in pixels (odd).
        sigma: Gaussian pre-smoothing of the grey images, pixels (0: none).
        min_eigenvalue: pixels whose window structure tensor has a smaller minimum eigenvalue are not moved.
        max_step: largest update of one flow component in one iteration, pixels.
        mode: ``dense`` (this module), ``pyramid`` (the sparse coarse-to-fine refinement alone) or
            ``dense_pyramid`` (dense, then the pyramid at its candidates: errors of several pixels recovered where
            selection looks; see docs/flow.md for the measurements behind the default).
        pyramid: settings of the pyramid refinement (:class:`dfvo.matching.pyramid_refinement.PyramidRefinementConfig`).
    """

    iterations: int = 2
    coarse_iterations: int = 3
    method: RefinementMethod = RefinementMethod.inverse_compositional
    window: int = 11
    sigma: float = 1.0
    min_eigenvalue: float = 1e-6
    max_step: float = 2.0
    mode: RefinementMode = RefinementMode.dense_pyramid
    pyramid: PyramidRefinementConfig = field(default_factory=PyramidRefinementConfig)

    def __post_init__(self) -> None:
        self.mode = choice(RefinementMode, self.mode, "flow.refine.mode")
        self.method = choice(RefinementMethod, self.method, "flow.refine.method")
        if int(self.iterations) < 0:
            raise ValueError(f"flow.refine.iterations={self.iterations}; expected >= 0 (0 disables refinement)")
        if int(self.coarse_iterations) < 0:
            raise ValueError(f"flow.refine.coarse_iterations={self.coarse_iterations}; expected >= 0")
        if int(self.window) < 3 or int(self.window) % 2 == 0:
            raise ValueError(f"flow.refine.window={self.window}; expected an odd window side >= 3 pixels")
        if float(self.sigma) < 0 or float(self.min_eigenvalue) < 0 or float(self.max_step) <= 0:
            raise ValueError(f"flow.refine: sigma={self.sigma}, min_eigenvalue={self.min_eigenvalue}, max_step="
                             f"{self.max_step}; expected sigma >= 0, min_eigenvalue >= 0, max_step > 0")


def _check_inputs(image1: torch.Tensor, image2: torch.Tensor, flow: torch.Tensor, what: str) -> None:
    KORNIA_CHECK_SHAPE(image1, ["B", "C", "H", "W"])
    KORNIA_CHECK_SHAPE(flow, ["B", "2", "H", "W"])
    KORNIA_CHECK(image1.shape == image2.shape and image1.shape[1] in (1, 3),
                 f"{what}: image1 {tuple(image1.shape)} and image2 {tuple(image2.shape)} must have the same "
                 "(B,3,H,W) or (B,1,H,W) shape")
    KORNIA_CHECK(flow.shape[0] == image1.shape[0] and flow.shape[-2:] == image1.shape[-2:],
                 f"{what}: flow {tuple(flow.shape)} must share B, H, W with the images {tuple(image1.shape)}")


# ---------------------------------------------------------------------------------------- inverse compositional
@dataclass
class _Templates:
    """Per-frame data of the inverse-compositional method, (N,C,H,W) float32: ``grey`` (1), ``grad`` (2: gx, gy),
    ``prods`` (3: gxx, gxy, gyy), ``inv`` (3: entries xx, xy, yy of the inverse window structure tensor, zero where
    the pixel is not moved), ``ok`` (1, bool: smaller eigenvalue above ``min_eigenvalue``)."""

    grey: torch.Tensor
    grad: torch.Tensor
    prods: torch.Tensor
    inv: torch.Tensor
    ok: torch.Tensor


def _invert(prods: torch.Tensor, cfg: FlowRefinementConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse (xx, xy, yy) of the window means of ``prods`` (N,3,H,W) and where it is usable (N,1,H,W)."""
    sxx, sxy, syy = box_mean(prods, int(cfg.window)).split(1, 1)
    det = sxx * syy - sxy * sxy
    lam_min = smaller_eigenvalue(sxx, sxy, syy)
    ok = (lam_min > cfg.min_eigenvalue) & (det > 0)
    inv_det = torch.where(ok, 1.0 / det.clamp_min(1e-30), torch.zeros_like(det))
    return torch.cat([syy * inv_det, -sxy * inv_det, sxx * inv_det], 1), ok


def _templates(grey: torch.Tensor, cfg: FlowRefinementConfig) -> _Templates:
    """Templates of (N,1,H,W) grey frames (smoothed here)."""
    grey = smooth(grey, float(cfg.sigma))
    grad = gradient(grey)
    gx, gy = grad.split(1, 1)
    prods = torch.cat([gx * gx, gx * gy, gy * gy], 1)
    inv, ok = _invert(prods, cfg)
    return _Templates(grey, grad, prods, inv, ok)


@lru_cache(maxsize=8)
def _normalised_grid(height: int, width: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """(1,2,H,W) ``grid_sample`` coordinates (align_corners=True) of the pixel centres and (1,2,1,1) the factor from
    pixels to those units (:func:`dfvo.matching.flow_warp.normalise_pixels`); cached, never modified."""
    sx, sy = 2.0 / max(width - 1, 1), 2.0 / max(height - 1, 1)
    v, u = torch.meshgrid(torch.arange(height, device=device, dtype=torch.float32),
                          torch.arange(width, device=device, dtype=torch.float32), indexing="ij")
    base = torch.stack([u * sx - 1.0, v * sy - 1.0])[None]
    return base, torch.tensor([sx, sy], device=device, dtype=torch.float32).view(1, 2, 1, 1)


def _inside(grid: torch.Tensor) -> torch.Tensor:
    """(P,1,H,W) bool: the (P,2,H,W) ``grid_sample`` coordinates lie in image 2 (both within [-1, 1]).

    (The larger of the two absolute values, compared once: a third of the time of comparing both and reducing.)"""
    a = grid.abs()
    return torch.maximum(a[:, :1], a[:, 1:]) <= 1.0


def _refine_ic(t: _Templates, template: torch.Tensor, target: torch.Tensor, u: torch.Tensor, finite: torch.Tensor,
               cfg: FlowRefinementConfig) -> torch.Tensor:
    """Refine ``u`` (P,2,H,W) float32 (zero where not ``finite`` (P,1,H,W)) of the pairs ``t`` frame
    ``template[p]`` -> frame ``target[p]``."""
    i1, g, prods, inv, ok = (x[template] for x in (t.grey, t.grad, t.prods, t.inv, t.ok))
    i2 = t.grey[target]
    if not bool(finite.all()):  # non-finite vectors constrain nothing: their pairs' structure tensors without them
        keep = finite.to(torch.float32)
        g, prods = g * keep, prods * keep
        inv, ok = _invert(prods, cfg)
    movable = ok & finite
    base, scale = _normalised_grid(u.shape[-2], u.shape[-1], u.device)
    p_x, p_y = prods[:, :2], prods[:, 1:]  # (gxx, gxy) and (gxy, gyy)
    inv_x, inv_y = inv[:, :2], inv[:, 1:]
    w, step_max = int(cfg.window), float(cfg.max_step)
    for _ in range(int(cfg.iterations)):
        grid = torch.addcmul(base, u, scale)
        inside = _inside(grid)
        warped = F.grid_sample(i2, grid.permute(0, 2, 3, 1), mode="bilinear", padding_mode="border",
                               align_corners=True)
        r = (warped - i1).mul_(inside)
        rhs = (p_x * u[:, :1]).addcmul_(p_y, u[:, 1:]).addcmul_(g, r, value=-1.0)  # g g^T u(y) - g r
        b = box_mean(rhs, w)
        new = (inv_x * b[:, :1]).addcmul_(inv_y, b[:, 1:])
        u = u + new.sub_(u).clamp_(-step_max, step_max).mul_(movable & inside)
    return u


# ---------------------------------------------------------------------------------------- symmetric (second order)
def _prepare_symmetric(grey: torch.Tensor, cfg: FlowRefinementConfig) -> torch.Tensor:
    """(N,3,H,W) float32 per frame of (N,1,H,W) grey frames: the smoothed grey image and its gradients (gx, gy)."""
    grey = smooth(grey, float(cfg.sigma))
    return torch.cat([grey, gradient(grey)], 1)


def _refine_symmetric(frames: torch.Tensor, template: torch.Tensor, target: torch.Tensor, u: torch.Tensor,
                      finite: torch.Tensor, cfg: FlowRefinementConfig) -> torch.Tensor:
    """Refine ``u`` (P,2,H,W) float32 (zero where not ``finite`` (P,1,H,W)) of the pairs frame ``template[p]`` ->
    frame ``target[p]`` of prepared ``frames`` (:func:`_prepare_symmetric`)."""
    i1, grad1 = frames[template].split((1, 2), 1)
    image2_and_grad = frames[target]
    base, scale = _normalised_grid(u.shape[-2], u.shape[-1], u.device)
    w, step_max, eps = int(cfg.window), float(cfg.max_step), float(cfg.min_eigenvalue)
    pick_a = torch.tensor([0, 0, 1], device=u.device)
    pick_b = torch.tensor([0, 1, 1], device=u.device)
    for _ in range(int(cfg.iterations)):
        grid = torch.addcmul(base, u, scale)
        inside = _inside(grid)
        warped = F.grid_sample(image2_and_grad, grid.permute(0, 2, 3, 1), mode="bilinear", padding_mode="border",
                               align_corners=True)
        r = warped[:, :1] - i1
        g = (grad1 + warped[:, 1:]) * (0.5 * (inside & finite))  # a target outside image 2 constrains nothing
        gg = g[:, pick_a] * g[:, pick_b]  # gxx, gxy, gyy
        sums = box_mean(torch.cat([gg, gg[:, :2] * u[:, :1] + gg[:, 1:] * u[:, 1:] - g * r], 1), w)
        sxx, sxy, syy, bx, by = sums.split(1, 1)
        det = sxx * syy - sxy * sxy
        trace = sxx + syy
        # smaller eigenvalue > eps  <=>  trace > 2 eps  and  det > eps (trace - eps)
        ok = (trace > 2.0 * eps) & (det > eps * (trace - eps)) & (det > 0) & finite
        inv_det = torch.where(ok, 1.0 / det.clamp_min(1e-30), torch.zeros_like(det))
        new = torch.cat([syy * bx - sxy * by, sxx * by - sxy * bx], 1) * inv_det
        step = (new - u).clamp_(-step_max, step_max)
        u = u + step * (ok & inside)
    return u


# ---------------------------------------------------------------------------------------- public
def _half(x: torch.Tensor) -> torch.Tensor:
    """(N,C,H,W) averaged to (N,C,ceil(H/2),ceil(W/2))."""
    H, W = x.shape[-2:]
    if H % 2 == 0 and W % 2 == 0:  # (strided sums: faster than avg_pool2d on a CPU)
        return (x[..., ::2, ::2] + x[..., 1::2, ::2] + x[..., ::2, 1::2] + x[..., 1::2, 1::2]) * 0.25
    return F.interpolate(x, size=((H + 1) // 2, (W + 1) // 2), mode="area")


def _refine_pairs(frames: torch.Tensor, groups: list[tuple[slice, slice]], flow: torch.Tensor,
                  cfg: FlowRefinementConfig) -> torch.Tensor:
    """Refine the flows (P,2,H,W) of pairs of ``frames`` (N,C,H,W), each frame prepared once per resolution:
    ``coarse_iterations`` at half resolution, then ``iterations``.

    ``groups`` lists (template frames, target frames) ranges of equal length, one pair per flow row, in the order of
    ``flow``'s rows; the ranges are views of the prepared frames (no per-pair copies)."""
    if cfg.method == RefinementMethod.symmetric:
        prepare, refine = _prepare_symmetric, _refine_symmetric
    else:
        prepare, refine = _templates, _refine_ic
    rows, start = [], 0
    for template, target in groups:
        n = template.stop - template.start
        rows.append((template, target, slice(start, start + n)))
        start += n

    def refine_groups(prepared: object, u: torch.Tensor, finite: torch.Tensor, c: FlowRefinementConfig
                      ) -> torch.Tensor:
        parts = [refine(prepared, template, target, u[r], finite[r], c) for template, target, r in rows]
        return parts[0] if len(parts) == 1 else torch.cat(parts)

    grey = to_grey(frames)
    finite = torch.isfinite(flow).all(1, keepdim=True)  # (P,1,H,W)
    u = torch.where(finite, flow, torch.zeros_like(flow)).to(torch.float32)
    H, W = flow.shape[-2:]
    if int(cfg.coarse_iterations) > 0 and min(H, W) >= 16:
        coarse = replace(cfg, iterations=int(cfg.coarse_iterations))
        grey_small = _half(grey)
        h, w = grey_small.shape[-2:]
        factor = torch.tensor([w / W, h / H], device=flow.device, dtype=torch.float32).view(1, 2, 1, 1)
        start = _half(u) * factor
        if bool(finite.all()):
            finite_small = torch.ones_like(start[:, :1], dtype=torch.bool)
        else:
            finite_small = _half(finite.to(torch.float32)) > 0.999  # all of its pixels finite
        refined = refine_groups(prepare(grey_small, coarse), start, finite_small, coarse)
        u = u + F.interpolate(refined - start, size=(H, W), mode="bilinear", align_corners=False) / factor
    u = refine_groups(prepare(grey, cfg), u, finite, cfg)
    return torch.where(finite, u.to(flow.dtype), flow)


def refine_flow(image1: torch.Tensor, image2: torch.Tensor, flow: torch.Tensor,
                cfg: FlowRefinementConfig | None = None) -> torch.Tensor:
    """Refine ``flow`` (1->2) by window-consistent Gauss–Newton on brightness constancy (see module docstring).

    Args:
        image1: (B,3,H,W) or (B,1,H,W) first image, [0,1].
        image2: second image, same shape.
        flow: (B,2,H,W) initial flow 1->2 in pixels.
        cfg: settings (defaults: :class:`FlowRefinementConfig`).

    Returns:
        (B,2,H,W) refined flow 1->2 (same dtype as ``flow``); pixels the images cannot constrain are unchanged, and
        so are non-finite flow vectors (they constrain nothing around them either).
    """
    cfg = cfg or FlowRefinementConfig()
    _check_inputs(image1, image2, flow, "refine_flow")
    if cfg.iterations == 0:
        return flow
    B = image1.shape[0]
    return _refine_pairs(torch.cat([image1, image2]), [(slice(0, B), slice(B, 2 * B))], flow, cfg)


def refine_forward_backward(images1: torch.Tensor, images2: torch.Tensor, flow_fwd: torch.Tensor,
                            flow_bwd: torch.Tensor, cfg: FlowRefinementConfig | None = None
                            ) -> tuple[torch.Tensor, torch.Tensor]:
    """Refine forward (1->2) and backward (2->1) flows of B pairs in one batch of 2B.

    Args:
        images1, images2: (B,3,H,W) images of the pairs. flow_fwd: (B,2,H,W) 1->2 on image 1's pixels;
        flow_bwd: (B,2,H,W) 2->1 on image 2's pixels.

    Returns:
        ``(flow_fwd, flow_bwd)`` refined, each (B,2,H,W); the same numbers as :func:`refine_flow` on each.
    """
    cfg = cfg or FlowRefinementConfig()
    _check_inputs(images1, images2, flow_fwd, "refine_forward_backward")
    _check_inputs(images2, images1, flow_bwd, "refine_forward_backward")
    B = images1.shape[0]
    if cfg.iterations == 0:
        return flow_fwd, flow_bwd
    if cfg.mode == RefinementMode.pyramid:
        return refine_pairs_pyramid(images1, images2, flow_fwd, flow_bwd, cfg.pyramid)
    groups = [(slice(0, B), slice(B, 2 * B)), (slice(B, 2 * B), slice(0, B))]
    refined = _refine_pairs(torch.cat([images1, images2]), groups, torch.cat([flow_fwd, flow_bwd]), cfg)
    if cfg.mode == RefinementMode.dense_pyramid:
        return refine_pairs_pyramid(images1, images2, refined[:B], refined[B:], cfg.pyramid)
    return refined[:B], refined[B:]


def refine_consecutive(images: torch.Tensor, flow_fwd: torch.Tensor, flow_bwd: torch.Tensor,
                       cfg: FlowRefinementConfig | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Refine the flows of the B consecutive pairs (k, k+1) of B+1 frames; each frame is prepared once.

    The same numbers as :func:`refine_forward_backward` ``(images[:-1], images[1:], ...)``; the
    inverse-compositional method computes each frame's grey image, gradients and inverse structure tensors once
    for both of the pairs it belongs to.

    Args:
        images: (B+1,3,H,W) frames in order. flow_fwd: (B,2,H,W) k->k+1 on frame k's pixels; flow_bwd:
            (B,2,H,W) k+1->k on frame k+1's pixels.

    Returns:
        ``(flow_fwd, flow_bwd)`` refined, each (B,2,H,W).
    """
    cfg = cfg or FlowRefinementConfig()
    KORNIA_CHECK_SHAPE(images, ["N", "C", "H", "W"])
    B = images.shape[0] - 1
    KORNIA_CHECK(B >= 1 and flow_fwd.shape[0] == B and flow_bwd.shape == flow_fwd.shape,
                 f"refine_consecutive: {images.shape[0]} frames need {images.shape[0] - 1} forward and backward "
                 f"flows; got {tuple(flow_fwd.shape)} and {tuple(flow_bwd.shape)}")
    _check_inputs(images[:-1], images[1:], flow_fwd, "refine_consecutive")
    if cfg.iterations == 0:
        return flow_fwd, flow_bwd
    if cfg.mode == RefinementMode.pyramid:
        return refine_pyramid(images, flow_fwd, flow_bwd, cfg.pyramid)
    refined = _refine_pairs(images, [(slice(0, B), slice(1, B + 1)), (slice(1, B + 1), slice(0, B))],
                            torch.cat([flow_fwd, flow_bwd]), cfg)
    if cfg.mode == RefinementMode.dense_pyramid:
        return refine_pyramid(images, refined[:B], refined[B:], cfg.pyramid)
    return refined[:B], refined[B:]
