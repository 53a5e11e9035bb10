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


def _autograd_reference(f1: torch.Tensor, f2: torch.Tensor, r: int, stride: int) -> torch.Tensor:
    """The layer as autograd differentiates it: a multiply and a channel sum per displacement of the padded feat2."""
    c, h, w = f1.shape[1:]
    f2p = torch.nn.functional.pad(f2, (r * stride,) * 4)
    return torch.stack([(f1 * f2p[:, :, iy * stride: iy * stride + h, ix * stride: ix * stride + w]).sum(1)
                        for iy in range(2 * r + 1) for ix in range(2 * r + 1)], 1) / c


@pytest.mark.parametrize("r,stride", [(0, 1), (1, 1), (2, 2), (3, 1)])
def test_correlation_gradient_is_the_derivative(r: int, stride: int) -> None:
    """The hand-written backward passes torch.autograd.gradcheck (float64, both inputs)."""
    g = torch.Generator().manual_seed(7 + r)
    f1 = torch.randn(2, 3, 5, 6, generator=g, dtype=torch.float64, requires_grad=True)
    f2 = torch.randn(2, 3, 5, 6, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: correlation(a, b, r, stride), (f1, f2))


@pytest.mark.parametrize("dtypes", [(torch.float32, torch.float32), (torch.bfloat16, torch.bfloat16),
                                    (torch.bfloat16, torch.float32)])
def test_correlation_values_are_autograds_to_the_bit_and_gradients_to_rounding(
        dtypes: tuple[torch.dtype, torch.dtype]) -> None:
    """In each precision a training step meets (bf16 features against float32 warped ones under autocast), the values
    equal the autograd formulation's bit for bit and the gradients it gives (same dtypes as the inputs) agree to the
    precision's rounding."""
    g = torch.Generator().manual_seed(11)
    f1 = torch.randn(2, 16, 12, 20, generator=g).to(dtypes[0]).requires_grad_(True)
    f2 = torch.randn(2, 16, 12, 20, generator=g).to(dtypes[1]).requires_grad_(True)
    ours, ref = correlation(f1, f2, 3), _autograd_reference(f1, f2, 3, 1)
    assert ours.dtype == ref.dtype and torch.equal(ours, ref)
    weight = torch.randn(ours.shape, generator=g)
    g_ours = torch.autograd.grad((ours.float() * weight).sum(), (f1, f2))
    g_ref = torch.autograd.grad((ref.float() * weight).sum(), (f1, f2))
    for a, b, dt in zip(g_ours, g_ref, dtypes):
        assert a.dtype == b.dtype == dt
        tol = 1e-5 if dt == torch.float32 else 3e-2  # bf16: autograd sums 49 bf16 terms, ours in float32
        torch.testing.assert_close(a.float(), b.float(), rtol=tol, atol=tol * b.float().abs().max().item())


def test_correlation_without_gradients_is_the_same_to_the_bit() -> None:
    """Inference (no gradient wanted) takes the plain tensor path, with the training path's values to the bit."""
    g = torch.Generator().manual_seed(13)
    f1 = torch.randn(2, 16, 12, 20, generator=g).to(torch.bfloat16)
    f2 = torch.randn(2, 16, 12, 20, generator=g)
    with torch.no_grad():
        plain = correlation(f1, f2, 2)
    trained = correlation(f1.requires_grad_(True), f2, 2)
    assert trained.grad_fn is not None and plain.grad_fn is None
    assert torch.equal(plain, trained.detach()) and torch.equal(plain, _autograd_reference(f1.detach(), f2, 2, 1))
