"""Scale beyond the CNN: the camera-height prior, the three-frame relative scale, the filter, the plausibility gates,
on exact synthetic cases."""

import math

import pytest
import torch

import dfvo.tracking.odometry as odometry
from dfvo.synthetic import CAMERA_HEIGHT, SyntheticWorld
from dfvo.tracking import TrackerConfig, VisualOdometry
from dfvo.tracking.config import CameraHeightConfig, GateConfig, HandheldConfig, RoadPlaneConfig, ScaleConfig
from dfvo.tracking.gates import check_length, check_support, image_parallax_px
from dfvo.tracking.ground_plane import fit_road_plane
from dfvo.tracking.scale_filter import ScaleFilter
from dfvo.tracking.temporal_scale import middle_depths, relative_scale

torch.set_num_threads(1)

TRIANGULATED = {"points": "triangulated"}
NETWORK_DEPTH = {"points": "depth"}


@pytest.fixture(scope="module")
def straight(straight_pairs):
    """Six pairs of straight driving with exact flow and depth (the E-tracker takes every pair)."""
    return straight_pairs(7)


def lengths(results) -> torch.Tensor:
    return torch.stack([r.T_prev_cur[:3, 3].norm() for r in results])


def cfg_with(**scale) -> TrackerConfig:
    """The E-tracker with one-view scale and ``scale`` settings; no estimated camera height (a test that wants the
    height gives it)."""
    road = scale.pop("road", {})
    return TrackerConfig(mode="e", scale=ScaleConfig(depth_views=1, **scale), road_plane=RoadPlaneConfig(**road),
                         camera_height=CameraHeightConfig(estimate=False))


@pytest.mark.parametrize("temporal", [False, True])
@pytest.mark.parametrize("road", [TRIANGULATED, NETWORK_DEPTH], ids=["triangulated", "depth"])
def test_camera_height_corrects_a_biased_depth(straight, temporal, road):
    """Depth 30 % too far: the paper's scale makes every translation 1.3x too long; the camera-height prior
    (the road plane of the triangulated points, or of the network's own depth) brings each one within 1 %."""
    w, ff, fb, d, rel = straight
    true = rel[:, :3, 3].norm(dim=-1)
    plain = VisualOdometry(cfg_with(temporal=False)).run(ff, fb, 1.3 * d, w.intrinsics(), batch_size=3)
    assert torch.allclose(lengths(plain) / true, torch.full_like(true, 1.3), atol=1e-3)
    res = VisualOdometry(cfg_with(camera_height=CAMERA_HEIGHT, temporal=temporal, road=road)).run(
        ff, fb, 1.3 * d, w.intrinsics(), batch_size=3)
    assert all(r.diagnostics.tracker == "E" for r in res)
    assert ((lengths(res) / true - 1).abs() < 0.01).all(), lengths(res) / true
    for r in res:
        assert r.diagnostics.plane_inliers >= 20 and r.diagnostics.cnn_bias > 1.2
        assert "cnn" in r.diagnostics.scale_source
    if temporal:  # the CNN's factor is learnt over frames: the error shrinks
        assert abs(float(lengths(res)[-1] / true[-1]) - 1) < abs(float(lengths(res)[0] / true[0]) - 1)
    heights = torch.tensor([r.diagnostics.scale_height for r in res], dtype=torch.float64)
    if road == TRIANGULATED:  # exact flow: the triangulated road plane is exact
        assert torch.allclose(heights / true, torch.ones_like(true), atol=1e-6)
    else:  # the network's road plane is exact (1.3x the camera height); the bias it observes goes through the filter
        fits = torch.tensor([r.diagnostics.camera_height_fit for r in res], dtype=torch.float64)
        assert torch.allclose(fits, torch.full_like(fits, 1.3 * CAMERA_HEIGHT), rtol=1e-6)
        assert ((heights / true - 1).abs() < 0.01).all(), heights / true


def test_road_plane_fit_ignores_kerbs_clutter_and_walls():
    """Road points at 1.65 m, a pavement 0.15 m higher, a wall and random clutter: the least-quantile plane fit
    returns the road exactly; a camera pitched beyond max_tilt_deg finds no road."""
    g = torch.Generator().manual_seed(0)
    u = torch.rand(1000, 3, generator=g, dtype=torch.float64)
    road = torch.stack([u[:400, 0] * 8 - 4, torch.full((400,), 1.65, dtype=torch.float64), 4 + u[:400, 1] * 20], -1)
    kerb = torch.stack([4 + u[400:550, 0] * 2, torch.full((150,), 1.5, dtype=torch.float64), 4 + u[400:550, 1] * 20],
                       -1)
    wall = torch.stack([torch.full((150,), -5.0, dtype=torch.float64), u[550:700, 0] * 3 - 1, 4 + u[550:700, 1] * 20],
                       -1)
    clutter = (u[700:] - 0.5) * torch.tensor([10.0, 3.0, 20.0], dtype=torch.float64) + \
        torch.tensor([0.0, 0.5, 14.0], dtype=torch.float64)
    X = torch.cat([road, kerb, wall, clutter])[None] * 0.37  # any unit: the height scales with it
    rows = torch.ones(1, 1000, dtype=torch.bool)
    plane = fit_road_plane(X, rows, generators=[torch.Generator().manual_seed(1)])
    assert bool(plane.success[0])
    assert abs(float(plane.height[0]) - 1.65 * 0.37) < 1e-9
    assert torch.allclose(plane.normal[0], torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), atol=1e-9)
    assert int(plane.num_inliers[0]) >= 400
    pitch = torch.tensor([[1.0, 0.0, 0.0], [0.0, math.cos(0.5), -math.sin(0.5)], [0.0, math.sin(0.5), math.cos(0.5)]],
                         dtype=torch.float64)
    tilted = fit_road_plane(road[None] @ pitch.T, torch.ones(1, 400, dtype=torch.bool), max_tilt_deg=15.0,
                            generators=[torch.Generator().manual_seed(1)])
    assert not bool(tilted.success[0])


def test_three_frame_relative_scale_is_exact(straight):
    """Pair (0,1) tracked with its true metric pose leaves depths in frame 1; pair (1,2)'s unit-translation pose and
    the exact flow 1->2 give pair (1,2)'s metric length from them to 1e-4 (the flow is sampled bilinearly at
    sub-pixel points)."""
    w, ff, fb, d, rel = straight
    K = w.intrinsics()[None]
    T10 = torch.linalg.inv(rel[0])  # T_cur_prev of pair (0,1)
    H, W = ff.shape[-2:]
    vv, uu = torch.meshgrid(torch.arange(100, H, 7), torch.arange(0, W, 7), indexing="ij")
    p0 = torch.stack([uu.flatten(), vv.flatten()], -1).to(torch.float64)
    p1 = p0 + ff[0][:, vv.flatten(), uu.flatten()].T.to(torch.float64)
    mid = middle_depths(T10, K, p0, p1, torch.ones(p0.shape[0], dtype=torch.bool))
    assert mid is not None and mid.pts.shape[0] > 100
    T21 = torch.linalg.inv(rel[1])
    L = float(T21[:3, 3].norm())
    incon = torch.zeros(1, 1, H, W)
    out = relative_scale(mid, ff[1:2], incon, K, T21[None, :3, :3], T21[None, :3, 3] / L)
    assert out.num_points > 50
    assert abs(out.scale / L - 1) < 1e-4
    assert relative_scale(None, ff[1:2], incon, K, T21[None, :3, :3], T21[None, :3, 3] / L).scale is None


def test_relative_scale_with_refined_points_recovers_an_underestimated_flow(straight):
    """The flow 1->2 given to the three-frame scale is the exact flow shortened by 5 % and 10 % (a network that
    underestimates large flows, consistent with itself: zero inconsistency). The previous pair's points are frame 0's
    corners (what the selection keeps), carried to frame 1 exactly. Read from the dense flow the scale is 5-10 % off;
    with ``grey_pair`` (``tracker.scale_filter.refine_points``) the points are carried by a photometric refinement at
    the points in the rendered images and the scale is within 1 % of the true length (measured: 0.995), whatever the
    flow it started from."""
    from kornia.color import rgb_to_grayscale

    from dfvo.matching.pyramid_refinement import PyramidRefinementConfig, build_pyramid, select_candidates

    w, ff, fb, d, rel = straight
    K = w.intrinsics()[None]
    H, W = ff.shape[-2:]
    images = [w.render(i, right=False)["image"][None] for i in (0, 1, 2)]
    corners, found = select_candidates(build_pyramid(images[0], 3)[0], PyramidRefinementConfig())
    p0 = corners[0][found[0]].to(torch.float64)
    p1 = p0 + ff[0][:, p0[:, 1].long(), p0[:, 0].long()].T.to(torch.float64)
    mid = middle_depths(torch.linalg.inv(rel[0]), K, p0, p1, torch.ones(p0.shape[0], dtype=torch.bool))
    T21 = torch.linalg.inv(rel[1])
    L = float(T21[:3, 3].norm())
    grey = tuple(rgb_to_grayscale(img) for img in images[1:])
    for short in (0.95, 0.9):
        args = (mid, short * ff[1:2], torch.zeros(1, 1, H, W), K, T21[None, :3, :3], T21[None, :3, 3] / L)
        dense = relative_scale(*args)
        assert dense.scale is not None and abs(dense.scale / L - short) < 0.02  # the flow's error, passed on
        refined = relative_scale(*args, grey_pair=grey)
        assert refined.num_points > 200 and abs(refined.scale / L - 1) < 0.01, (refined, L)
        # its settings are the caller's (infer.py: flow.refine.pyramid): no iterations leaves the flow's error
        idle = PyramidRefinementConfig(levels=1, iterations=[0])
        unrefined = relative_scale(*args, grey_pair=grey, point_refinement=idle)
        assert unrefined.scale is not None and abs(unrefined.scale / L - short) < 0.02


def test_the_point_refinement_settings_reach_the_scale_fusion(monkeypatch: pytest.MonkeyPatch, tmp_path):
    """``VisualOdometry(cfg, point_refinement)`` hands them to its scale fusion (also after ``reset``), and
    infer.py's run passes ``flow.refine.pyramid``."""
    from hydra import compose, initialize_config_module

    import dfvo.inference.pipeline as pipeline
    from dfvo.matching.pyramid_refinement import PyramidRefinementConfig

    settings = PyramidRefinementConfig(levels=2, iterations=[3, 2])
    vo = VisualOdometry(TrackerConfig(), settings)
    vo.reset()
    assert vo.fusion.point_refinement is settings
    seen = []

    class Spy(VisualOdometry):
        def __init__(self, cfg, point_refinement=None):
            seen.append(point_refinement)
            super().__init__(cfg, point_refinement)

    monkeypatch.setattr(pipeline, "VisualOdometry", Spy)
    with initialize_config_module("dfvo.conf.infer", version_base="1.3"):
        cfg = compose("infer", overrides=["data.num_frames=3", "img_res.height=64", "img_res.width=96",
                                          "flow=oracle", "depth=oracle", "progress=false", f"out_dir={tmp_path}",
                                          "flow.refine.pyramid.levels=2", "flow.refine.pyramid.iterations=[3,2]"])
    pipeline.run_inference(cfg)
    assert [(s.levels, s.iterations) for s in seen] == [(2, [3, 2])]


def test_temporal_filter_keeps_the_scale_through_the_network_s_frame_noise(straight):
    """Depth off by a different factor every frame (+-15 %): the per-frame scale follows the noise; with the
    temporal filter the three-frame relative scale carries the scale and the error shrinks."""
    w, ff, fb, d, rel = straight
    true = rel[:, :3, 3].norm(dim=-1)
    factors = torch.tensor([1.0, 1.15, 0.85, 1.15, 0.85, 1.15], dtype=torch.float32)
    dn = d * factors[:, None, None, None]
    per_frame = VisualOdometry(cfg_with(temporal=False)).run(ff, fb, dn, w.intrinsics(), batch_size=6)
    filt = VisualOdometry(cfg_with(temporal=True)).run(ff, fb, dn, w.intrinsics(), batch_size=6)
    err_pf = (lengths(per_frame) / true - 1).abs()
    err_f = (lengths(filt) / true - 1).abs()
    assert err_pf[1:].min() > 0.14
    assert err_f[1:].max() < 0.08
    for k, r in enumerate(filt[1:], start=1):  # the temporal observation is exact: previous length x true ratio
        assert abs(r.diagnostics.scale_temporal / float(lengths(filt)[k - 1] * true[k] / true[k - 1]) - 1) < 1e-5
        assert r.diagnostics.scale_source.startswith("temporal")


def test_scale_filter_fusion_prediction_and_gating():
    f = ScaleFilter(temporal=True, estimate_bias=False, cnn_log_std=0.1, height_log_std=0.05, motion_log_std=0.1,
                    temporal_log_std=0.01, relative_process_std=0.0, bias_prior_log_std=0.5, bias_log_std=0.0,
                    gate_sigma=4.0, warmup_frames=0)
    est = f.estimate(f.prior(), cnn=1.0, height=1.2)  # first frame: inverse-variance weights 1/0.01 and 1/0.0025
    assert est.source == "height+cnn"
    assert math.isclose(math.log(est.scale), (0.0 * 100 + math.log(1.2) * 400) / 500, rel_tol=1e-5)
    f.commit(est.state)
    nothing = f.estimate(f.prior(), cnn=None, height=None)  # no observation: the prediction, flagged
    assert nothing.source == "prediction" and math.isclose(nothing.scale, est.scale)
    outlier = f.estimate(f.prior(temporal_scale=est.scale, temporal_log_std=0.01), cnn=3 * est.scale, height=None,
                         temporal_used=True)
    assert outlier.rejected == ["cnn"] and outlier.source == "temporal"
    assert math.isclose(outlier.scale, est.scale)
    per_frame = ScaleFilter(temporal=False, estimate_bias=False, cnn_log_std=0.1, height_log_std=0.05,
                            motion_log_std=0.1, temporal_log_std=0.01, relative_process_std=0.0,
                            bias_prior_log_std=0.5, bias_log_std=0.0, gate_sigma=4.0)
    assert per_frame.estimate(per_frame.prior(), cnn=None, height=None).scale is None  # no memory, no prediction


def test_gates_reject_implausible_results():
    cfg = GateConfig()
    assert check_support("PnP", 21, 173, cfg) is not None  # 12 % inliers
    assert check_support("PnP", 100, 173, cfg) is None
    assert "gate: PnP translation 42" in check_length("PnP", 42.0, 1.1, cfg)
    assert check_length("PnP", 1.2, 1.1, cfg) is None
    assert check_length("E", 1.2, 0.0, cfg) is None  # start from standstill (expected taken as 0.7 m)
    assert check_length("E", 0.4, 1.1, cfg) is not None  # too short for the motion model ...
    assert check_length("PnP", 0.01, 1.1, cfg) is None  # ... but a stop is plausible
    assert check_length("PnP", 42.0, None, cfg) is None  # no expectation yet
    assert check_length("PnP", 42.0, 1.1, GateConfig(enabled=False)) is None


def test_a_stop_needs_an_image_without_parallax(straight):
    """A 0.08 m "stop" after 1 m steps is plausible only when the image agrees: exact flow of a 1 m step has tens of
    pixels of parallax (rejected, saying why); the same points under a pure rotation have none (a stop, accepted)."""
    w, ff, fb, d, rel = straight
    K = w.intrinsics()
    H, W = ff.shape[-2:]
    vv, uu = torch.meshgrid(torch.arange(0, H, 9), torch.arange(0, W, 9), indexing="ij")
    p0 = torch.stack([uu.flatten(), vv.flatten()], -1).to(torch.float64)
    p1 = p0 + ff[1][:, vv.flatten(), uu.flatten()].T.to(torch.float64)
    T_cur_prev = torch.linalg.inv(rel[1])
    moving = image_parallax_px(p0, p1, T_cur_prev[:3, :3], K)
    assert moving > 5.0
    yaw = torch.tensor([[math.cos(0.05), 0.0, math.sin(0.05)], [0.0, 1.0, 0.0], [-math.sin(0.05), 0.0, math.cos(0.05)]],
                       dtype=torch.float64)
    y = torch.cat([p0, torch.ones_like(p0[:, :1])], -1) @ (K.double() @ yaw @ torch.linalg.inv(K.double())).T
    rotated = image_parallax_px(p0, y[:, :2] / y[:, 2:], yaw, K)
    assert rotated < 1e-6
    cfg = GateConfig()
    assert "not a stop" in check_length("E", 0.08, 1.0, cfg, moving)
    assert check_length("E", 0.08, 1.0, cfg, rotated) is None
    assert check_length("E", 0.08, 1.0, cfg) is None  # parallax unknown: the length alone decides
    assert check_length("E", 0.05, 0.08, cfg, moving) is None  # not shorter than the expectation by the factor


def test_gate_rejects_a_planted_absurd_pnp_result(monkeypatch):
    """A planar scene (PnP frames) where PnP returns 42 m on frame 2: rejected, constant motion, flagged; with the
    gates off the absurd pose is used."""
    w = SyntheticWorld(seed=0, num_frames=12, scenario="planar", height=96, width=320)
    frames = [w.render(i, right=False) for i in range(3)]
    ff, fb = torch.stack([f["flow_fwd"] for f in frames]), torch.stack([f["flow_bwd"] for f in frames])
    d = torch.stack([f["depth"] for f in frames])
    real = odometry.track_pnp
    calls = []

    def planted(*args, **kwargs):
        T, ok, nin = real(*args, **kwargs)
        calls.append(1)
        if len(calls) == 2:
            T = T.clone()
            T[0, :3, 3] = T[0, :3, 3] / T[0, :3, 3].norm() * 42.0
        return T, ok, nin

    monkeypatch.setattr(odometry, "track_pnp", planted)
    pnp_alone = ScaleConfig(depth_views=1, fuse_pnp=False)  # PnP's own length: what its gate judges
    res = VisualOdometry(TrackerConfig(scale=pnp_alone)).run(ff, fb, d, w.intrinsics(), batch_size=3)
    assert [r.diagnostics.tracker for r in res] == ["PnP", "constant_motion", "PnP"]
    bad = res[1].diagnostics
    assert bad.gate_rejected and "gate: PnP translation 42" in bad.fallback_reason
    assert torch.equal(res[1].T_prev_cur, res[0].T_prev_cur)
    calls.clear()
    off = VisualOdometry(TrackerConfig(scale=pnp_alone, gate=GateConfig(enabled=False))).run(
        ff, fb, d, w.intrinsics(), batch_size=3)
    assert off[1].diagnostics.tracker == "PnP" and abs(float(off[1].T_prev_cur[:3, 3].norm()) - 42.0) < 1e-6


@pytest.mark.parametrize("road", [TRIANGULATED, NETWORK_DEPTH], ids=["triangulated", "depth"])
def test_batched_equals_streaming_with_camera_height_and_filter(straight, road):
    w, ff, fb, d, rel = straight
    noisy = d * torch.tensor([1.0, 1.1, 0.9, 1.05, 0.95, 1.1])[:, None, None, None]
    d_next = torch.cat([noisy[1:], noisy[-1:]])
    cfg = TrackerConfig(mode="hybrid", scale=ScaleConfig(depth_views=2, camera_height=CAMERA_HEIGHT, temporal=True),
                        road_plane=RoadPlaneConfig(**road))
    K = w.intrinsics()
    batched = VisualOdometry(cfg).run(ff, fb, noisy, K, batch_size=4, depths_next=d_next)
    vo = VisualOdometry(cfg)
    stream = [vo.step(ff[k:k + 1], fb[k:k + 1], noisy[k:k + 1], K[None], depth_cur=d_next[k:k + 1])
              for k in range(ff.shape[0])]
    for a, b in zip(batched, stream, strict=True):
        assert torch.allclose(a.T_w_cur, b.T_w_cur, atol=1e-9)
        da, db = a.diagnostics.as_row(), b.diagnostics.as_row()
        for key in ("tracker", "scale_source", "plane_inliers", "fallback_reason", "gate_rejected"):
            assert da[key] == db[key], key
        for key in ("scale", "scale_cnn", "scale_height", "scale_temporal", "cnn_bias"):
            assert (da[key] is None and db[key] is None) or math.isclose(da[key], db[key], rel_tol=1e-9), key
    assert any(r.diagnostics.scale_temporal is not None for r in batched)
    vo.reset()  # a reset forgets the filter: the first frame again
    again = vo.step(ff[:1], fb[:1], noisy[:1], K[None], depth_cur=d_next[:1])
    assert torch.allclose(again.T_w_cur, batched[0].T_w_cur, atol=1e-9)


def test_bad_scale_settings_raise():
    with pytest.raises(ValueError, match="camera_height"):
        ScaleConfig(camera_height=-1.0)
    with pytest.raises(ValueError, match="road_plane.points"):
        RoadPlaneConfig(points="lidar")
    with pytest.raises(ValueError, match="max_length_ratio"):
        GateConfig(max_length_ratio=1.0)


def _infer_config(*overrides: str):
    from hydra import compose, initialize_config_module

    from dfvo.inference.config import typed

    with initialize_config_module(config_module="dfvo.conf.infer", version_base="1.3"):
        return typed(compose(config_name="infer", overrides=list(overrides)))


def test_dataset_camera_height_reaches_the_tracker():
    """KITTI's dataset config sets the camera 1.65 m above the road and the tracker uses it; data.camera_height=null
    turns it off, an explicit tracker.scale.camera_height wins; the synthetic default sets none."""
    assert _infer_config("data=kitti_odom").tracker.scale.camera_height == 1.65
    assert _infer_config("data=kitti_raw").tracker.scale.camera_height == 1.65
    assert _infer_config("data=kitti_odom", "data.camera_height=null").tracker.scale.camera_height is None
    assert _infer_config("data=kitti_odom", "tracker.scale.camera_height=1.5").tracker.scale.camera_height == 1.5
    assert _infer_config().tracker.scale.camera_height is None
    with pytest.raises(ValueError, match="data.camera_height"):
        _infer_config("data=kitti_odom", "data.camera_height=-1")


def _run_handheld(gate: GateConfig, world: tuple[torch.Tensor, ...]) -> tuple[list, list[float]]:
    """The tracker with these gate settings (a car's motion model: the settings as given throughout) on
    ``world`` (the ``handheld_exact`` fixture): its results and the direction error (degrees) of every E step against
    the true step."""
    ff, fb, d, K, poses = world
    res = VisualOdometry(TrackerConfig(scale=ScaleConfig(camera_height=None), gate=gate, motion="car")).run(
        ff, fb, d[:-1], K, depths_next=d[1:])
    errors = []
    for k, r in enumerate(res):
        t_true = (torch.linalg.inv(poses[k]) @ poses[k + 1])[:3, 3]
        t = r.T_prev_cur[:3, 3].double()
        if r.diagnostics.tracker == "E" and t_true.norm() > 1e-6:
            errors.append(math.degrees(math.acos(float((t @ t_true) / (t.norm() * t_true.norm())))))
    return res, errors


def test_a_direction_confirmed_by_consecutive_frames_is_accepted(handheld_exact: tuple[torch.Tensor, ...]) -> None:
    """The synthetic hand-held world with exact flow and its depth 10x too far (steps of 10-40 cm: the direction
    gate applies): where the hand turns for good, the gate keeps rejecting the true new direction frame after frame
    (constant motion); with ``confirm_direction_frames=2`` the second frame that agrees is accepted, and every
    accepted direction is the true one (exact inputs)."""
    trackers, errors = {}, {}
    for confirm in (None, 2):
        res, errors[confirm] = _run_handheld(GateConfig(confirm_direction_frames=confirm), handheld_exact)
        trackers[confirm] = [r.diagnostics.tracker for r in res]
    cm = {c: sum(t == "constant_motion" for t in v) for c, v in trackers.items()}
    assert cm[None] >= 4 and cm[2] <= cm[None] - 3, cm
    assert max(errors[2]) < 1.0, errors[2]  # what the confirmation accepted is the true motion


def test_a_turn_that_pnp_confirms_in_the_same_frame_is_accepted(handheld_exact: tuple[torch.Tensor, ...]) -> None:
    """The same world (exact flow, depth 10x too far): where the hand turns, E and PnP both find the new direction
    and the direction gate rejects both (constant motion); with ``confirm_direction_by_pnp_deg=30`` E's result is
    accepted in that very frame (PnP, on depth that is wrong in scale but not in shape, turns with it), and every
    accepted direction is the true one (exact inputs)."""
    trackers, errors, confirmed = {}, {}, {}
    for limit in (None, 30.0):
        res, errors[limit] = _run_handheld(GateConfig(confirm_direction_by_pnp_deg=limit), handheld_exact)
        trackers[limit] = [r.diagnostics.tracker for r in res]
        confirmed[limit] = [k for k, r in enumerate(res) if "PnP's result points the same way" in
                            (r.diagnostics.fallback_reason or "")]
    cm = {c: sum(t == "constant_motion" for t in v) for c, v in trackers.items()}
    assert cm[None] >= 4 and cm[30.0] <= cm[None] - 3, cm
    assert confirmed[None] == [] and len(confirmed[30.0]) >= 1, confirmed
    assert all(trackers[None][k] == "constant_motion" and trackers[30.0][k] == "E" for k in confirmed[30.0])
    assert max(errors[30.0]) < 1.0, errors[30.0]  # what the confirmation accepted is the true motion


def test_a_new_pace_confirmed_by_consecutive_frames_is_accepted(planar_exact: tuple[torch.Tensor, ...]) -> None:
    """The planar hand-held world with exact flow and depth: where the hand slows threefold or more and keeps its new
    pace (frames 14 and 33), the length gate rejects the true, shorter lengths of the homography and of PnP frame
    after frame (constant motion at the old pace, up to ``max_consecutive`` frames). With a hand's
    ``confirm_length_frames=2`` the second frame that agrees is accepted and the gate expects the new pace from then
    on; each length so accepted is the true one (exact inputs), and every direction is the true one either way.
    (What stays wrong: the first frame of each change, and the frames where the scale filter itself gates the true
    observation out and uses its prediction until ``scale_filter.max_rejections``.)"""
    ff, fb, d, K, poses = planar_exact
    true = torch.linalg.inv(poses[:-1]) @ poses[1:]
    runs = {}
    for confirm in (None, 2):
        cfg = TrackerConfig(scale=ScaleConfig(camera_height=None), motion="handheld",
                            handheld=HandheldConfig(confirm_length_frames=confirm))
        runs[confirm] = VisualOdometry(cfg).run(ff, fb, d[:-1], K, depths_next=d[1:])
    ratio = {c: [float(r.T_prev_cur[:3, 3].norm() / true[k, :3, 3].norm().clamp_min(1e-12)) for k, r in enumerate(res)]
             for c, res in runs.items()}
    moving = [k for k in range(len(true)) if float(true[k, :3, 3].norm()) > 1e-3]
    wrong = {c: [k for k in moving if abs(r[k] - 1.0) > 0.1] for c, r in ratio.items()}  # length off by > 10 %
    cm = {c: sum(r.diagnostics.tracker == "constant_motion" for r in res) for c, res in runs.items()}
    assert len(wrong[None]) >= 18 and len(wrong[2]) <= 12 and cm[2] <= cm[None] - 10, (wrong, cm)
    confirmed = [k for k, r in enumerate(runs[2]) if "agree on the new length" in (r.diagnostics.fallback_reason or "")]
    assert len(confirmed) >= 2 and all(runs[2][k - 1].diagnostics.tracker == "constant_motion" for k in confirmed)
    assert all(abs(ratio[2][k] - 1.0) < 0.02 for k in confirmed), [ratio[2][k] for k in confirmed]
    for c, res in runs.items():
        for k in moving:
            if res[k].diagnostics.tracker != "constant_motion":
                t, t_true = res[k].T_prev_cur[:3, 3].double(), true[k, :3, 3]
                assert float((t @ t_true) / (t.norm() * t_true.norm())) > math.cos(math.radians(1.0)), (c, k)


def test_a_first_road_observation_moves_the_network_s_length_and_its_bias_together():
    """Frames with the CNN scale alone keep the network's length (its bias unknown: ``x + b``); when the first road
    observation makes the bias observable, the kept length is uncertain by the bias's prior and anti-correlated with
    it, so the road observation moves both (hand-derived Kalman update). KITTI 06 at every third frame started so:
    the network's 2.19 m against the road's 3.80 m, and the lengths stayed short when the bias started at 1."""
    cnn_var, motion_var, bias_var, road_var = 0.1 ** 2, 0.1 ** 2, 0.5 ** 2, 0.07 ** 2
    f = ScaleFilter(temporal=True, estimate_bias=False, cnn_log_std=0.1, height_log_std=0.05, motion_log_std=0.1,
                    temporal_log_std=0.01, relative_process_std=0.0, bias_prior_log_std=0.5, bias_log_std=0.0,
                    gate_sigma=4.0, warmup_frames=0)
    network, road = 2.19, 3.80  # the network's first length (its bias 0.58) and the road's length, metres
    first = f.estimate(f.prior(), cnn=network, height=None)
    x, pxx = first.state.x, first.state.pxx  # log 2.19 and the CNN's variance (after a prior of 1e6)
    assert first.source == "cnn" and math.isclose(x, math.log(network), rel_tol=1e-6)
    assert math.isclose(pxx, cnn_var, rel_tol=1e-6)
    f.commit(first.state)
    prior = f.start_bias_estimate(f.prior())
    # by hand: x with variance cnn + motion + bias, covariance with b -bias, b = 0 with variance bias
    assert math.isclose(prior.pxx, pxx + motion_var + bias_var) and math.isclose(prior.pxb, -bias_var)
    assert prior.x == x and prior.b == 0.0 and math.isclose(prior.pbb, bias_var)
    est = f.estimate(prior, cnn=None, height=None, homography=road, homography_log_std=0.07)
    s = pxx + motion_var + bias_var + road_var
    y = math.log(road) - x
    assert math.isclose(math.log(est.scale), x + (pxx + motion_var + bias_var) / s * y)
    assert math.isclose(math.log(est.bias), -bias_var / s * y)
    assert abs(est.scale / road - 1) < 0.03  # the road's length, not the network's (0.58 of it) ...
    assert 0.55 < est.bias < 0.65  # ... and the network's factor found in the same update
