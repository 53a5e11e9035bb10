"""Photometric error: SSIM + L1, and the per-pixel minimum over source views.

Convention:
    Images (B,3,H,W) in [0,1]; errors are per pixel (B,1,H,W), averaged over the colour channels.
"""

from __future__ import annotations

import torch
from kornia.core.check import KORNIA_CHECK_SHAPE
from kornia.filters import get_gaussian_kernel1d

INVALID_ERROR = 1e4  # error given to out-of-view pixels before the per-pixel minimum


SSIM_C1, SSIM_C2 = 0.01**2, 0.03**2  # SSIM's stabilising constants for images in [0, 1]


class _ReflectFilter3(torch.autograd.Function):
    """A normalised symmetric 3-tap filter ``(w, 1 - 2w, w)`` along one dimension of a (B,C,H,W) tensor with reflect
    padding by one sample (``F.pad(mode="reflect")`` then a valid 1-D convolution), written as ``x + w * (left + right
    - 2x)`` with in-place shifted adds (a constant stays exactly constant, so SSIM's variances ``E[x^2] - mu^2`` of a
    flat patch are exactly 0); its backward is the filter's adjoint written the same way. On a CPU this is faster than
    a depthwise ``conv2d`` of the padded tensor and its backward (the convolution library has no fast path for one
    channel per group and three taps): SSIM's forward and backward on 12 views of 96x320, 135 -> ~80 ms on one Zen 4
    thread (docs/training.md, "The losses' arithmetic")."""

    @staticmethod
    def _second_difference(x: torch.Tensor, dim: int, adjoint: bool) -> torch.Tensor:
        """``left + right - 2x`` along ``dim`` with reflected ends (``adjoint``: its transpose)."""
        n = x.shape[dim]
        d = x * -2.0
        d.narrow(dim, 1, n - 1).add_(x.narrow(dim, 0, n - 1))
        d.narrow(dim, 0, n - 1).add_(x.narrow(dim, 1, n - 1))
        if adjoint:  # sample 1 also fed out[0], sample n-2 also fed out[n-1]
            d.narrow(dim, 1, 1).add_(x.narrow(dim, 0, 1))
            d.narrow(dim, n - 2, 1).add_(x.narrow(dim, n - 1, 1))
        else:  # the reflected neighbours of the first and the last sample
            d.narrow(dim, 0, 1).add_(x.narrow(dim, 1, 1))
            d.narrow(dim, n - 1, 1).add_(x.narrow(dim, n - 2, 1))
        return d

    @staticmethod
    def forward(ctx: torch.autograd.function.FunctionCtx, x: torch.Tensor, w: float,  # type: ignore[override]
                dim: int) -> torch.Tensor:
        ctx.w, ctx.dim = w, dim  # type: ignore[attr-defined]
        # in place: a fresh output tensor of this size costs more than the arithmetic (page faults)
        return _ReflectFilter3._second_difference(x, dim, False).mul_(w).add_(x)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: torch.autograd.function.FunctionCtx, grad: torch.Tensor  # type: ignore[override]
                 ) -> tuple[torch.Tensor, None, None]:
        w, dim = ctx.w, ctx.dim  # type: ignore[attr-defined]
        return _ReflectFilter3._second_difference(grad, dim, True).mul_(w).add_(grad), None, None


def ssim_moments(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The local mean and second moment (each (B,C,H,W)) of images (B,C,H,W) under SSIM's window (:func:`ssim_map`):
    an image compared with several others (a target with its source views, at every scale) needs them once."""
    c = x.shape[1]
    moments = _filter(torch.cat([x, x * x], 1))
    return moments[:, :c], moments[:, c:]


def _filter(moments: torch.Tensor) -> torch.Tensor:
    """SSIM's 3x3 Gaussian window (sigma 1.5, reflect padding) over every channel of (B,N,H,W), as two 1-D passes."""
    kernel = get_gaussian_kernel1d(3, 1.5, device=moments.device, dtype=moments.dtype)
    w = float(kernel[0, 0])  # the outer taps; the centre one is 1 - 2w
    # contiguous (NCHW): the shifted adds along W are slower on a channels-last tensor (strided rows)
    return _ReflectFilter3.apply(_ReflectFilter3.apply(moments.contiguous(), w, -1), w, -2)


def ssim_map(x: torch.Tensor, y: torch.Tensor, eps: float = 1e-12,
             x_moments: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
    """Per-pixel, per-channel SSIM (B,C,H,W) of images (B,C,H,W) in [0,1] with a 3x3 Gaussian window (sigma 1.5) and
    reflect padding: ``kornia.metrics.ssim(x, y, 3, padding="same")``'s values (to float32 rounding, tested).

    The local moments (means, second moments, cross moment) are filtered in one stacked tensor by the window's two
    1-D passes (:class:`_ReflectFilter3`, reflect padding included) instead of kornia's ten padded convolutions.
    ``x_moments``: :func:`ssim_moments` of ``x`` when known (the same values to the bit: each channel is filtered on
    its own). Images need at least 2 rows and columns.
    """
    c = x.shape[1]
    if x_moments is None:
        mu_x, mu_y, e_xx, e_yy, e_xy = _filter(torch.cat([x, y, x * x, y * y, x * y], 1)).split(c, 1)
    else:
        mu_x, e_xx = x_moments
        mu_y, e_yy, e_xy = _filter(torch.cat([y, y * y, x * y], 1)).split(c, 1)
    mu_xx, mu_yy, mu_xy = mu_x**2, mu_y**2, mu_x * mu_y
    num = (2.0 * mu_xy + SSIM_C1) * (2.0 * (e_xy - mu_xy) + SSIM_C2)
    den = (mu_xx + mu_yy + SSIM_C1) * ((e_xx - mu_xx) + (e_yy - mu_yy) + SSIM_C2)
    return num / (den + eps)


def ssim_l1_error(target: torch.Tensor, warped: torch.Tensor, alpha: float = 0.85,
                  target_moments: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
    """Per-pixel ``alpha * (1 - SSIM) / 2 + (1 - alpha) * |I - I'|``.

    Args:
        target: (B,3,H,W) image of the target view.
        warped: (B,3,H,W) source view warped into the target.
        alpha: weight of the SSIM term (0.85 in the paper).
        target_moments: :func:`ssim_moments` of ``target`` when it is compared with several views (optional).

    Returns:
        (B,1,H,W) error, 0 for identical images; SSIM with kornia's 3x3 window (:func:`ssim_map`).
    """
    KORNIA_CHECK_SHAPE(target, ["B", "3", "H", "W"])
    KORNIA_CHECK_SHAPE(warped, ["B", "3", "H", "W"])
    if target.shape != warped.shape:
        raise ValueError(f"ssim_l1_error: target {tuple(target.shape)} and warped {tuple(warped.shape)} differ")
    l1 = (target - warped).abs().mean(1, keepdim=True)
    s = ssim_map(target, warped, x_moments=target_moments)
    dssim = ((1.0 - s) / 2.0).clamp(0.0, 1.0).mean(1, keepdim=True)
    return alpha * dssim + (1.0 - alpha) * l1


def min_over_views(errors: list[torch.Tensor], valids: list[torch.Tensor | None]) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel minimum of several (B,1,H,W) error maps, ignoring views where a pixel is out of view.

    Args:
        errors: per-view errors (B,1,H,W).
        valids: per-view (B,1,H,W) bool masks (None = valid everywhere).

    Returns:
        min_error (B,1,H,W) (0 where no view is valid) and mask (B,1,H,W) bool: at least one view valid.
    """
    if not errors or len(errors) != len(valids):
        raise ValueError(f"min_over_views: expected as many masks as errors (>0), got {len(errors)}, {len(valids)}")
    stacked = []
    any_valid = torch.zeros_like(errors[0], dtype=torch.bool)
    for err, valid in zip(errors, valids):
        KORNIA_CHECK_SHAPE(err, ["B", "1", "H", "W"])
        if valid is None:
            valid = torch.ones_like(err, dtype=torch.bool)
        stacked.append(torch.where(valid, err, torch.full_like(err, INVALID_ERROR)))
        any_valid = any_valid | valid
    best = torch.cat(stacked, 1).min(1, keepdim=True).values
    return torch.where(any_valid, best, torch.zeros_like(best)), any_valid
