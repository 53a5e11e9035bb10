"""The refinements' image operations (one copy for the dense and the pyramid refinement) against independent
references: kornia's grey and gradient, and a float64 box filter."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from kornia.color import rgb_to_grayscale
from kornia.filters import spatial_gradient

from dfvo.matching.image_ops import box_mean, gradient, grey, shi_tomasi, smooth


def _box64(x: torch.Tensor, window: int) -> torch.Tensor:
    r = window // 2
    return F.avg_pool2d(F.pad(x.double(), (r, r, r, r), mode="replicate"), window, stride=1)


def test_box_mean_keeps_float32_precision_on_large_values() -> None:
    """Values of hundreds (flows, products of gradients): the mean-removed running sums stay within ~1e-5 relative
    of a float64 box filter, where plain float32 running sums along a 640-pixel row lose an order of magnitude more."""
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 3, 96, 640, generator=g) * 100 + 300
    for window in (7, 11):
        ref = _box64(x, window)
        assert float((box_mean(x, window).double() - ref).abs().max()) < 1e-4
        padded = F.pad(x, (window // 2 + 1, window // 2, window // 2 + 1, window // 2), mode="replicate")
        c = padded.cumsum(-1)
        plain = c[..., window:] - c[..., :-window]
        c = plain.cumsum(-2)
        plain = (c[..., window:, :] - c[..., :-window, :]) / (window * window)
        assert float((plain.double() - ref).abs().max()) > 3 * float((box_mean(x, window).double() - ref).abs().max())


def test_gradient_and_grey_are_kornias_numbers() -> None:
    img = torch.rand(2, 3, 40, 56, generator=torch.Generator().manual_seed(1))
    g = grey(img)
    assert g.dtype == torch.float32 and torch.equal(g, rgb_to_grayscale(img))
    assert grey(g) is g  # already grey
    assert torch.equal(gradient(g), spatial_gradient(g, mode="diff")[:, 0])


def test_smooth_keeps_constants_and_zero_sigma_is_identity() -> None:
    flat = torch.full((1, 1, 20, 30), 0.25)
    assert torch.allclose(smooth(flat, 1.0), flat, atol=1e-7)
    x = torch.rand(1, 1, 20, 30)
    assert smooth(x, 0.0) is x
    assert float(smooth(x, 1.5).std()) < float(x.std())


def test_box_sums_equal_a_direct_window_mean() -> None:
    """The running-sum box filter equals average pooling over the replicate-padded map, also for large offsets."""
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 3, 37, 53, generator=g) + torch.tensor([0.0, 200.0, -50.0]).view(1, 3, 1, 1)
    for window in (3, 11):
        r = window // 2
        ref = F.avg_pool2d(F.pad(x.double(), (r, r, r, r), mode="replicate"), window, stride=1)
        torch.testing.assert_close(box_mean(x, window).double(), ref, atol=2e-5, rtol=0)


def test_shi_tomasi_is_the_window_structure_tensor_s_smaller_eigenvalue() -> None:
    """Against float64 eigenvalues (torch.linalg.eigvalsh) of the window mean of g g^T, the gradients by hand; and
    hand-derived cases: a ramp I = a u has the structure tensor [[a^2, 0], [0, 0]] (score 0, an edge's aperture
    problem), I = a u^2 / 2 + b v^2 / 2 at its centre pixel the window mean of diag((a u)^2, (b v)^2), so its score
    is min(a^2, b^2) * (w^2 - 1) / 12 (the mean of a window's squared offsets)."""
    g = torch.Generator().manual_seed(1)
    img = torch.rand(1, 1, 40, 50, generator=g, dtype=torch.float64)
    p = F.pad(img, (1, 1, 1, 1), mode="replicate")
    gx, gy = 0.5 * (p[..., 1:-1, 2:] - p[..., 1:-1, :-2]), 0.5 * (p[..., 2:, 1:-1] - p[..., :-2, 1:-1])
    s = _box64(torch.cat([gx * gx, gx * gy, gy * gy], 1), 7)
    A = torch.stack([torch.stack([s[0, 0], s[0, 1]], -1), torch.stack([s[0, 1], s[0, 2]], -1)], -2)
    ref = torch.linalg.eigvalsh(A)[..., 0]
    assert float((shi_tomasi(img.float(), 7, 0.0)[0, 0].double() - ref).abs().max()) < 1e-6
    v, u = torch.meshgrid(torch.arange(41.0) - 20, torch.arange(61.0) - 30, indexing="ij")
    assert float(shi_tomasi((0.01 * u)[None, None], 11, 0.0)[0, 0, 5:-5, 5:-5].abs().max()) < 1e-9
    a, b, w = 0.002, 0.001, 11
    bowl = (0.5 * a * u**2 + 0.5 * b * v**2)[None, None]
    expected = min(a, b) ** 2 * (w * w - 1) / 12
    assert float(shi_tomasi(bowl, w, 0.0)[0, 0, 20, 30]) == pytest.approx(expected, rel=1e-4)
