"""Tests of the synthetic training distribution: highway scenario, speed and turn settings, frame-skip pairs,
camera height, held-out worlds, and that the default worlds did not change."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from dfvo.geometry.camera import backproject_points, pixel_grid, rigid_flow
from dfvo.synthetic import (
    CAMERA_HEIGHT,
    HELD_OUT_SEED,
    SKY_DEPTH,
    TRAINING_SCENARIOS,
    SyntheticFlowDataset,
    SyntheticSequenceDataset,
    SyntheticWorld,
    check_training_seeds,
    held_out_worlds,
)

H, W = 96, 320


def relative(world: SyntheticWorld, i: int, j: int) -> torch.Tensor:
    """(1,4,4) transform from camera i to camera j (``T_j_i``-style, computed in float64 from the poses)."""
    P = world.poses()
    return (torch.linalg.inv(P[j]) @ P[i]).float()[None]


def sample(img: torch.Tensor, pix: torch.Tensor) -> torch.Tensor:
    """Bilinear sample (C,H,W) at (H,W,2) pixel positions (pixel-centre convention)."""
    Hh, Ww = img.shape[-2:]
    g = torch.stack([2 * pix[..., 0] / (Ww - 1) - 1, 2 * pix[..., 1] / (Hh - 1) - 1], -1)
    return F.grid_sample(img[None], g[None], mode="bilinear", align_corners=True)[0]


def steps_and_yaw(world: SyntheticWorld) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame translation (m) and rotation angle (deg) between consecutive poses."""
    P = world.poses().numpy()
    rel = np.linalg.inv(P[:-1]) @ P[1:]
    ang = np.degrees(np.arccos(np.clip((np.trace(rel[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1)))
    return np.linalg.norm(rel[:, :3, 3], axis=1), ang


@pytest.fixture(scope="module")
def highway() -> SyntheticWorld:
    return SyntheticWorld(seed=4, num_frames=10, height=H, width=W, scenario="highway")


def test_highway_has_textured_far_terrain(highway: SyntheticWorld) -> None:
    s = highway.render(5)
    depth, valid = s["depth"][0], s["flow_fwd_valid"][0]
    far = (depth > 100) & (depth < SKY_DEPTH)
    assert far.float().mean() > 0.02, "hills and forest edges beyond 100 m should fill part of the image"
    assert depth[far].max() > 200
    # textured: horizontal image gradients on far pixels, as on the road
    grad = (s["image"][:, :, 1:] - s["image"][:, :, :-1]).abs().mean(0)
    assert grad[far[:, 1:]].mean() > 0.01
    # flow exists there, is valid, and is the camera's rigid flow
    assert valid[far].float().mean() > 0.7
    assert s["flow_fwd"].norm(dim=0)[far & valid].median() > 0.2
    rf = rigid_flow(s["depth"][None], relative(highway, 5, 6), s["K"][None])[0]
    static = valid & ~s["dynamic_mask"][0]
    assert (rf - s["flow_fwd"]).norm(dim=0)[static].max() < 1e-3


def test_highway_traffic_moves_on_its_own(highway: SyntheticWorld) -> None:
    i = 5
    s = highway.render(i)
    dyn = s["dynamic_mask"][0] & s["flow_fwd_valid"][0]
    assert dyn.float().mean() > 0.005
    rf = rigid_flow(s["depth"][None], relative(highway, i, i + 1), s["K"][None])[0]
    assert (rf - s["flow_fwd"]).norm(dim=0)[dyn].median() > 0.5, "vehicle flow is not the camera's rigid flow"
    # independent per-pixel loop: lift, carry with the vehicle's pose from frame i to i+1, project
    P = highway.poses().numpy()
    Ti, Tj = highway.vehicle_poses(i).numpy(), highway.vehicle_poses(i + 1).numpy()
    half = highway.vehicle_sizes().numpy() / 2
    K = s["K"].double().numpy()
    vs, us = torch.nonzero(dyn, as_tuple=True)
    for k in torch.linspace(0, len(us) - 1, 25).long().tolist():
        v, u = vs[k].item(), us[k].item()
        p_w = np.append(P[i][:3, :3] @ (s["depth"][0, v, u].item() * np.linalg.solve(K, [u, v, 1.0])) + P[i][:3, 3], 1)
        # the vehicle whose box has the point on its surface
        surface = [abs((np.abs(np.linalg.solve(T, p_w)[:3]) / h).max() - 1) for T, h in zip(Ti, half, strict=True)]
        m = int(np.argmin(surface))
        p_c1 = np.linalg.solve(P[i + 1], Tj[m] @ np.linalg.solve(Ti[m], p_w))[:3]
        uv = (K @ p_c1)[:2] / p_c1[2]
        assert np.allclose(uv - [u, v], s["flow_fwd"][:, v, u].double().numpy(), atol=2e-3)
    # traffic at its own speeds: faster and slower than the camera, and oncoming
    cam = P[i + 1][:3, 3] - P[i][:3, 3]
    heading = P[i][:3, 2]
    v_cam = float(cam @ heading)
    v_veh = (Tj[:, :3, 3] - Ti[:, :3, 3]) @ heading
    assert 1.9 < v_cam < 3.2
    assert (v_veh > v_cam + 0.05).any() and ((v_veh > 0.3) & (v_veh < v_cam - 0.05)).any() and (v_veh < -1.0).any()


@pytest.mark.parametrize("scenario,kwargs", [("drive", {"speed": 2.0}), ("highway", {}), ("city", {"speed": 0.8}),
                                             ("handheld", {"speed": 0.05}), ("handheld_planar", {"speed": 0.05})])
def test_frame_skip_flow_is_exact(scenario: str, kwargs: dict) -> None:
    world = SyntheticWorld(seed=7, num_frames=6, height=H, width=W, scenario=scenario, **kwargs)
    i = 1
    grid = pixel_grid(H, W)
    img_i = world.image(i)
    depth_i = world.depth(i)
    dyn_i = world.dynamic_mask(i)[0]
    K = world.intrinsics()[None]
    errors = {}
    for k in (1, 2, 3):
        flow, valid = world.flow(i, i + k)
        valid = valid[0]
        assert valid.float().mean() > 0.15
        # photometric: image i+k warped by the flow reproduces image i on visible pixels (moving vehicles too)
        warped = sample(world.image(i + k), grid + flow.permute(1, 2, 0))
        errors[k] = (warped - img_i).abs().mean(0)[valid].mean().item()
        assert errors[k] < 0.02, (k, errors[k])
        # geometric: depth i reprojected with the relative pose i -> i+k is the flow on static pixels
        rf = rigid_flow(depth_i[None], relative(world, i, i + k), K)[0]
        assert (rf - flow).norm(dim=0)[valid & ~dyn_i].max() < 1e-3
    # a flow of the wrong frame gap does not reproduce image i
    flow2, valid2 = world.flow(i, i + 2)
    wrong = sample(world.image(i + 3), grid + flow2.permute(1, 2, 0))
    assert (wrong - img_i).abs().mean(0)[valid2[0]].mean() > 2 * errors[3]
    # composition: flow i->i+1 followed by flow i+1->i+2 is flow i->i+2
    f01, v01 = world.flow(i, i + 1)
    f12, v12 = world.flow(i + 1, i + 2)
    land = grid + f01.permute(1, 2, 0)
    composed = f01 + sample(f12, land)
    m = v01[0] & valid2[0] & (sample(v12.float(), land)[0] > 0.999)
    diff = (composed - flow2).norm(dim=0)[m]
    assert m.float().mean() > 0.2
    assert diff.median() < 0.02 and (diff < 0.2).float().mean() > 0.97


@pytest.mark.parametrize("scenario,kwargs", [("drive", {}), ("highway", {}), ("city", {"speed": 1.0})])
def test_camera_height_and_kitti_intrinsics(scenario: str, kwargs: dict) -> None:
    K = SyntheticWorld(num_frames=2, height=192, width=640, scenario=scenario, **kwargs).intrinsics()
    assert K[0, 0].item() == pytest.approx(718.856 * 640 / 1241, rel=1e-6)
    assert K[1, 1].item() == pytest.approx(718.856 * 192 / 376, rel=1e-6)
    assert K[0, 2].item() == pytest.approx((607.1928 + 0.5) * 640 / 1241 - 0.5, rel=1e-6)
    assert K[1, 2].item() == pytest.approx((185.2157 + 0.5) * 192 / 376 - 0.5, rel=1e-6)
    # the road plane fitted to the ground pixels' back-projected depth is 1.65 m below the camera
    world = SyntheticWorld(seed=2, num_frames=4, height=H, width=W, scenario=scenario, **kwargs)
    depth = world.depth(1).reshape(1, -1)
    ground = (world.view(1).ids.reshape(-1) == 0) & (depth[0] < 40)
    pts = backproject_points(pixel_grid(H, W).reshape(1, -1, 2), depth, world.intrinsics()[None])[0]
    pts = pts[ground].double()
    centre = pts.mean(0)
    normal = torch.linalg.svd(pts - centre)[2][-1]
    assert CAMERA_HEIGHT == 1.65
    assert (centre @ normal).abs().item() == pytest.approx(1.65, abs=2e-3)
    assert abs(normal[1].item()) > math.cos(math.radians(1.0)), "road normal within 1 degree of the camera's y axis"


def test_handheld_world_moves_like_a_hand_over_a_desk() -> None:
    """The hand-held world: stops that are exact (zero motion on 'still' frames), jerks (the direction of motion
    reverses between moving frames), turns about all three axes, the camera inside its box; the desk fitted to the
    ground pixels' back-projected depth lies exactly the camera's true clearance below it, along a normal tilted
    from the camera's y axis by the camera's pitch and roll."""
    from dfvo.synthetic.handheld import BOX_ACROSS, BOX_ALONG, HEIGHT_RANGE

    world = SyntheticWorld(seed=3, num_frames=80, height=H, width=W, scenario="handheld")
    P = world.poses().numpy()
    steps = np.diff(P[:, :3, 3], axis=0)
    length = np.linalg.norm(steps, axis=1)
    names = world.segment_names()
    still = np.array([names[k] == "still" and names[k + 1] == "still" for k in range(len(steps))])
    assert still.any() and (length[still] == 0).all() and (length[~still] > 0).mean() > 0.9
    moving = np.nonzero(length > 0.005)[0]
    cos = [steps[a] @ steps[b] / (length[a] * length[b]) for a, b in zip(moving[:-1], moving[1:], strict=True)
           if b == a + 1]
    assert min(cos) < 0.0  # the hand reverses from one frame to the next at least once
    rel = np.stack([P[k, :3, :3].T @ P[k + 1, :3, :3] for k in range(len(P) - 1)])
    rotvec = np.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]], 1) / 2
    assert (np.abs(rotvec).max(0) > math.radians(0.5)).all()  # turns about every axis
    assert (np.abs(P[:, 0, 3]) <= BOX_ACROSS + 0.07).all() and (np.abs(P[:, 2, 3]) <= BOX_ALONG + 0.07).all()
    clearance = CAMERA_HEIGHT - P[:, 1, 3]
    assert (clearance >= HEIGHT_RANGE[0] - 0.07).all() and (clearance <= HEIGHT_RANGE[1] + 0.07).all()
    for k in (0, 40):
        depth = world.depth(k).reshape(1, -1)
        ground = world.view(k).ids.reshape(-1) == 0
        assert ground.float().mean() > 0.05
        pts = backproject_points(pixel_grid(H, W).reshape(1, -1, 2), depth, world.intrinsics()[None])[0]
        pts = pts[ground].double()
        centre = pts.mean(0)
        normal = torch.linalg.svd(pts - centre)[2][-1]
        normal = normal * torch.sign(normal[1])
        assert (centre @ normal).item() == pytest.approx(clearance[k], abs=2e-3)
        down_in_camera = torch.from_numpy(P[k, :3, :3].T @ np.array([0.0, 1.0, 0.0]))  # world y in camera axes
        assert float(normal @ down_in_camera) > math.cos(math.radians(0.5))


def test_planar_handheld_world_is_one_plane_seen_by_a_hand() -> None:
    """The planar hand-held world: every pixel of every frame is the desk (no sky, no object), its back-projected
    depth lies on the world plane ``y = CAMERA_HEIGHT`` to a millimetre, the camera looks 40-80 deg down at it from
    0.3-0.8 m, and the hand stops dead and turns about every axis as in the corner world (same motion model)."""
    from dfvo.synthetic.handheld import HEIGHT_RANGE, PLANAR_PITCH_RANGE

    world = SyntheticWorld(seed=3, num_frames=80, height=H, width=W, scenario="handheld_planar")
    P = world.poses().numpy()
    names = world.segment_names()
    steps = np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1)
    still = np.array([names[k] == "still" and names[k + 1] == "still" for k in range(len(steps))])
    assert still.any() and (steps[still] == 0).all() and (steps[~still] > 0).mean() > 0.9
    rel = np.stack([P[k, :3, :3].T @ P[k + 1, :3, :3] for k in range(len(P) - 1)])
    rotvec = np.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]], 1) / 2
    # turns about every camera axis (about its y less: the world's yaw lies mostly along the pitched-down camera's z)
    assert (np.abs(rotvec).max(0) > math.radians(0.2)).all() and np.linalg.norm(rotvec, axis=1).max() > math.radians(2)
    # the optical axis (camera z in world axes) points down (world +y) by the pitch
    pitch = np.degrees(np.arcsin(P[:, 1, 2]))
    lo, hi = sorted(-math.degrees(a) for a in PLANAR_PITCH_RANGE)
    assert (pitch >= lo - 5).all() and (pitch <= hi + 5).all() and pitch.max() - pitch.min() > 5
    clearance = CAMERA_HEIGHT - P[:, 1, 3]
    assert (clearance >= HEIGHT_RANGE[0] - 0.07).all() and (clearance <= HEIGHT_RANGE[1] + 0.07).all()
    for k in (0, 25, 50, 79):
        assert bool((world.view(k).ids == 0).all())  # the desk alone
        depth = world.depth(k).reshape(1, -1)
        pts = backproject_points(pixel_grid(H, W).reshape(1, -1, 2), depth, world.intrinsics()[None])[0].double()
        y_world = pts @ torch.from_numpy(P[k, 1, :3]) + P[k, 1, 3]  # world y of every pixel's point
        assert float((y_world - CAMERA_HEIGHT).abs().max()) < 1e-3
    # textured: the image differs from its own 8x8 block means (detail finer than 8 px) and varies across the view
    img = world.image(10)[None]
    coarse = F.interpolate(F.avg_pool2d(img, 8), scale_factor=8)
    assert float(img.std()) > 0.1 and float((img - coarse).abs().mean()) > 0.01


def test_speed_range_and_turns() -> None:
    cruise = []
    for seed in range(12):
        world = SyntheticWorld(seed=seed, num_frames=40, height=8, width=8, scenario="straight", speed=(0.3, 3.0))
        step, _ = steps_and_yaw(world)
        c = step.mean()
        assert 0.3 * 0.92 <= step.min() and step.max() <= 3.0 * 1.08
        assert np.all(np.abs(step / c - 1) < 0.17), "a world drives at its own (nearly constant) speed"
        cruise.append(c)
    assert min(cruise) < 0.8 and max(cruise) > 2.2, cruise
    fixed, _ = steps_and_yaw(SyntheticWorld(seed=3, num_frames=40, height=8, width=8, scenario="straight", speed=1.5))
    assert np.all(np.abs(fixed - 1.5) <= 1.5 * 0.081)
    for seed in range(3):
        step, yaw = steps_and_yaw(SyntheticWorld(seed=seed, num_frames=30, height=8, width=8, scenario="highway"))
        assert 2.0 * 0.96 < step.min() and step.max() < 3.0 * 1.04 and yaw.max() < 1.0
    # street corners: yaw rates up to ~10 deg/frame at low speed, braking keeps them bounded at any speed
    strongest = 0.0
    for seed in range(6):
        for speed in (0.7, 3.0):
            world = SyntheticWorld(seed=seed, num_frames=80, height=8, width=8, scenario="city", speed=speed)
            step, yaw = steps_and_yaw(world)
            assert yaw.max() < 10.5 and step.max() < speed * 1.09
            turning = np.array(world.segment_names()[:-1]) == "turn"
            assert turning.any()
            if speed == 0.7:
                strongest = max(strongest, yaw[turning].max())
            else:
                # braked from 3 m/frame to <= sqrt(LATERAL * 12 m) * 13.8 / 12 = 1.26 in the corner
                assert np.median(step[turning]) < 1.3 and step[turning].max() < 1.5, "the camera brakes for corners"
    assert strongest > 6.0


def test_default_drive_worlds_unchanged() -> None:
    """Other tests and the shipped-model benchmarks rely on SyntheticWorld(seed=...) of before this change."""
    world = SyntheticWorld(seed=0, num_frames=100, height=H, width=W)
    expected = [[-0.999987253232003, 0.005049096306666574, 1.224619084115113e-16, 24.21642738262068],
                [0.005048982040359734, 0.9999646224792157, 0.0067276719863351144, 0.0],
                [3.396866377854635e-05, 0.006727586230261145, -0.9999773689587401, 9.717157287525382],
                [0.0, 0.0, 0.0, 1.0]]
    assert np.allclose(world.poses()[50].numpy(), expected, atol=1e-12)
    s = world.render(22)
    assert s["image"].double().sum().item() == pytest.approx(34543.34558040276, rel=1e-5)
    assert s["image_right"].double().sum().item() == pytest.approx(34608.2131716162, rel=1e-5)
    assert s["depth"].double().sum().item() == pytest.approx(1728682.7843370438, rel=1e-6)
    assert s["flow_fwd"].double().sum().item() == pytest.approx(-248181.65216255188, rel=1e-5)
    assert int(s["flow_fwd_valid"].sum()) == 21203 and int(s["dynamic_mask"].sum()) == 4099


def test_flow_dataset_frame_skips_and_scenario_mix() -> None:
    ds = SyntheticFlowDataset([0, 1], num_frames=6, height=48, width=160, frame_skips=(1, 2, 3),
                              scenario=("drive", "highway"), speed=1.5)
    assert len(ds) == 2 * (5 + 4 + 3)
    assert [w.scenario for w in ds.worlds] == ["drive", "highway"]
    pos = next(n for n, (w, k, skip) in enumerate(ds.items) if w == 1 and skip == 3 and k == 2)
    item = ds[pos]
    world = ds.worlds[1]
    assert int(item["frame_skip"]) == 3 and int(item["index"]) == 2
    assert torch.equal(item["image"], world.image(2)) and torch.equal(item["image_next"], world.image(5))
    f, v = world.flow(2, 5)
    fb, vb = world.flow(5, 2)
    assert torch.equal(item["flow_fwd"], f) and torch.equal(item["flow_fwd_valid"], v)
    assert torch.equal(item["flow_bwd"], fb) and torch.equal(item["flow_bwd_valid"], vb)
    batch = torch.utils.data.default_collate([ds[0], item])
    assert batch["flow_fwd"].shape == (2, 2, 48, 160) and batch["frame_skip"].tolist() == [1, 3]
    seq = SyntheticSequenceDataset([3], num_frames=6, height=48, width=160, frame_skips=(1, 2))
    assert len(seq) == 4 + 2
    item = seq[5]
    k = int(item["index"])
    assert int(item["frame_skip"]) == 2 and torch.equal(item["image_prev"], seq.worlds[0].image(k - 2))
    assert torch.equal(item["pose_next"], seq.worlds[0].poses()[k + 2].float())
    for bad in ((0,), (6,), ()):
        with pytest.raises(ValueError, match="frame_skips"):
            SyntheticFlowDataset([0], num_frames=6, height=48, width=160, frame_skips=bad)


def test_kept_frames_give_the_same_snippets_rendering_each_frame_once() -> None:
    """``keep_frames``: every item bit for bit the item rendered afresh (images of neighbours shaded with the right
    view, or alone), in any order and twice over; each frame of each world rendered once."""
    fresh = SyntheticSequenceDataset([3, 8], num_frames=7, height=48, width=160, frame_skips=(1, 2),
                                     scenario=["city", "highway"])
    kept = SyntheticSequenceDataset([3, 8], num_frames=7, height=48, width=160, frame_skips=(1, 2),
                                    scenario=["city", "highway"], keep_frames=True)
    calls: list[tuple[int, int]] = []
    for w, world in enumerate(kept.worlds):
        def counted(index: int, *args: object, _w: int = w, _render=world.render, **kwargs: object) -> dict:
            calls.append((_w, index))
            return _render(index, *args, **kwargs)
        world.render = counted  # type: ignore[method-assign]
    order = torch.randperm(len(fresh), generator=torch.Generator().manual_seed(0)).tolist()
    for i in order + order[::-1]:
        a, b = fresh[i], kept[i]
        assert a.keys() == b.keys()
        for key in a:
            assert torch.equal(a[key], b[key]), (i, key)
    assert sorted(calls) == [(w, k) for w in range(2) for k in range(7)]  # 7 frames each, once


def test_object_kind_names_what_each_pixel_shows() -> None:
    """``object_kind``: sky exactly where the depth is the sky's, every moving vehicle's pixel a car, parked cars too
    (cars beyond the moving ones), and each object pixel the kind of the box the ray hit."""
    from dfvo.synthetic.render import SKY_DEPTH
    from dfvo.synthetic.scene import KIND_CAR

    cars = moving = 0
    for scenario in ("drive", "highway"):
        world = SyntheticWorld(seed=1000, num_frames=12, height=48, width=160, scenario=scenario)
        for k in range(0, 12, 3):
            kind, dyn = world.object_kind(k), world.dynamic_mask(k)
            assert kind.shape == (1, 48, 160) and kind.dtype == torch.int64
            assert torch.equal(kind == -1, world.depth(k) == SKY_DEPTH)
            assert bool((kind[dyn] == KIND_CAR).all())
            ids = world.view(k).ids
            hit = ids > 0
            assert torch.equal(kind[0][hit], torch.as_tensor(world._scene.kind)[ids[hit] - 1])
            cars, moving = cars + int((kind == KIND_CAR).sum()), moving + int(dyn.sum())
    assert cars > moving > 0


def test_held_out_worlds_convention() -> None:
    worlds = held_out_worlds()
    assert {w.scenario for w in worlds} == set(TRAINING_SCENARIOS)
    assert all(w.seed >= HELD_OUT_SEED for w in worlds) and len({w.name for w in worlds}) == len(worlds)
    hw = next(w for w in worlds if w.scenario == "highway")
    world = hw.make(num_frames=5, height=8, width=8)
    assert world.seed == hw.seed and world.scenario == "highway"
    check_training_seeds([0, 5, 999])
    with pytest.raises(ValueError, match="held-out"):
        check_training_seeds([3, 1000])
    with pytest.raises(ValueError, match="scenario"):
        held_out_worlds(("motorway",))


@pytest.mark.parametrize("kwargs,name", [({"speed": 0.0}, "speed"), ({"speed": (3.0, 1.0)}, "speed"),
                                         ({"speed": "fast"}, "speed"), ({"turn_rate": (5.0, 50.0)}, "turn_rate"),
                                         ({"scenario": "motorway"}, "scenario")])
def test_bad_settings_name_the_setting(kwargs: dict, name: str) -> None:
    with pytest.raises(ValueError, match=name):
        SyntheticWorld(num_frames=4, height=8, width=8, **kwargs)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_gpu_rendering_matches_cpu() -> None:
    cpu = SyntheticWorld(seed=5, num_frames=5, height=H, width=W, scenario="highway")
    gpu = SyntheticWorld(seed=5, num_frames=5, height=H, width=W, scenario="highway", device="cuda")
    a, b = cpu.render(2), gpu.render(2)
    for key, value in b.items():
        assert value.device.type == "cuda", key
    same = a["depth"] == b["depth"].cpu()
    assert same.float().mean() > 0.99 or torch.allclose(a["depth"], b["depth"].cpu(), rtol=1e-4)
    assert (a["image"] - b["image"].cpu()).abs().mean() < 2e-3
    agree = a["flow_fwd_valid"] & b["flow_fwd_valid"].cpu()
    assert agree.float().mean() > 0.95 * a["flow_fwd_valid"].float().mean()
    assert (a["flow_fwd"] - b["flow_fwd"].cpu()).norm(dim=0)[agree].median() < 1e-3
