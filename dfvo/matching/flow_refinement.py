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

with ``g = (grad I1(y) + grad I2(y + u(y))) / 2`` and the sums box filters. (Using the centre's flow in the
whole window is what makes the update stable: the plain per-pixel LK update lets checkerboard patterns in the
flow grow, because a box filter cannot see them.) A pixel is updated only where the smaller eigenvalue of the
window's mean structure tensor exceeds ``min_eigenvalue`` (intensities in [0,1], gradients per pixel); a step
is clamped to ``max_step`` pixels per component. Images are converted to grey and smoothed by a Gaussian of
``sigma`` pixels first (it widens the basin of convergence and suppresses aliasing).

Convention:
    Images (B,3,H,W) or (B,1,H,W) float in [0,1]; flow (B,2,H,W) in pixels, ``flow_1->2(x)`` = position in
    image 2 of pixel x of image 1 minus x (:mod:`dfvo.matching.flow_warp` sampling convention).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from kornia.color import rgb_to_grayscale
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE
from kornia.filters import gaussian_blur2d

from dfvo.matching.flow_warp import warp_by_flow

__all__ = ["FlowRefinementConfig", "refine_flow", "refine_forward_backward"]


@dataclass
class FlowRefinementConfig:
    """Settings of :func:`refine_flow` (``flow.refine`` in ``conf/flow/*.yaml``).

    Attributes:
        iterations: Gauss–Newton iterations (0: no refinement).
        window: side of the square window in pixels (odd).
        sigma: Gaussian pre-smoothing of the grey images, pixels (0: none).
        min_eigenvalue: pixels whose window structure tensor has a smaller minimum eigenvalue are not moved.
        max_step: largest update of one flow component in one iteration, pixels.
    """

    iterations: int = 5
    window: int = 11
    sigma: float = 1.0
    min_eigenvalue: float = 1e-6
    max_step: float = 2.0

    def __post_init__(self) -> None:
        if int(self.iterations) < 0:
            raise ValueError(f"flow.refine.iterations={self.iterations}; expected >= 0 (0 disables refinement)")
        if int(self.window) < 3 or int(self.window) % 2 == 0:
            raise ValueError(f"flow.refine.window={self.window}; expected an odd window side >= 3 pixels")
        if float(self.sigma) < 0 or float(self.min_eigenvalue) < 0 or float(self.max_step) <= 0:
            raise ValueError(f"flow.refine: sigma={self.sigma}, min_eigenvalue={self.min_eigenvalue}, max_step="
                             f"{self.max_step}; expected sigma >= 0, min_eigenvalue >= 0, max_step > 0")


def _grey(image: torch.Tensor, sigma: float) -> torch.Tensor:
    g = rgb_to_grayscale(image) if image.shape[1] == 3 else image
    if sigma > 0:
        k = 2 * int(round(3 * sigma)) + 1
        g = gaussian_blur2d(g, (k, k), (sigma, sigma), border_type="replicate", separable=True)
    return g


def _gradient(image: torch.Tensor) -> torch.Tensor:
    """Central differences (d/du, d/dv) of (B,1,H,W) with replicated borders -> (B,2,H,W).

    The same numbers as ``kornia.filters.spatial_gradient(mode="diff")``, without its 3x3 convolution (~10x slower
    on a CPU)."""
    p = F.pad(image, (1, 1, 1, 1), mode="replicate")
    return torch.cat([0.5 * (p[..., 1:-1, 2:] - p[..., 1:-1, :-2]), 0.5 * (p[..., 2:, 1:-1] - p[..., :-2, 1:-1])], 1)


def _box(x: torch.Tensor, window: int) -> torch.Tensor:
    """Mean over a ``window`` x ``window`` neighbourhood (replicate border): (B,C,H,W) float32 -> same.

    Running sums (``cumsum``) along each axis: O(1) per pixel whatever the window, several times faster on a CPU
    than pooling or depthwise convolutions. Each row (then column) has its mean removed before its running sum and
    added back after, so the sums stay small (a random walk, not a ramp) and float32 keeps them exact to ~1e-6
    of the values' spread even for flows of hundreds of pixels.
    """
    r = window // 2
    x = F.pad(x, (r + 1, r, r + 1, r), mode="replicate")
    mean = x.mean(-1, keepdim=True)
    c = (x - mean).cumsum(-1)
    x = (c[..., window:] - c[..., :-window]) / window + mean
    mean = x.mean(-2, keepdim=True)
    c = (x - mean).cumsum(-2)
    return (c[..., window:, :] - c[..., :-window, :]) / window + mean


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
    KORNIA_CHECK_SHAPE(image1, ["B", "C", "H", "W"])
    KORNIA_CHECK_SHAPE(flow, ["B", "2", "H", "W"])
    KORNIA_CHECK(image1.shape == image2.shape and image1.shape[1] in (1, 3),
                 f"refine_flow: image1 {tuple(image1.shape)} and image2 {tuple(image2.shape)} must have the same "
                 "(B,3,H,W) or (B,1,H,W) shape")
    KORNIA_CHECK(flow.shape[0] == image1.shape[0] and flow.shape[-2:] == image1.shape[-2:],
                 f"refine_flow: flow {tuple(flow.shape)} must share B, H, W with the images {tuple(image1.shape)}")
    if cfg.iterations == 0:
        return flow
    dtype = flow.dtype
    i1 = _grey(image1.to(torch.float32), float(cfg.sigma))
    i2 = _grey(image2.to(torch.float32), float(cfg.sigma))
    grad1 = _gradient(i1)  # (B,2,H,W): d/du, d/dv
    image2_and_grad = torch.cat([i2, _gradient(i2)], 1)  # (B,3,H,W)
    finite = torch.isfinite(flow).all(1, keepdim=True)  # (B,1,H,W)
    u = torch.where(finite, flow, torch.zeros_like(flow)).to(torch.float32)
    w = int(cfg.window)
    for _ in range(int(cfg.iterations)):
        warped, inside = warp_by_flow(image2_and_grad, u)
        r = warped[:, :1] - i1
        g = 0.5 * (grad1 + warped[:, 1:]) * (inside & finite)  # a target outside image 2 constrains nothing
        gx, gy = g[:, :1], g[:, 1:]
        gxx, gxy, gyy = gx * gx, gx * gy, gy * gy
        ux, uy = u[:, :1], u[:, 1:]
        sums = _box(torch.cat([gxx, gxy, gyy, gxx * ux + gxy * uy - gx * r, gxy * ux + gyy * uy - gy * r], 1), w)
        sxx, sxy, syy, bx, by = sums.unbind(1)
        det = sxx * syy - sxy * sxy
        half_trace = 0.5 * (sxx + syy)
        lam_min = half_trace - torch.sqrt((0.5 * (sxx - syy)) ** 2 + sxy * sxy)
        ok = (lam_min > cfg.min_eigenvalue) & (det > 0)
        inv_det = torch.where(ok, 1.0 / det.clamp_min(1e-30), torch.zeros_like(det))
        new = torch.stack([(syy * bx - sxy * by) * inv_det, (sxx * by - sxy * bx) * inv_det], 1)
        step = (new - u).clamp(-cfg.max_step, cfg.max_step)
        u = u + torch.where(ok.unsqueeze(1) & finite, step, torch.zeros_like(step))
    return torch.where(finite, u.to(dtype), flow)


def refine_forward_backward(images1: torch.Tensor, images2: torch.Tensor, flow_fwd: torch.Tensor,
                            flow_bwd: torch.Tensor, cfg: FlowRefinementConfig | None = None
                            ) -> tuple[torch.Tensor, torch.Tensor]:
    """Refine forward (1->2) and backward (2->1) flows in one batch of 2B pairs.

    Args:
        images1, images2: (B,3,H,W) images of the pairs. flow_fwd: (B,2,H,W) 1->2 on image 1's pixels;
        flow_bwd: (B,2,H,W) 2->1 on image 2's pixels.

    Returns:
        ``(flow_fwd, flow_bwd)`` refined, each (B,2,H,W).
    """
    B = images1.shape[0]
    refined = refine_flow(torch.cat([images1, images2]), torch.cat([images2, images1]),
                          torch.cat([flow_fwd, flow_bwd]), cfg)
    return refined[:B], refined[B:]
