"""Tests of the synthetic driving world: exact flow, depth, stereo and poses against independent computations."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from kornia.geometry.depth import warp_frame_depth

from dfvo.geometry.camera import backproject_points, pixel_grid, project_points, rigid_flow, transform_points
from dfvo.synthetic import SKY_DEPTH, SyntheticFlowDataset, SyntheticSequenceDataset, SyntheticWorld

H, W = 96, 320


@pytest.fixture(scope="module")
def drive() -> SyntheticWorld:
    return SyntheticWorld(seed=3, num_frames=100, height=H, width=W)


def relative(world: SyntheticWorld, i: int, j: int) -> torch.Tensor:
    """(1,4,4) T_j_i computed in float64 from the world's poses."""
    P = world.poses()
    return (torch.linalg.inv(P[j]) @ P[i]).float()[None]


def sample(img: torch.Tensor, pix: torch.Tensor) -> torch.Tensor:
    """Bilinear sample (C,H,W) at (H,W,2) pixel positions (align_corners=True pixel-centre convention)."""
    Hh, Ww = img.shape[-2:]
    g = torch.stack([2 * pix[..., 0] / (Ww - 1) - 1, 2 * pix[..., 1] / (Hh - 1) - 1], -1)
    return F.grid_sample(img[None], g[None], mode="bilinear", align_corners=True)[0]


def test_render_keys_shapes_and_intrinsics(drive: SyntheticWorld) -> None:
    s = drive.render(5)
    shapes = {"image": (3, H, W), "image_right": (3, H, W), "depth": (1, H, W), "K": (3, 3), "T_right_left": (4, 4),
              "pose": (4, 4), "dynamic_mask": (1, H, W), "flow_fwd": (2, H, W), "flow_bwd": (2, H, W),
              "flow_fwd_valid": (1, H, W), "flow_bwd_valid": (1, H, W), "index": ()}
    for key, shape in shapes.items():
        assert tuple(s[key].shape) == shape, key
    assert s["flow_fwd_valid"].dtype == torch.bool and s["dynamic_mask"].dtype == torch.bool
    assert 0.0 <= s["image"].min() and s["image"].max() <= 1.0 and s["image"].std() > 0.05
    K = s["K"]
    # KITTI odometry ratios (pixel-centre resize convention)
    assert K[0, 0].item() == pytest.approx(718.856 * W / 1241, rel=1e-5)
    assert K[1, 1].item() == pytest.approx(718.856 * H / 376, rel=1e-5)
    assert K[0, 2].item() == pytest.approx((607.1928 + 0.5) * W / 1241 - 0.5, rel=1e-5)
    assert torch.allclose(s["T_right_left"][:3, 3], torch.tensor([-0.54, 0.0, 0.0]))
    assert torch.allclose(s["pose"], drive.poses()[5].float())
    last = drive.render(len(drive) - 1)
    assert "flow_fwd" not in last and "image" in last
    assert drive.intrinsics().shape == (3, 3) and len(drive.segment_names()) == len(drive) == 100
    with pytest.raises(IndexError, match="out of range"):
        drive.render(100)


def test_determinism_by_seed() -> None:
    a = SyntheticWorld(seed=11, num_frames=6, height=48, width=160).render(2)
    b = SyntheticWorld(seed=11, num_frames=6, height=48, width=160).render(2)
    c = SyntheticWorld(seed=12, num_frames=6, height=48, width=160).render(2)
    for key in a:
        assert torch.equal(a[key], b[key]), key
    assert not torch.equal(a["image"], c["image"])
    # shading left and right in one pass equals shading each alone
    alone = SyntheticWorld(seed=11, num_frames=6, height=48, width=160)
    assert torch.equal(alone.image(2, 1), a["image_right"]) and torch.equal(alone.image(2, 0), a["image"])


@pytest.mark.parametrize("scenario,index", [("drive", 10), ("drive", 40), ("rotation", 3), ("planar", 2),
                                            ("moving_car", 6), ("straight", 4), ("city", 5), ("highway", 4)])
def test_static_flow_equals_rigid_flow(scenario: str, index: int, drive: SyntheticWorld) -> None:
    world = drive if scenario == "drive" else SyntheticWorld(seed=5, num_frames=12, height=H, width=W,
                                                             scenario=scenario)
    s = world.render(index)
    rf = rigid_flow(s["depth"][None], relative(world, index, index + 1), s["K"][None])[0]
    static = s["flow_fwd_valid"][0] & ~s["dynamic_mask"][0]
    assert static.float().mean() > 0.15
    err = (rf - s["flow_fwd"]).norm(dim=0)[static]
    assert err.max() < 1e-3
    # backward flow as well, on image index+1
    s1 = world.render(index + 1, right=False, flow=False)
    rb = rigid_flow(s1["depth"][None], relative(world, index + 1, index), s["K"][None])[0]
    static_b = s["flow_bwd_valid"][0] & ~s1["dynamic_mask"][0]
    assert (rb - s["flow_bwd"]).norm(dim=0)[static_b].max() < 1e-3


def test_moving_car_flow_follows_object_motion() -> None:
    """Independent per-pixel loop: lift, carry with the vehicle's pose from frame i to i+1, project."""
    world = SyntheticWorld(seed=2, num_frames=10, height=H, width=W, scenario="moving_car")
    i = 5
    s = world.render(i)
    dyn = s["dynamic_mask"][0] & s["flow_fwd_valid"][0]
    assert dyn.float().mean() > 0.3, "the moving_car scenario should be dominated by the truck"
    P = world.poses().numpy()
    Ti, Tj = world.vehicle_poses(i).numpy(), world.vehicle_poses(i + 1).numpy()
    K = s["K"].double().numpy()
    vs, us = torch.nonzero(dyn, as_tuple=True)
    pick = torch.linspace(0, len(us) - 1, 40).long()
    for v, u in zip(vs[pick].tolist(), us[pick].tolist(), strict=True):
        z = s["depth"][0, v, u].item()
        p_c = z * np.linalg.solve(K, [u, v, 1.0])
        p_w = np.append(P[i][:3, :3] @ p_c + P[i][:3, 3], 1.0)
        # which vehicle: the one whose box (in its own frame) contains the point
        k = int(np.argmin([np.abs(np.linalg.solve(T, p_w)[:3]).max() for T in Ti]))
        p_w1 = Tj[k] @ np.linalg.solve(Ti[k], p_w)
        p_c1 = np.linalg.solve(P[i + 1], p_w1)[:3]
        uv = (K @ p_c1)[:2] / p_c1[2]
        assert np.allclose(uv - [u, v], s["flow_fwd"][:, v, u].double().numpy(), atol=2e-3)
    # the truck moves: its flow differs from the camera-only (rigid) flow
    rf = rigid_flow(s["depth"][None], relative(world, i, i + 1), s["K"][None])[0]
    assert (rf - s["flow_fwd"]).norm(dim=0)[dyn].median() > 0.5


@pytest.mark.parametrize("scenario,index", [("drive", 12), ("moving_car", 4), ("highway", 3)])
def test_forward_backward_consistency(scenario: str, index: int, drive: SyntheticWorld) -> None:
    world = drive if scenario == "drive" else SyntheticWorld(seed=4, num_frames=8, height=H, width=W,
                                                             scenario=scenario)
    s = world.render(index)
    grid = pixel_grid(H, W)
    target = grid + s["flow_fwd"].permute(1, 2, 0)
    back = sample(s["flow_bwd"], target)
    diff = (s["flow_fwd"] + back).norm(dim=0)
    # valid pixels whose bilinear footprint in image j is also visible (not straddling an occlusion edge)
    vis_b = sample(s["flow_bwd_valid"].float(), target)[0] > 0.999
    m = s["flow_fwd_valid"][0] & vis_b
    assert m.float().mean() > 0.3  # the highway's sky is a third of the image
    assert diff[m].median() < 0.02
    assert (diff[m] < 0.5).float().mean() > 0.97


def test_occlusion_masks_against_depth_of_other_frame(drive: SyntheticWorld) -> None:
    """Valid pixels land on a surface at their projected depth; occluded ones land behind a nearer surface."""
    i = 20
    s = drive.render(i)
    d1 = drive.render(i + 1, right=False, flow=False)["depth"]
    T = relative(drive, i, i + 1)
    pts = backproject_points(pixel_grid(H, W).reshape(1, -1, 2), s["depth"].reshape(1, -1), s["K"][None])
    pix, z = project_points(transform_points(T, pts), s["K"][None])
    inside = (pix[0, :, 0] >= 0) & (pix[0, :, 0] <= W - 1) & (pix[0, :, 1] >= 0) & (pix[0, :, 1] <= H - 1)
    nearest = pix[0].round().long()
    nu, nv = nearest[:, 0].clamp(0, W - 1), nearest[:, 1].clamp(0, H - 1)
    d_other = d1[0, nv, nu]
    static = ~s["dynamic_mask"].reshape(-1) & (s["depth"].reshape(-1) < SKY_DEPTH) & inside & (z[0] > 0)
    valid = s["flow_fwd_valid"].reshape(-1)
    rel = (z[0] - d_other) / d_other
    assert (rel[valid & static].abs() < 0.05).float().mean() > 0.98
    occluded = static & ~valid
    assert occluded.sum() > 20, "a driving frame should have occluded pixels (behind poles, cars, corners)"
    # an occluded point lands next to a nearer surface: the 3x3 neighbourhood minimum of depth j is in front
    near = -F.max_pool2d(-d1[None], 3, stride=1, padding=1)[0, 0]
    in_front = near[nv, nu] < z[0] / 1.005
    assert in_front[occluded].float().mean() > 0.9
    assert not valid[s["depth"].reshape(-1) >= SKY_DEPTH].any(), "sky is never valid"


def test_warping_next_image_reproduces_current(drive: SyntheticWorld) -> None:
    i = 8
    s = drive.render(i)
    img1 = drive.image(i + 1)
    T = relative(drive, i, i + 1)
    warped = warp_frame_depth(img1[None], s["depth"][None], T, s["K"][None])[0]
    m = (s["flow_fwd_valid"][0] & ~s["dynamic_mask"][0])
    err = (warped - s["image"]).abs().mean(0)[m].mean()
    assert err < 0.02
    T_bad = T.clone()
    T_bad[0, 0, 3] += 0.3
    bad = warp_frame_depth(img1[None], s["depth"][None], T_bad, s["K"][None])[0]
    assert (bad - s["image"]).abs().mean(0)[m].mean() > 3 * err


def test_stereo_disparity_is_f_b_over_depth(drive: SyntheticWorld) -> None:
    s = drive.render(30)
    K, depth = s["K"], s["depth"][0]
    disp = K[0, 0] * 0.54 / depth
    grid = pixel_grid(H, W)
    target = grid.clone()
    target[..., 0] -= disp
    # geometry: the right camera sees the same surface at depth z at u - f*b/z
    d_right = drive.view(30, 1).depth
    hit = torch.isfinite(d_right)
    nu = target[..., 0].round().long().clamp(0, W - 1)
    nv = grid[..., 1].long()
    inside = (target[..., 0] >= 0) & (depth < SKY_DEPTH)
    rel = ((d_right[nv, nu] - depth) / depth).abs()
    agree = (rel < 0.05) & hit[nv, nu]
    assert agree[inside].float().mean() > 0.9
    # photometric: the right image warped by the disparity reproduces the left image
    warped = sample(s["image_right"], target)
    err = (warped - s["image"]).abs().mean(0)[inside & agree].mean()
    assert err < 0.02
    t2 = grid.clone()
    t2[..., 0] -= 1.3 * disp
    bad = (sample(s["image_right"], t2) - s["image"]).abs().mean(0)[inside & agree].mean()
    assert bad > 3 * err


def test_drive_segments_and_speed() -> None:
    world = SyntheticWorld(seed=0, num_frames=100, height=H, width=W)
    names = world.segment_names()
    assert {"drive", "turn", "still", "rotation", "planar", "moving_car"} <= set(names)
    P = world.poses()
    rel = torch.linalg.inv(P[:-1]) @ P[1:]
    step = rel[:, :3, 3].norm(dim=-1)
    angle = torch.rad2deg(torch.arccos(((rel[:, 0, 0] + rel[:, 1, 1] + rel[:, 2, 2] - 1) / 2).clamp(-1, 1)))
    for k, name in enumerate(names[:-1]):
        nxt = names[k + 1]
        if name == "drive" and nxt == "drive":
            assert 0.6 < step[k] < 1.5, (k, step[k])
        if name == "still" and nxt == "still":
            assert torch.equal(P[k], P[k + 1])
        if name == "rotation" and nxt == "rotation":
            assert step[k] < 1e-9 and angle[k] > 1.0
    yaw = torch.atan2(P[:, 0, 2], P[:, 2, 2])
    assert (yaw.max() - yaw.min()) > math.radians(80), "the default drive should include a 90-degree turn"


def _plane_residual(points: torch.Tensor) -> float:
    centred = points - points.mean(0)
    return torch.linalg.svdvals(centred)[-1].item() / math.sqrt(len(points))


def test_planar_and_still_and_rotation_scenarios() -> None:
    planar = SyntheticWorld(seed=1, num_frames=6, height=H, width=W, scenario="planar")
    s = planar.render(2)
    pts = backproject_points(pixel_grid(H, W).reshape(1, -1, 2), s["depth"].reshape(1, -1), s["K"][None])[0]
    assert (s["depth"] < SKY_DEPTH).all()
    assert _plane_residual(pts) < 1e-3, "planar scenario: every pixel lies on the facade plane"
    still = SyntheticWorld(seed=1, num_frames=4, height=H, width=W, scenario="still")
    st = still.render(1)
    static = ~st["dynamic_mask"][0] & st["flow_fwd_valid"][0]
    assert torch.equal(still.poses()[1], still.poses()[2])
    assert st["flow_fwd"][:, static].abs().max() < 1e-4
    rot = SyntheticWorld(seed=1, num_frames=6, height=H, width=W, scenario="rotation")
    P = rot.poses()
    assert torch.allclose(P[:, :3, 3], P[0:1, :3, 3].expand(6, 3))
    r = rot.render(1)
    # pure rotation: the flow of every static pixel (sky included) is independent of depth
    rf = rigid_flow(torch.full_like(r["depth"][None], 7.0), relative(rot, 1, 2), r["K"][None])[0]
    sky = r["depth"][0] >= SKY_DEPTH
    assert (rf - r["flow_fwd"]).norm(dim=0)[~r["dynamic_mask"][0]].max() < 1e-3
    assert sky.any()


def test_exposure_and_noise_change_images_not_geometry() -> None:
    base = SyntheticWorld(seed=6, num_frames=6, height=48, width=160)
    exp = SyntheticWorld(seed=6, num_frames=6, height=48, width=160, exposure_change=True)
    noisy = SyntheticWorld(seed=6, num_frames=6, height=48, width=160, noise_std=0.02)
    a, b, c = base.render(2), exp.render(2), noisy.render(2)
    for key in ("depth", "flow_fwd", "flow_fwd_valid"):
        assert torch.equal(a[key], b[key]) and torch.equal(a[key], c[key])
    ratio = [exp.image(k).mean() / base.image(k).mean() for k in range(4)]
    assert max(ratio) - min(ratio) > 0.05
    d = (c["image"] - a["image"])[(a["image"] > 0.1) & (a["image"] < 0.9)]
    assert d.std().item() == pytest.approx(0.02, rel=0.15)
    assert torch.equal(c["image"], SyntheticWorld(seed=6, num_frames=6, height=48, width=160,
                                                  noise_std=0.02).render(2)["image"])


def test_datasets_and_collate() -> None:
    seq = SyntheticSequenceDataset(seeds=[0, 1], num_frames=5, height=48, width=160)
    assert len(seq) == 2 * 3
    item = seq[4]
    world = seq.worlds[1]
    k = int(item["index"])
    assert torch.equal(item["image_prev"], world.image(k - 1)) and torch.equal(item["image_next"], world.image(k + 1))
    for key in ("image", "image_right", "K", "T_right_left", "pose", "pose_prev", "pose_next", "depth"):
        assert key in item
    batch = torch.utils.data.default_collate([seq[0], seq[1]])
    assert batch["image_prev"].shape == (2, 3, 48, 160)
    flow = SyntheticFlowDataset(seeds=[2], num_frames=4, height=48, width=160)
    assert len(flow) == 3
    f = flow[2]
    assert {"image", "image_next", "flow_fwd", "flow_bwd", "flow_fwd_valid", "flow_bwd_valid", "K"} <= set(f)
    with pytest.raises(ValueError, match="seeds"):
        SyntheticFlowDataset(seeds=[], num_frames=4, height=48, width=160)


def test_bad_arguments_name_the_setting() -> None:
    with pytest.raises(ValueError, match="scenario"):
        SyntheticWorld(scenario="motorway")
    with pytest.raises(ValueError, match="num_frames"):
        SyntheticWorld(num_frames=1)
    with pytest.raises(ValueError, match="baseline"):
        SyntheticWorld(baseline=0.0)
