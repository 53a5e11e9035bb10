"""Correlation layer against a direct per-displacement, per-pixel loop."""

from __future__ import annotations

import pytest
import torch

from dfvo.models.correlation import correlation


def _direct(f1: torch.Tensor, f2: torch.Tensor, r: int, stride: int) -> torch.Tensor:
    b, c, h, w = f1.shape
    out = torch.zeros(b, (2 * r + 1) ** 2, h, w, dtype=f1.dtype)
    for iy, dy in enumerate(range(-r, r + 1)):
        for ix, dx in enumerate(range(-r, r + 1)):
            k = iy * (2 * r + 1) + ix
            for y in range(h):
                for x in range(w):
                    y2, x2 = y + dy * stride, x + dx * stride
                    if 0 <= y2 < h and 0 <= x2 < w:
                        out[:, k, y, x] = (f1[:, :, y, x] * f2[:, :, y2, x2]).sum(1) / c
    return out


@pytest.mark.parametrize("r,stride", [(0, 1), (1, 1), (3, 1), (2, 2)])
def test_correlation_matches_direct_loop(r: int, stride: int) -> None:
    g = torch.Generator().manual_seed(r * 10 + stride)
    f1 = torch.randn(2, 5, 7, 9, generator=g, dtype=torch.float64)
    f2 = torch.randn(2, 5, 7, 9, generator=g, dtype=torch.float64)
    out = correlation(f1, f2, r, stride)
    assert out.shape == (2, (2 * r + 1) ** 2, 7, 9)
    torch.testing.assert_close(out, _direct(f1, f2, r, stride), atol=1e-12, rtol=1e-12)


def test_correlation_peaks_at_true_shift() -> None:
    """feat2 = feat1 shifted by (dx, dy) = (2, -1): the cost volume's argmax is that displacement inside."""
    g = torch.Generator().manual_seed(0)
    f1 = torch.randn(1, 128, 20, 24, generator=g)
    f2 = torch.roll(f1, shifts=(-1, 2), dims=(2, 3))  # f2[y-1, x+2] = f1[y, x]
    out = correlation(f1, f2, 3)
    best = out[0, :, 4:-4, 4:-4].argmax(0)
    k_true = (-1 + 3) * 7 + (2 + 3)
    assert (best == k_true).all()


def test_correlation_gradients_and_errors() -> None:
    f1 = torch.randn(1, 4, 6, 6, requires_grad=True)
    f2 = torch.randn(1, 4, 6, 6, requires_grad=True)
    correlation(f1, f2, 2).sum().backward()
    assert f1.grad is not None and torch.isfinite(f1.grad).all() and f2.grad.abs().sum() > 0
    with pytest.raises(Exception, match="same shape"):
        correlation(f1, f2[:, :, :5], 1)
    with pytest.raises(Exception, match="max_displacement"):
        correlation(f1, f2, -1)
