"""Correlation (cost volume) layer in plain PyTorch: no CUDA or CuPy build, runs wherever PyTorch runs.

Convention:
    - Features are (B,C,H,W). The cost volume compares pixel ``x`` of ``feat1`` with pixel ``x + d`` of
      ``feat2`` for every integer displacement ``d = (dx, dy)`` with ``|dx|, |dy| <= max_displacement``
      (in pixels of the feature map, multiplied by ``stride`` when a dilated search is asked for).
    - Output channel ``k = (dy + R) * (2R + 1) + (dx + R)`` (row-major over (dy, dx), ``R`` the radius),
      value ``mean_c feat1[c, y, x] * feat2[c, y + dy, x + dx]``; positions outside ``feat2`` count as 0.
    - Memory is bounded: one displacement's product is materialised at a time (``B*C*H*W`` extra elements), never
      the ``(2R+1)^2`` stack of shifted features. (A multiply and a channel sum per displacement: on a CPU faster than
      an einsum per row of displacements, whose batched matrix products are tiny.)
    - The gradient is written by hand (:class:`_Correlation`): per displacement one fused multiply-add into each
      input's gradient, accumulated in the products' precision (float32 when either input is), instead of autograd's
      multiply, zero-padded slice gradient and sum per displacement -- ~2x faster on a CPU (``python
      benchmarks/train_step.py``); the forward values are the same to the bit.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE


def correlation(feat1: torch.Tensor, feat2: torch.Tensor, max_displacement: int, stride: int = 1) -> torch.Tensor:
    """Local cost volume between two feature maps.

    Args:
        feat1: (B,C,H,W) features of the reference image.
        feat2: (B,C,H,W) features of the other image (usually already warped by the current flow).
        max_displacement: search radius ``R`` in displacement steps (>= 0).
        stride: pixels between two displacement steps (1 = dense search, 2 = every other pixel, ...).

    Returns:
        (B,(2R+1)^2,H,W) channel-averaged dot products, ordered as in the module docstring.
    """
    KORNIA_CHECK_SHAPE(feat1, ["B", "C", "H", "W"])
    KORNIA_CHECK_SHAPE(feat2, ["B", "C", "H", "W"])
    KORNIA_CHECK(feat1.shape == feat2.shape,
                 f"correlation: feat1 {tuple(feat1.shape)} and feat2 {tuple(feat2.shape)} must have the same shape")
    KORNIA_CHECK(max_displacement >= 0 and stride >= 1,
                 f"correlation: need max_displacement >= 0 and stride >= 1, got {max_displacement}, {stride}")
    pad = max_displacement * stride
    dtype = torch.promote_types(feat1.dtype, feat2.dtype)
    # the products' precision once, not per displacement (exact: each product is computed in it anyway)
    f1, f2 = feat1.to(dtype), F.pad(feat2.to(dtype), (pad, pad, pad, pad))
    if torch.is_grad_enabled() and (feat1.requires_grad or feat2.requires_grad):
        return _Correlation.apply(f1, f2, max_displacement, stride)
    return _cost_volume(f1, f2, max_displacement, stride)  # inference and export: plain tensor operations


def _cost_volume(f1: torch.Tensor, f2: torch.Tensor, r: int, stride: int) -> torch.Tensor:
    """The cost volume (module docstring) of ``f1`` (B,C,h,w) against ``f2`` (B,C,h+2p,w+2p) zero-padded by ``p = r *
    stride``, one displacement at a time."""
    c, h, w = f1.shape[1:]
    costs = []
    for iy in range(2 * r + 1):
        for ix in range(2 * r + 1):
            costs.append((f1 * f2[:, :, iy * stride: iy * stride + h, ix * stride: ix * stride + w]).sum(1))
    return torch.stack(costs, 1) / c


class _Correlation(torch.autograd.Function):
    """:func:`correlation` with its gradient written by hand (module docstring)."""

    @staticmethod
    def forward(ctx: torch.autograd.function.FunctionCtx, f1: torch.Tensor, f2: torch.Tensor,  # type: ignore[override]
                r: int, stride: int) -> torch.Tensor:
        """``f1`` (B,C,h,w) and the zero-padded ``f2`` in their common dtype (as :func:`correlation` makes them)."""
        ctx.save_for_backward(f1, f2)
        ctx.geometry = (r, stride)  # type: ignore[attr-defined]
        return _cost_volume(f1, f2, r, stride)

    @staticmethod
    def backward(ctx: torch.autograd.function.FunctionCtx, grad: torch.Tensor  # type: ignore[override]
                 ) -> tuple[torch.Tensor | None, torch.Tensor | None, None, None]:
        if torch.is_grad_enabled():  # autograd.grad(..., create_graph=True): a silent constant otherwise
            raise RuntimeError("correlation: its gradient is written by hand and cannot be differentiated again "
                               "(create_graph=True / double backward)")
        f1, f2 = ctx.saved_tensors  # type: ignore[attr-defined]
        r, stride = ctx.geometry  # type: ignore[attr-defined]
        need1, need2 = ctx.needs_input_grad[:2]
        c, h, w = f1.shape[1:]
        g = (grad / c).to(f1.dtype)
        g1 = torch.zeros_like(f1) if need1 else None
        g2 = torch.zeros_like(f2) if need2 else None
        k = 0
        for iy in range(2 * r + 1):
            for ix in range(2 * r + 1):
                gk = g[:, k:k + 1]
                rows, cols = slice(iy * stride, iy * stride + h), slice(ix * stride, ix * stride + w)
                if g1 is not None:
                    g1.addcmul_(gk, f2[:, :, rows, cols])
                if g2 is not None:
                    g2[:, :, rows, cols].addcmul_(gk, f1)
                k += 1
        # the gradient of the padded f2 (autograd takes it back through the pad and both inputs' casts)
        return g1, g2, None, None
