"""Flow warping and forward-backward inconsistency against flows computed by hand."""

import pytest
import torch

from dfvo.matching.consistency import forward_backward_inconsistency
from dfvo.matching.flow_warp import warp_by_flow

H, W = 24, 37


def _grid(dtype=torch.float64):
    v, u = torch.meshgrid(torch.arange(H, dtype=dtype), torch.arange(W, dtype=dtype), indexing="ij")
    return u, v


def _bilinear_field(u, v):
    """A field that bilinear interpolation reproduces exactly: a + b u + c v + d u v (two channels)."""
    return torch.stack([0.5 + 0.3 * u - 0.7 * v + 0.01 * u * v, -2.0 + 0.05 * u + 0.2 * v - 0.02 * u * v])


def test_constant_translation_matches_analytic():
    u, v = _grid()
    source = _bilinear_field(u, v).unsqueeze(0)  # (1,2,H,W)
    flow = torch.zeros(1, 2, H, W, dtype=torch.float64)
    flow[:, 0], flow[:, 1] = 2.5, -1.25
    warped, valid = warp_by_flow(source, flow)
    expected = _bilinear_field(u + 2.5, v - 1.25).unsqueeze(0)
    inside = (u + 2.5 <= W - 1) & (v - 1.25 >= 0)
    assert torch.equal(valid[0, 0], inside)
    assert valid.dtype == torch.bool and valid.shape == (1, 1, H, W)
    err = (warped - expected).abs()[:, :, inside]
    assert err.max() < 1e-5
    # the convention slip of the official code: normalising by W-1 but sampling with align_corners=False
    # reads position u*W/(W-1) - 1/2 instead of u; the analytic check above must be able to tell the difference
    tu, tv = u + 2.5, v - 1.25
    grid = torch.stack([2 * tu / (W - 1) - 1, 2 * tv / (H - 1) - 1], -1).unsqueeze(0)
    slipped = torch.nn.functional.grid_sample(source, grid, align_corners=False, padding_mode="border")
    assert (slipped - expected).abs()[:, :, inside].max() > 0.1


def test_affine_flow_matches_analytic_float32():
    u, v = _grid(torch.float32)
    A = torch.tensor([[0.97, 0.04], [-0.03, 1.02]])
    b = torch.tensor([1.3, -0.6])
    tu = A[0, 0] * u + A[0, 1] * v + b[0]
    tv = A[1, 0] * u + A[1, 1] * v + b[1]
    flow = torch.stack([tu - u, tv - v]).unsqueeze(0)
    source = torch.stack([0.1 * u + 0.2 * v, 0.3 * u - 0.05 * v, 0.001 * u * v]).unsqueeze(0)
    warped, valid = warp_by_flow(source, flow)
    expected = torch.stack([0.1 * tu + 0.2 * tv, 0.3 * tu - 0.05 * tv, 0.001 * tu * tv]).unsqueeze(0)
    inside = (tu >= 0) & (tu <= W - 1) & (tv >= 0) & (tv <= H - 1)
    assert torch.equal(valid[0, 0], inside)
    assert inside.sum() > 0.7 * H * W and (~inside).sum() > 0
    assert (warped - expected).abs()[:, :, inside].max() < 1e-5


def test_edge_targets_and_nonfinite_flow():
    source = torch.arange(H * W, dtype=torch.float64).reshape(1, 1, H, W)
    flow = torch.zeros(1, 2, H, W, dtype=torch.float64)
    flow[0, 0, 0, 0] = W - 1  # lands exactly on the last column centre: valid
    flow[0, 0, 0, 1] = W - 1  # lands half a pixel... one pixel outside: invalid
    flow[0, 1, 1, 0] = float("nan")
    warped, valid = warp_by_flow(source, flow)
    assert bool(valid[0, 0, 0, 0]) and warped[0, 0, 0, 0] == source[0, 0, 0, W - 1]
    assert not bool(valid[0, 0, 0, 1])
    assert not bool(valid[0, 0, 1, 0])
    assert torch.isfinite(warped).all()


def test_shape_errors():
    with pytest.raises(Exception, match="flow|shape"):
        warp_by_flow(torch.zeros(1, 3, H, W), torch.zeros(1, 3, H, W))
    with pytest.raises(Exception, match="must share"):
        warp_by_flow(torch.zeros(1, 3, H, W), torch.zeros(1, 2, H, W + 1))
    with pytest.raises(Exception, match="same shape"):
        forward_backward_inconsistency(torch.zeros(1, 2, H, W), torch.zeros(2, 2, H, W))


def test_inconsistency_zero_for_inverse_affine_pair_and_inf_outside():
    u, v = _grid()
    A = torch.tensor([[1.03, 0.02], [-0.01, 0.98]], dtype=torch.float64)
    b = torch.tensor([-0.8, 0.45], dtype=torch.float64)
    tu = A[0, 0] * u + A[0, 1] * v + b[0]
    tv = A[1, 0] * u + A[1, 1] * v + b[1]
    fwd = torch.stack([tu - u, tv - v]).unsqueeze(0)
    Ai = torch.linalg.inv(A)
    su = Ai[0, 0] * (u - b[0]) + Ai[0, 1] * (v - b[1])
    sv = Ai[1, 0] * (u - b[0]) + Ai[1, 1] * (v - b[1])
    bwd = torch.stack([su - u, sv - v]).unsqueeze(0)
    diff = forward_backward_inconsistency(fwd, bwd)
    inside = (tu >= 0) & (tu <= W - 1) & (tv >= 0) & (tv <= H - 1)
    assert diff.shape == (1, 1, H, W)
    assert diff[0, 0][inside].max() < 1e-5
    assert torch.isinf(diff[0, 0][~inside]).all()
    # a constant error c in the backward flow shows up as |c| everywhere inside
    c = torch.tensor([0.3, -0.4], dtype=torch.float64).view(1, 2, 1, 1)
    diff2 = forward_backward_inconsistency(fwd, bwd + c)
    assert (diff2[0, 0][inside] - 0.5).abs().max() < 1e-5


def test_inconsistency_batched_equals_single():
    g = torch.Generator().manual_seed(3)
    fwd = torch.randn(3, 2, H, W, generator=g)
    bwd = torch.randn(3, 2, H, W, generator=g)
    full = forward_backward_inconsistency(fwd, bwd)
    for b in range(3):
        single = forward_backward_inconsistency(fwd[b : b + 1], bwd[b : b + 1])
        assert torch.equal(torch.isinf(full[b : b + 1]), torch.isinf(single))
        fin = torch.isfinite(single)
        assert torch.allclose(full[b : b + 1][fin], single[fin], atol=1e-6)


def test_gradients_for_training_losses():
    """Warping is differentiable in the flow (slope of the source) and the inconsistency has finite gradients."""
    u, v = _grid()
    source = (0.3 * u - 0.7 * v).reshape(1, 1, H, W)
    flow = torch.full((1, 2, H, W), 0.25, dtype=torch.float64, requires_grad=True)
    warped, valid = warp_by_flow(source, flow)
    warped[valid].sum().backward()
    inner = valid[0, 0]
    assert torch.allclose(flow.grad[0, 0][inner], torch.full_like(flow.grad[0, 0][inner], 0.3))
    assert torch.allclose(flow.grad[0, 1][inner], torch.full_like(flow.grad[0, 1][inner], -0.7))
    fwd = torch.zeros(1, 2, H, W, dtype=torch.float64, requires_grad=True)
    bwd = torch.zeros(1, 2, H, W, dtype=torch.float64, requires_grad=True)
    diff = forward_backward_inconsistency(fwd, bwd)
    diff[torch.isfinite(diff)].sum().backward()
    assert torch.isfinite(fwd.grad).all() and torch.isfinite(bwd.grad).all()


def test_flow_magnitude_values_and_gradient_at_zero() -> None:
    """sqrt(u^2 + v^2) per pixel (3-4-5 triangles), the same values as torch's norm over the channels, and a finite
    (zero) gradient where the flow is exactly zero, as the supervised EPE needs at pixels it gets right."""
    from dfvo.matching.flow_warp import flow_magnitude

    flow = torch.tensor([[[[3.0, 0.0]], [[4.0, 0.0]]]], requires_grad=True)  # (1,2,1,2): (3,4) and (0,0)
    mag = flow_magnitude(flow)
    assert mag.shape == (1, 1, 1, 2)
    torch.testing.assert_close(mag[0, 0, 0, 0], torch.tensor(5.0))
    assert float(mag[0, 0, 0, 1]) < 1e-9
    mag.sum().backward()
    torch.testing.assert_close(flow.grad[0, :, 0, 0], torch.tensor([0.6, 0.8]))
    assert torch.equal(flow.grad[0, :, 0, 1], torch.zeros(2))
    x = torch.randn(2, 2, 8, 9, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(flow_magnitude(x), x.norm(dim=1, keepdim=True))
