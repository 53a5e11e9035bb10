"""Self-supervised depth losses: photometric error, warping by depth + pose, smoothness, depth consistency."""

from __future__ import annotations

import pytest
import torch

from dfvo.geometry.camera import pixel_grid
from dfvo.losses.depth_consistency import depth_consistency_loss, inverse_depth_difference
from dfvo.losses.photometric import min_over_views, ssim_l1_error
from dfvo.losses.reprojection import reproject
from dfvo.losses.smoothness import edge_aware_smoothness
from dfvo.synthetic import SyntheticWorld

H, W = 64, 192


@pytest.fixture(scope="module")
def world_frame() -> dict:
    world = SyntheticWorld(seed=0, num_frames=6, height=H, width=W, scenario="straight")
    frame = world.render(2, right=True, flow=True)
    poses = world.poses()
    frame["image_next"] = world.image(3)
    frame["T_next_cur"] = (torch.linalg.inv(poses[3]) @ poses[2]).float()
    return frame


def test_ssim_l1_error_constant_images_by_hand() -> None:
    a, b = torch.full((1, 3, 8, 8), 0.5), torch.full((1, 3, 8, 8), 0.6)
    assert ssim_l1_error(a, a).abs().max() < 1e-6
    # constant patches: SSIM = (2 mu_a mu_b + C1) / (mu_a^2 + mu_b^2 + C1), C1 = 0.01^2
    ssim = (2 * 0.5 * 0.6 + 1e-4) / (0.25 + 0.36 + 1e-4)
    expected = 0.85 * (1 - ssim) / 2 + 0.15 * 0.1
    err = ssim_l1_error(a, b)
    assert err.shape == (1, 1, 8, 8)
    assert torch.allclose(err[..., 2:-2, 2:-2], torch.full((1, 1, 4, 4), expected), atol=1e-5)
    assert torch.allclose(ssim_l1_error(a, b, alpha=0.0), torch.full((1, 1, 8, 8), 0.1), atol=1e-6)


def test_min_over_views_ignores_out_of_view() -> None:
    e1 = torch.tensor([1.0, 2.0, 3.0, 4.0]).reshape(1, 1, 1, 4)
    e2 = torch.tensor([2.0, 1.0, 0.5, 9.0]).reshape(1, 1, 1, 4)
    v1 = torch.tensor([True, True, True, False]).reshape(1, 1, 1, 4)
    v2 = torch.tensor([True, True, False, False]).reshape(1, 1, 1, 4)
    best, mask = min_over_views([e1, e2], [v1, v2])
    assert best.flatten().tolist() == [1.0, 1.0, 3.0, 0.0]
    assert mask.flatten().tolist() == [True, True, True, False]


def test_reproject_matches_true_flow(world_frame: dict) -> None:
    """Warping by the true depth and pose lands exactly where the world's true flow says (static pixels)."""
    f = world_frame
    rep = reproject(f["image_next"][None], f["depth"][None], f["T_next_cur"][None], f["K"][None])
    u = (rep.grid[0, ..., 0] + 1) / 2 * (W - 1)
    v = (rep.grid[0, ..., 1] + 1) / 2 * (H - 1)
    grid = pixel_grid(H, W)
    flow = torch.stack([u - grid[..., 0], v - grid[..., 1]])
    static = f["flow_fwd_valid"][0] & ~f["dynamic_mask"][0]
    assert static.float().mean() > 0.4
    assert (rep.valid[0, 0] | ~static).all()
    assert (flow - f["flow_fwd"])[:, static].abs().max() < 1e-2


def test_reproject_masks_out_of_view() -> None:
    K = torch.tensor([[[50.0, 0, 15.5], [0, 50.0, 7.5], [0, 0, 1]]])
    T = torch.eye(4)[None].clone()
    T[0, 0, 3] = 1.0  # source camera 1 m to the left: points shift right by 50 px at 1 m depth
    rep = reproject(torch.rand(1, 3, 16, 32), torch.ones(1, 1, 16, 32), T, K)
    # u + 50 stays inside [0, 31] for no column
    assert not rep.valid.any()
    T[0, 0, 3] = 0.1  # shift of 5 px: the last 5 columns leave the image
    rep = reproject(torch.rand(1, 3, 16, 32), torch.ones(1, 1, 16, 32), T, K)
    assert rep.valid[0, 0, :, :27].all() and not rep.valid[0, 0, :, 27:].any()
    T[0, 2, 3] = -2.0  # points end up behind the source camera
    assert not reproject(torch.rand(1, 3, 16, 32), torch.ones(1, 1, 16, 32), T, K).valid.any()


@pytest.mark.parametrize("view", ["next", "stereo"])
def test_photometric_small_for_true_depth_and_grows_with_wrong_depth(world_frame: dict, view: str) -> None:
    f = world_frame
    src, T = (f["image_next"], f["T_next_cur"]) if view == "next" else (f["image_right"], f["T_right_left"].float())
    static = ~f["dynamic_mask"][0, 0] & (f["depth"][0, 0] < 999)  # not sky, not moving cars
    medians, means = [], []
    for factor in (1.0, 0.8, 1.25):
        rep = reproject(src[None], f["depth"][None] * factor, T[None], f["K"][None])
        err = ssim_l1_error(f["image"][None], rep.warped)[0, 0]
        m = static & rep.valid[0, 0]
        if view == "next":
            m &= f["flow_fwd_valid"][0]  # occlusions are the per-pixel minimum's job, not this test's
        medians.append(err[m].median())
        means.append(err[m].mean())
    assert medians[0] < 5e-3  # a perfect warp: error only from resampling texture at 64x192
    assert medians[1] > 2 * medians[0] and medians[2] > 2 * medians[0]
    assert means[1] > means[0] and means[2] > means[0]


def test_smoothness_by_hand() -> None:
    img = torch.zeros(1, 3, 4, 5)
    assert edge_aware_smoothness(torch.full((1, 1, 4, 5), 3.0), img) == 0
    ramp = torch.arange(1.0, 6.0).reshape(1, 1, 1, 5).expand(1, 1, 4, 5)
    # normalised by its mean 3: x-steps of 1/3 everywhere, no y-steps
    assert torch.allclose(edge_aware_smoothness(ramp, img), torch.tensor(1 / 3))
    assert torch.allclose(edge_aware_smoothness(ramp, img, normalise=False), torch.tensor(1.0))
    # scaling the field does not change the normalised loss
    assert torch.allclose(edge_aware_smoothness(7 * ramp, img), torch.tensor(1 / 3))
    # a step in the field coinciding with an image edge of height 1 is down-weighted by exp(-1)
    step = torch.zeros(1, 1, 4, 5)
    step[..., 3:] = 1.0
    edge = torch.zeros(1, 3, 4, 5)
    edge[..., 3:] = 1.0
    plain = edge_aware_smoothness(step, img, normalise=False)
    assert torch.allclose(plain, torch.tensor(4 / 16))
    assert torch.allclose(edge_aware_smoothness(step, edge, normalise=False), plain * torch.exp(torch.tensor(-1.0)))
    with pytest.raises(ValueError, match="resolution"):
        edge_aware_smoothness(step, torch.zeros(1, 3, 4, 6))


def test_depth_consistency_by_hand() -> None:
    z = torch.full((1, 1, 2, 2), 2.0)
    d = torch.tensor([2.0, 4.0, 1.0, 2.0]).reshape(1, 1, 2, 2)
    diff = inverse_depth_difference(z, d)
    assert torch.allclose(diff.flatten(), torch.tensor([0.0, 0.25, 0.5, 0.0]))
    other = torch.tensor([0.1, 0.1, 0.1, 0.1]).reshape(1, 1, 2, 2)
    valid_other = torch.tensor([True, True, False, True]).reshape(1, 1, 2, 2)
    loss = depth_consistency_loss([diff, other], [None, valid_other])
    assert torch.allclose(loss, torch.tensor((0.0 + 0.1 + 0.5 + 0.0) / 4))


def test_consistency_zero_for_true_depths(world_frame: dict) -> None:
    """Two views of the true depth agree: 1/z_j equals the next frame's depth sampled at the projection."""
    f = world_frame
    world = SyntheticWorld(seed=0, num_frames=6, height=H, width=W, scenario="straight")
    depth_next = world.depth(3)[None]
    rep = reproject(depth_next, f["depth"][None], f["T_next_cur"][None], f["K"][None])
    diff = inverse_depth_difference(rep.depth_in_source, rep.warped)[0, 0]
    static = f["flow_fwd_valid"][0] & ~f["dynamic_mask"][0, 0]
    # bilinear sampling of a piecewise-smooth depth: exact up to interpolation inside surfaces
    assert diff[static].median() < 1e-4
    assert inverse_depth_difference(rep.depth_in_source, rep.warped * 1.5)[0, 0][static].median() > 1e-2


def test_ssim_map_is_kornias_ssim() -> None:
    """The stacked-moment SSIM equals kornia.metrics.ssim (3x3 Gaussian window, reflect padding) computed in float64
    to float32 rounding (kornia's own float32 values are 3e-6 from it), on random images and on an image against
    itself (1 everywhere), and so does its gradient."""
    from kornia.metrics import ssim

    from dfvo.losses.photometric import ssim_map

    g = torch.Generator().manual_seed(1)
    x, y = torch.rand(2, 3, 17, 23, generator=g), torch.rand(2, 3, 17, 23, generator=g, requires_grad=True)
    y64 = y.detach().double().requires_grad_(True)
    ours, ref = ssim_map(x, y), ssim(x.double(), y64, 3, max_val=1.0, padding="same")
    torch.testing.assert_close(ours.double(), ref, rtol=0, atol=1e-5)
    torch.testing.assert_close(torch.autograd.grad(ours.sum(), y)[0].double(), torch.autograd.grad(ref.sum(), y64)[0],
                               rtol=1e-5, atol=5e-5)
    torch.testing.assert_close(ssim_map(x, x), torch.ones_like(x), rtol=0, atol=1e-5)


@pytest.mark.parametrize("shape", [(2, 5, 7, 9), (1, 3, 2, 2), (1, 2, 3, 11)])
def test_ssim_window_pass_is_a_reflect_padded_convolution_and_its_adjoint(shape: tuple[int, ...]) -> None:
    """SSIM's 1-D window pass (a scaled copy and shifted adds) equals F.pad(reflect) + a depthwise convolution along
    each dimension in float64, down to 2 samples, for a channels-last input too; its gradient passes
    torch.autograd.gradcheck."""
    import torch.nn.functional as F

    from dfvo.losses.photometric import _ReflectFilter3

    g = torch.Generator().manual_seed(3)
    x = torch.rand(*shape, generator=g, dtype=torch.float64, requires_grad=True)
    w0 = 0.3
    w1 = 1 - 2 * w0
    n = shape[1]
    for dim, pad, k in ((-1, (1, 1, 0, 0), (1, 1, 1, 3)), (-2, (0, 0, 1, 1), (1, 1, 3, 1))):
        kernel = torch.tensor([w0, w1, w0], dtype=torch.float64).view(k).expand(n, *k[1:])
        ref = F.conv2d(F.pad(x, pad, mode="reflect"), kernel, groups=n)
        torch.testing.assert_close(_ReflectFilter3.apply(x, w0, dim), ref, rtol=1e-14, atol=1e-14)
        torch.testing.assert_close(_ReflectFilter3.apply(x.to(memory_format=torch.channels_last), w0, dim), ref,
                                   rtol=1e-14, atol=1e-14)
        assert torch.autograd.gradcheck(lambda t, d=dim: _ReflectFilter3.apply(t, w0, d), (x,))


def test_ssim_with_the_targets_moments_given_is_the_same_to_the_bit() -> None:
    """A target compared with several views: its moments computed once (and repeated per view) give SSIM + L1 equal
    to the bit to computing them in the call, and the same gradient for the views."""
    from dfvo.losses.photometric import ssim_moments

    g = torch.Generator().manual_seed(5)
    target = torch.rand(2, 3, 9, 13, generator=g)
    views = torch.rand(6, 3, 9, 13, generator=g, requires_grad=True)
    moments = tuple(m.repeat(3, 1, 1, 1) for m in ssim_moments(target))
    plain, given = ssim_l1_error(target.repeat(3, 1, 1, 1), views), ssim_l1_error(target.repeat(3, 1, 1, 1), views,
                                                                                  target_moments=moments)
    assert torch.equal(plain, given)
    assert torch.equal(torch.autograd.grad(plain.sum(), views)[0], torch.autograd.grad(given.sum(), views)[0])


def _ssim_l1_by_autograd(target: torch.Tensor, warped: torch.Tensor, alpha: float) -> torch.Tensor:
    """SSIM + L1 composed of ssim_map and torch operations, differentiated by autograd: the reference."""
    from dfvo.losses.photometric import ssim_map

    dssim = ((1.0 - ssim_map(target, warped)) / 2.0).clamp(0.0, 1.0).mean(1, keepdim=True)
    return alpha * dssim + (1.0 - alpha) * (target - warped).abs().mean(1, keepdim=True)


@pytest.mark.parametrize("alpha", [0.85, 0.0, 1.0])
def test_ssim_l1_hand_written_gradient_is_autograds(alpha: float) -> None:
    """ssim_l1_error's hand-written backward (the warped view's gradient) equals autograd through the composed
    formulation in float64 to 1e-12, on random views, a flat patch in both images (zero variance), an identical
    patch (SSIM 1) and equal pixels (|x - y|'s kink), under a random incoming gradient; the values agree to
    float64 rounding and to float32 rounding in float32; torch.autograd.gradcheck passes."""
    g = torch.Generator().manual_seed(11)
    target = torch.rand(3, 3, 10, 12, generator=g, dtype=torch.float64)
    warped = (target + 0.2 * torch.randn(target.shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    target[0, :, :4, :4] = 0.25
    warped[0, :, :4, :4] = 0.6
    warped[1, :, 5:, 6:] = target[1, :, 5:, 6:]
    warped.requires_grad_(True)
    incoming = torch.rand(3, 1, 10, 12, generator=g, dtype=torch.float64)
    ours, ref = ssim_l1_error(target, warped, alpha), _ssim_l1_by_autograd(target, warped, alpha)
    assert type(ours.grad_fn).__name__ == "_SsimL1ErrorBackward"  # the hand-written path is the one tested
    torch.testing.assert_close(ours, ref, rtol=0, atol=1e-12)
    torch.testing.assert_close(torch.autograd.grad(ours, warped, incoming)[0],
                               torch.autograd.grad(ref, warped, incoming)[0], rtol=0, atol=1e-12)
    t32, w32 = target.float(), warped.detach().float().requires_grad_(True)
    ours32, ref32 = ssim_l1_error(t32, w32, alpha), _ssim_l1_by_autograd(t32, w32, alpha)
    torch.testing.assert_close(ours32, ref32, rtol=0, atol=1e-6)
    torch.testing.assert_close(torch.autograd.grad(ours32, w32, incoming.float())[0],
                               torch.autograd.grad(ref32, w32, incoming.float())[0], rtol=1e-4, atol=1e-4)
    small_t, small_w = target[:1, :, :5, :6], warped.detach()[:1, :, :5, :6].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda w: ssim_l1_error(small_t, w, alpha), (small_w,))


def test_ssim_l1_keeps_autograd_where_the_target_needs_a_gradient() -> None:
    """A target that needs a gradient (or no graph recorded) takes the composed formulation: both images' gradients
    equal autograd's, and under no_grad the values are the hand-written path's."""
    g = torch.Generator().manual_seed(12)
    target = torch.rand(2, 3, 8, 9, generator=g, dtype=torch.float64, requires_grad=True)
    warped = torch.rand(2, 3, 8, 9, generator=g, dtype=torch.float64, requires_grad=True)
    ours, ref = ssim_l1_error(target, warped), _ssim_l1_by_autograd(target, warped, 0.85)
    assert "SsimL1Error" not in type(ours.grad_fn).__name__
    both = (target, warped)
    for a, b in zip(torch.autograd.grad(ours.sum(), both), torch.autograd.grad(ref.sum(), both)):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
    with torch.no_grad():
        plain = ssim_l1_error(target, warped)
    torch.testing.assert_close(plain, ssim_l1_error(target.detach(), warped).detach(), rtol=0, atol=1e-15)


def test_hand_written_gradients_refuse_to_be_differentiated_again() -> None:
    """SSIM + L1, SSIM's window and the correlation have first-order gradients written by hand: asking for a
    differentiable gradient (create_graph=True) raises instead of returning one whose own gradient is silently 0."""
    from dfvo.losses.photometric import ssim_map
    from dfvo.models.correlation import correlation

    g = torch.Generator().manual_seed(13)
    target = torch.rand(1, 3, 4, 5, generator=g, dtype=torch.float64)
    warped = torch.rand(1, 3, 4, 5, generator=g, dtype=torch.float64, requires_grad=True)
    f1 = torch.rand(1, 4, 5, 6, generator=g, dtype=torch.float64, requires_grad=True)
    for name, value in (("ssim_l1_error", ssim_l1_error(target, warped)),
                        ("SSIM's window", ssim_map(target.requires_grad_(True), warped)),
                        ("correlation", correlation(f1, f1.detach() * 2, 1))):
        with pytest.raises(RuntimeError, match=f"{name}.*cannot be differentiated again"):
            torch.autograd.grad(value.sum(), warped if name != "correlation" else f1, create_graph=True)


def test_ssim_l1_takes_target_moments_that_broadcast() -> None:
    """One target's moments for a batch of its copies give the same error and gradient as the batch's own moments
    (as the composed formulation accepts); moments that do not broadcast are refused in one line naming the shapes."""
    from dfvo.losses.photometric import ssim_moments

    g = torch.Generator().manual_seed(14)
    one = torch.rand(1, 3, 6, 7, generator=g, dtype=torch.float64)
    batch = one.expand(3, -1, -1, -1)
    warped = torch.rand(3, 3, 6, 7, generator=g, dtype=torch.float64, requires_grad=True)
    given, own = ssim_l1_error(batch, warped, target_moments=ssim_moments(one)), ssim_l1_error(batch, warped)
    torch.testing.assert_close(given, own, rtol=0, atol=1e-15)
    torch.testing.assert_close(torch.autograd.grad(given.sum(), warped)[0], torch.autograd.grad(own.sum(), warped)[0],
                               rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match=r"target_moments of shapes \[\(2, 3, 6, 7\).*\(3, 3, 6, 7\)"):
        ssim_l1_error(batch, warped, target_moments=ssim_moments(torch.rand(2, 3, 6, 7, dtype=torch.float64)))


def test_reprojection_with_the_source_rays_given_is_the_same_warp(world_frame: dict) -> None:
    """Warping with the pose's rays computed once (source_rays) gives the same points, validity and warped image as
    back-projecting each depth (float32 rounding), at two depths; and its gradient reaches the depth and the pose."""
    from dfvo.losses.reprojection import source_rays

    f = world_frame
    image, K = f["image_next"][None], f["K"][None].float()
    T = f["T_next_cur"][None].float().requires_grad_(True)
    H, W = image.shape[-2:]
    rays = source_rays(T, K, H, W)
    for factor in (1.0, 1.3):
        depth = (f["depth"][None] * factor).requires_grad_(True)
        plain, given = reproject(image, depth, T, K), reproject(image, depth, T, K, rays)
        both = (given.valid & plain.valid)[:, 0]
        assert (given.valid != plain.valid).float().mean() < 1e-3 and both.float().mean() > 0.5  # border rounding
        torch.testing.assert_close(given.grid[both], plain.grid[both], rtol=0, atol=1e-5)
        torch.testing.assert_close(given.depth_in_source, plain.depth_in_source, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(given.warped.permute(0, 2, 3, 1)[both], plain.warped.permute(0, 2, 3, 1)[both],
                                   rtol=0, atol=1e-4)
        g_plain = torch.autograd.grad(plain.warped.sum(), (depth, T))
        g_given = torch.autograd.grad(given.warped.sum(), (depth, T), retain_graph=True)
        for a, b in zip(g_given, g_plain):
            torch.testing.assert_close(a, b, rtol=1e-3, atol=1e-3 * b.abs().max().item())
    with pytest.raises(ValueError, match="rays"):
        reproject(image, f["depth"][None], T, K, source_rays(T, K, H, W - 1))
