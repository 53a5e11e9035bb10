"""Flow losses on hand-built cases and on the synthetic world's exact flows."""

from __future__ import annotations

import pytest
import torch

from dfvo.losses.flow_losses import (
    endpoint_error,
    multiscale_epe,
    occlusion_mask,
    scale_weights,
    self_supervised_flow_loss,
)
from dfvo.matching.consistency import forward_backward_inconsistency
from dfvo.synthetic import SyntheticWorld
from dfvo.vis.colour import flow_to_color, scalar_to_color


def test_endpoint_error_hand_values() -> None:
    gt = torch.zeros(1, 2, 4, 4)
    flow = gt.clone()
    flow[:, 0, :2] = 3.0
    flow[:, 1, :2] = 4.0  # error 5 on the top half, 0 elsewhere
    assert endpoint_error(flow, gt).item() == pytest.approx(2.5)
    valid = torch.zeros(1, 1, 4, 4, dtype=torch.bool)
    valid[:, :, :3] = True  # 8 pixels with error 5, 4 with error 0
    assert endpoint_error(flow, gt, valid).item() == pytest.approx(40 / 12)


def test_multiscale_epe_weights_each_scale_by_two_to_the_scale() -> None:
    gt = torch.zeros(2, 2, 8, 8)
    flows = [gt + torch.tensor([1.0, 0.0]).view(1, 2, 1, 1) * s for s in (1, 2, 3)]  # EPE 1, 2, 3
    total, per = multiscale_epe(flows, gt)
    assert scale_weights(3) == [0.5, 0.25, 0.125]
    assert [p.item() for p in per] == pytest.approx([1.0, 2.0, 3.0])
    assert total.item() == pytest.approx(1 / 2 + 2 / 4 + 3 / 8)
    with pytest.raises(Exception, match="weights"):
        multiscale_epe(flows, gt, weights=[1.0])


def test_occlusion_mask_hand_built() -> None:
    fwd = torch.zeros(1, 2, 6, 10)
    fwd[:, 0] = 2.0
    visible, diff = occlusion_mask(fwd, -fwd)  # consistent: visible unless the target leaves the image
    assert visible[..., :8].all() and not visible[..., 8:].any()
    assert torch.isinf(diff[..., 9]).all() and (diff[..., :8] < 1e-6).all()
    visible, _ = occlusion_mask(fwd, fwd)  # bwd points the same way: 4 px inconsistency, 16 > 0.01*8 + 0.5
    assert not visible.any()


@pytest.fixture(scope="module")
def synthetic_pairs() -> list[dict[str, torch.Tensor]]:
    out = []
    for scenario, index in (("drive", 3), ("moving_car", 4), ("rotation", 2)):
        world = SyntheticWorld(seed=1, num_frames=12, height=64, width=192, scenario=scenario)
        sample = world.render(index, right=False)
        sample["image_next"] = world.image(index + 1)
        out.append({k: v.unsqueeze(0) for k, v in sample.items() if v.dim() > 0})
    return out


def test_true_flow_is_consistent_on_visible_pixels(synthetic_pairs: list[dict[str, torch.Tensor]]) -> None:
    for s in synthetic_pairs:
        diff = forward_backward_inconsistency(s["flow_fwd"], s["flow_bwd"])
        d = diff[s["flow_fwd_valid"]]
        assert torch.isfinite(d).all()
        assert d.median() < 1e-3 and (d < 0.1).float().mean() > 0.97


def test_losses_vanish_for_the_true_flow(synthetic_pairs: list[dict[str, torch.Tensor]]) -> None:
    for s in synthetic_pairs:
        ff, fb, valid = s["flow_fwd"], s["flow_bwd"], s["flow_fwd_valid"]
        total, per = multiscale_epe([ff, ff], ff, valid)
        assert total.item() < 1e-9 and per[0].item() < 1e-9  # flow_magnitude measures a zero error as 1e-10
        _, terms = self_supervised_flow_loss(s["image"], s["image_next"], ff, fb)
        _, terms_zero = self_supervised_flow_loss(s["image"], s["image_next"], ff * 0, fb * 0)
        _, terms_off = self_supervised_flow_loss(s["image"], s["image_next"], ff + 2.0, fb - 2.0)
        assert terms["consistency"] < 0.02  # pixels; only resampling error at object edges remains
        assert terms["photometric"] < 0.02  # rendering/interpolation error only
        assert terms["photometric"] < 0.3 * terms_zero["photometric"]
        assert terms["photometric"] < 0.5 * terms_off["photometric"]
        visible, _ = occlusion_mask(ff, fb)
        iou = (visible & valid).sum() / (visible | valid).sum()
        assert iou > 0.9  # fb-based occlusion mask agrees with the true visibility


def test_self_supervised_gradients_finite_at_perfect_flow(synthetic_pairs: list[dict[str, torch.Tensor]]) -> None:
    s = synthetic_pairs[0]
    ff = s["flow_fwd"].clone().requires_grad_(True)
    fb = s["flow_bwd"].clone().requires_grad_(True)
    loss, _ = self_supervised_flow_loss(s["image"], s["image_next"], [ff, ff * 1.0], [fb, fb * 1.0])
    loss.backward()
    assert torch.isfinite(ff.grad).all() and torch.isfinite(fb.grad).all() and ff.grad.abs().sum() > 0


def test_bad_inputs_raise() -> None:
    img = torch.rand(1, 3, 8, 8)
    with pytest.raises(Exception, match="upsample"):
        self_supervised_flow_loss(img, img, [torch.zeros(1, 2, 4, 4)], [torch.zeros(1, 2, 4, 4)])
    with pytest.raises(Exception, match="differ"):
        endpoint_error(torch.zeros(1, 2, 4, 4), torch.zeros(1, 2, 4, 5))


def test_flow_colour_coding() -> None:
    flow = torch.zeros(1, 2, 2, 2)
    flow[0, :, 0, 1] = torch.tensor([1.0, 0.0])  # right -> red
    flow[0, :, 1, 0] = torch.tensor([-1.0, 0.0])  # left -> cyan (opposite hue)
    rgb = flow_to_color(flow)
    torch.testing.assert_close(rgb[0, :, 0, 0], torch.ones(3))  # zero flow is white
    torch.testing.assert_close(rgb[0, :, 0, 1], torch.tensor([1.0, 0.0, 0.0]), atol=1e-5, rtol=0)
    torch.testing.assert_close(rgb[0, :, 1, 0], torch.tensor([0.0, 1.0, 1.0]), atol=1e-5, rtol=0)
    heat = scalar_to_color(torch.tensor([[[[0.0, float("inf")], [1.0, 0.5]]]]), vmax=1.0)
    torch.testing.assert_close(heat[0, :, 0, 0], torch.zeros(3))
    torch.testing.assert_close(heat[0, :, 0, 1], torch.tensor([0.0, 0.0, 1.0]))
    torch.testing.assert_close(heat[0, :, 1, 0], torch.ones(3))


def test_one_warp_per_direction_equals_separate_warps() -> None:
    """The self-supervised loss samples image j and the backward flow in one warp per direction and derives the
    occlusion mask from it; its value and gradient equal the formulation with one warp each (image, backward flow
    for the consistency, the mask's own two warps)."""
    from dfvo.losses.flow_losses import _direction_terms
    from dfvo.losses.photometric import ssim_l1_error
    from dfvo.losses.smoothness import edge_aware_smoothness
    from dfvo.matching.flow_warp import flow_magnitude, warp_by_flow

    g = torch.Generator().manual_seed(3)
    img_i, img_j = torch.rand(2, 3, 24, 40, generator=g), torch.rand(2, 3, 24, 40, generator=g)
    f_ij = (torch.randn(2, 2, 24, 40, generator=g) * 3).requires_grad_()
    f_ji = (torch.randn(2, 2, 24, 40, generator=g) * 3).requires_grad_()

    def separate() -> torch.Tensor:
        warped, _ = warp_by_flow(img_j, f_ij)
        visible, _ = occlusion_mask(f_ij.detach(), f_ji.detach())
        m = visible.float()
        photo = (ssim_l1_error(img_i, warped) * m).sum() / m.sum()
        smooth = edge_aware_smoothness(flow_magnitude(f_ij), img_i, normalise=False)
        bwd_at, _ = warp_by_flow(f_ji, f_ij)
        fc = ((((f_ij + bwd_at) ** 2).sum(1, keepdim=True) + 1e-6).sqrt() * m).sum() / m.sum()
        return photo + smooth + fc

    ref = separate()
    ref_grads = torch.autograd.grad(ref, [f_ij, f_ji])
    photo, smooth, fc, visible = _direction_terms(img_i, img_j, f_ij, f_ji, 0.85, True, 0.01, 0.5)
    assert visible.any() and not visible.all()
    one = photo + smooth + fc
    grads = torch.autograd.grad(one, [f_ij, f_ji])
    torch.testing.assert_close(one, ref, rtol=1e-6, atol=1e-7)
    for a, b in zip(grads, ref_grads):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-8)
