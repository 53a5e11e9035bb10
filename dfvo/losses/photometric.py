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
_SSIM_EPS = 1e-12  # added to SSIM's denominator (ssim_map's default eps)


def _refuse_create_graph(what: str) -> None:
    """Raise inside a hand-written backward asked for a differentiable gradient (``autograd.grad(...,
    create_graph=True)``, double backward): it would otherwise come back as a constant, silently."""
    if torch.is_grad_enabled():
        raise RuntimeError(f"{what}: its gradient is written by hand and cannot be differentiated again "
                           "(create_graph=True / double backward)")


class _ReflectFilter3(torch.autograd.Function):
    """A normalised symmetric 3-tap filter ``(w, 1 - 2w, w)`` along one dimension of a (B,C,H,W) tensor with reflect
    padding by one sample (``F.pad(mode="reflect")`` then a valid 1-D convolution), written as one scaled copy and two
    shifted in-place ``add_(alpha=w)`` (plus the two reflected end samples); its backward is the filter's adjoint
    written the same way. On a CPU this is faster than a depthwise ``conv2d`` of the padded tensor and its backward
    (the convolution library has no fast path for one channel per group and three taps): docs/training.md, "The
    losses' arithmetic"."""

    @staticmethod
    def apply_taps(x: torch.Tensor, w: float, dim: int, adjoint: bool) -> torch.Tensor:
        """The filter along ``dim`` (``adjoint``: its transpose) of ``x`` into a new tensor."""
        n = x.shape[dim]
        out = x * (1.0 - 2.0 * w)
        out.narrow(dim, 1, n - 1).add_(x.narrow(dim, 0, n - 1), alpha=w)
        out.narrow(dim, 0, n - 1).add_(x.narrow(dim, 1, n - 1), alpha=w)
        if adjoint:  # sample 1 also fed out[0], sample n-2 also fed out[n-1]
            out.narrow(dim, 1, 1).add_(x.narrow(dim, 0, 1), alpha=w)
            out.narrow(dim, n - 2, 1).add_(x.narrow(dim, n - 1, 1), alpha=w)
        else:  # the reflected neighbours of the first and the last sample
            out.narrow(dim, 0, 1).add_(x.narrow(dim, 1, 1), alpha=w)
            out.narrow(dim, n - 1, 1).add_(x.narrow(dim, n - 2, 1), alpha=w)
        return out

    @staticmethod
    def forward(ctx: torch.autograd.function.FunctionCtx, x: torch.Tensor, w: float,  # type: ignore[override]
                dim: int) -> torch.Tensor:
        ctx.w, ctx.dim = w, dim  # type: ignore[attr-defined]
        return _ReflectFilter3.apply_taps(x, w, dim, False)

    @staticmethod
    def backward(ctx: torch.autograd.function.FunctionCtx, grad: torch.Tensor  # type: ignore[override]
                 ) -> tuple[torch.Tensor, None, None]:
        _refuse_create_graph("SSIM's window")
        return _ReflectFilter3.apply_taps(grad, ctx.w, ctx.dim, True), None, None  # type: ignore[attr-defined]


def ssim_moments(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The local mean and second moment (each (B,C,H,W)) of images (B,C,H,W) under SSIM's window (:func:`ssim_map`):
    an image compared with several others (a target with its source views, at every scale) needs them once."""
    c = x.shape[1]
    moments = _filter(torch.cat([x, x * x], 1))
    return moments[:, :c], moments[:, c:]


def _window_tap(dtype: torch.dtype) -> float:
    """The outer tap ``w`` of SSIM's 1-D Gaussian window (3 taps, sigma 1.5, normalised; the centre is 1 - 2w)."""
    return float(get_gaussian_kernel1d(3, 1.5, dtype=dtype)[0, 0])


def _filter(moments: torch.Tensor) -> torch.Tensor:
    """SSIM's 3x3 Gaussian window (sigma 1.5, reflect padding) over every channel of (B,N,H,W), as two 1-D passes."""
    w = _window_tap(moments.dtype)
    # contiguous (NCHW): the shifted adds along W are slower on a channels-last tensor (strided rows)
    return _ReflectFilter3.apply(_ReflectFilter3.apply(moments.contiguous(), w, -1), w, -2)


def _filter_adjoint(grad: torch.Tensor) -> torch.Tensor:
    """The adjoint (transpose) of :func:`_filter` applied to a (B,N,H,W) gradient: each 1-D pass's adjoint."""
    w = _window_tap(grad.dtype)
    out = grad.contiguous()
    for dim in (-2, -1):
        out = _ReflectFilter3.apply_taps(out, w, dim, True)
    return out


def ssim_map(x: torch.Tensor, y: torch.Tensor, eps: float = _SSIM_EPS,
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
    a, b, _, _, q = _ssim_factors(mu_x, e_xx, mu_y, e_yy, e_xy, eps)
    return (a * b) / q


def _ssim_factors(mu_x: torch.Tensor, e_xx: torch.Tensor, mu_y: torch.Tensor, e_yy: torch.Tensor, e_xy: torch.Tensor,
                  eps: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """SSIM ``= a b / q`` from the filtered moments (each (B,C,H,W)): ``a = 2 mu_x mu_y + C1``, ``b = 2 cov_xy + C2``,
    ``cc = mu_x^2 + mu_y^2 + C1``, ``d = var_x + var_y + C2`` and ``q = cc d + eps``; returns ``(a, b, cc, d, q)``.
    Its in-place steps act only on results that autograd does not keep, so it serves the differentiated
    :func:`ssim_map` and the hand-written :class:`_SsimL1Error` (which needs the factors for its partials) alike."""
    mu_xx, mu_yy, mu_xy = mu_x * mu_x, mu_y * mu_y, mu_x * mu_y
    a = (mu_xy * 2.0).add_(SSIM_C1)
    b = (e_xy - mu_xy).mul_(2.0).add_(SSIM_C2)
    cc = (mu_xx + mu_yy).add_(SSIM_C1)
    d = (e_xx - mu_xx).add_(e_yy - mu_yy).add_(SSIM_C2)
    return a, b, cc, d, (cc * d).add_(eps)


class _SsimL1Error(torch.autograd.Function):
    """:func:`ssim_l1_error`'s per-pixel error with its gradient w.r.t. the warped view written by hand.

    The forward is :func:`ssim_map`'s arithmetic (the same values to float rounding, tested), with the warped view's
    three moments written into one (B,3,C,H,W) buffer and filtered together. While the graph is recorded it also
    forms SSIM's three partial derivatives w.r.t. the filtered moments ``mu_y``, ``E[y^2]`` and ``E[xy]`` from the
    quotient's factors it already holds (times the clamp's mask); the backward is then one product with the incoming
    gradient, the window's adjoint over the stacked three, and the chain rule through ``y``, ``y^2`` and ``xy``,
    instead of autograd's pass back through every operation of the quotient (tested against autograd in float64 and
    by gradcheck). :func:`ssim_l1_error` keeps the autograd formulation for a ``target`` or moments that need a
    gradient and when no graph is recorded."""

    @staticmethod
    def forward(ctx: torch.autograd.function.FunctionCtx, target: torch.Tensor,  # type: ignore[override]
                warped: torch.Tensor, alpha: float, mu_x: torch.Tensor, e_xx: torch.Tensor) -> torch.Tensor:
        B, c, H, W = target.shape
        stack = torch.empty((B, 3, c, H, W), dtype=torch.result_type(target, warped), device=warped.device)
        stack[:, 0].copy_(warped)
        torch.mul(warped, warped, out=stack[:, 1])
        torch.mul(target, warped, out=stack[:, 2])
        mu_y, e_yy, e_xy = _filter(stack.view(B, 3 * c, H, W)).view(B, 3, c, H, W).unbind(1)
        a, b, cc, d, q = _ssim_factors(mu_x, e_xx, mu_y, e_yy, e_xy, _SSIM_EPS)
        s = (a * b).div_(q)
        half = (1.0 - s).mul_(0.5)
        dssim = half.clamp(0.0, 1.0).mean(1, keepdim=True)
        diff = target - warped
        l1 = diff.abs().mean(1, keepdim=True)
        if ctx.needs_input_grad[1]:
            # ds/d(mu_y, E[y^2], E[xy]) of s = a b / (cc d + eps), zero where the clamp cuts (it passes its closed band)
            inv_q = q.reciprocal_()
            partials = torch.empty_like(stack)
            torch.mul(s, cc, out=partials[:, 1]).mul_(inv_q).neg_()
            torch.mul(a, inv_q, out=partials[:, 2]).mul_(2.0)
            torch.sub(cc, d, out=d).mul_(s).mul_(mu_y)  # d is not needed any more
            torch.addcmul(d, b.sub_(a), mu_x, out=partials[:, 0]).mul_(inv_q).mul_(2.0)
            partials.mul_(((half >= 0.0) & (half <= 1.0)).unsqueeze(1))
            ctx.save_for_backward(target, warped, partials, diff.sign_())
            ctx.alpha = alpha  # type: ignore[attr-defined]
        return alpha * dssim + (1.0 - alpha) * l1

    @staticmethod
    def backward(ctx: torch.autograd.function.FunctionCtx, grad: torch.Tensor  # type: ignore[override]
                 ) -> tuple[None, torch.Tensor, None, None, None]:
        _refuse_create_graph("ssim_l1_error")
        target, warped, partials, sign = ctx.saved_tensors  # type: ignore[attr-defined]
        alpha = ctx.alpha  # type: ignore[attr-defined]
        B, c, H, W = target.shape
        # d error / d s per channel is -alpha / (2 c): SSIM's term is alpha * mean_c((1 - s) / 2)
        g_moments = partials * (grad * (-alpha / (2.0 * c))).unsqueeze(1)
        g_mu_y, g_e_yy, g_e_xy = _filter_adjoint(g_moments.view(B, 3 * c, H, W)).view(B, 3, c, H, W).unbind(1)
        # through mu_y <- y, E[y^2] <- y^2, E[xy] <- x y, and the L1 term: d|x - y|/dy = -sign(x - y)
        g_y = torch.addcmul(g_mu_y, g_e_xy, target).addcmul_(g_e_yy, warped, value=2.0)
        return None, g_y.addcmul_(sign, grad, value=-(1.0 - alpha) / c), None, None, None


def ssim_l1_error(target: torch.Tensor, warped: torch.Tensor, alpha: float = 0.85,
                  target_moments: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
    """Per-pixel ``alpha * (1 - SSIM) / 2 + (1 - alpha) * |I - I'|``.

    Args:
        target: (B,3,H,W) image of the target view.
        warped: (B,3,H,W) source view warped into the target.
        alpha: weight of the SSIM term (0.85 in the paper).
        target_moments: :func:`ssim_moments` of ``target`` when it is compared with several views (optional).

    Returns:
        (B,1,H,W) error, 0 for identical images; SSIM with kornia's 3x3 window (:func:`ssim_map`). Its gradient
        w.r.t. ``warped`` is written by hand (:class:`_SsimL1Error`) unless ``target`` or its moments need one.
    """
    KORNIA_CHECK_SHAPE(target, ["B", "3", "H", "W"])
    KORNIA_CHECK_SHAPE(warped, ["B", "3", "H", "W"])
    if target.shape != warped.shape:
        raise ValueError(f"ssim_l1_error: target {tuple(target.shape)} and warped {tuple(warped.shape)} differ")
    moments = ssim_moments(target) if target_moments is None else target_moments
    if any(m.shape != target.shape for m in moments):  # e.g. one target's moments for a batch of its copies
        try:
            moments = tuple(m.expand_as(target) for m in moments)
        except RuntimeError:
            raise ValueError(f"ssim_l1_error: target_moments of shapes {[tuple(m.shape) for m in moments]} do not "
                             f"broadcast to the target's {tuple(target.shape)}") from None
    needs_grad = torch.is_grad_enabled() and warped.requires_grad
    if needs_grad and not (target.requires_grad or any(m.requires_grad for m in moments)):
        return _SsimL1Error.apply(target, warped, alpha, *moments)
    l1 = (target - warped).abs().mean(1, keepdim=True)
    s = ssim_map(target, warped, x_moments=moments)
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
