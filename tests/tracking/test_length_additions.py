"""The length of each step beyond the paper (issue 24): the rotation-compensated parallax and the planar-scene rule of
model selection, the filter's robust start and its restart, the camera height estimated from the network's road,
and the CNN bias learnt only where something else measures the metric scale. Truth: hand-derived projections,
the filter's own equations, the synthetic world's exact depth and poses."""

import math

import pytest
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from dfvo.synthetic import CAMERA_HEIGHT, SyntheticWorld
from dfvo.tracking import TrackerConfig, VisualOdometry
from dfvo.tracking.config import CameraHeightConfig, RoadPlaneConfig, ScaleConfig, ScaleFilterConfig
from dfvo.tracking.model_selection import homography_to_essential_residual, rotation_compensated_parallax
from dfvo.tracking.scale_filter import ScaleFilter

torch.set_num_threads(1)
D = torch.float64
K = torch.tensor([[500.0, 0.0, 320.0], [0.0, 500.0, 96.0], [0.0, 0.0, 1.0]], dtype=D)


def project(X: torch.Tensor) -> torch.Tensor:
    """(N,2) pixels of camera points X (N,3) under :data:`K`."""
    x = X @ K.T
    return x[:, :2] / x[:, 2:]


def scene(n: int = 200, planar: bool = False, seed: int = 0) -> torch.Tensor:
    """(N,3) points in front of the camera: on the road plane y = 1.65 (planar) or at depths 5-40 m anywhere."""
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(n, 3, generator=g, dtype=D)
    if planar:
        z = 5 + 35 * u[:, 2]
        return torch.stack([(u[:, 0] - 0.5) * 0.4 * z, torch.full_like(z, 1.65), z], -1)
    z = 5 + 35 * u[:, 2]
    return torch.stack([(u[:, 0] - 0.5) * 1.2 * z, (u[:, 1] - 0.5) * 0.35 * z, z], -1)


def turn(deg: float) -> torch.Tensor:
    """(3,3) a rotation of ``deg`` degrees about the camera's y axis (a car turning)."""
    return axis_angle_to_rotation_matrix(torch.tensor([[0.0, math.radians(deg), 0.0]], dtype=D))[0]


# ------------------------------------------------------------------------------------------ model selection
@pytest.mark.parametrize("deg", [0.0, 3.0])
def test_parallax_of_a_pure_rotation_is_zero_and_of_a_translation_its_image_motion(deg):
    """A pure rotation (any angle) moves no point off the infinite homography: zero parallax. Add a translation and
    each point's parallax is the distance between its projections with and without it (hand-derived)."""
    X = scene()
    R = turn(deg)
    pts_i = project(X)
    rotated = X @ R.T
    rows = torch.ones(1, X.shape[0], dtype=torch.bool)
    rot_only = rotation_compensated_parallax(pts_i[None], project(rotated)[None], rows, R[None], K[None])
    assert float(rot_only) < 1e-6
    t = torch.tensor([0.05, 0.0, -1.0], dtype=D)  # T_cur_prev's translation of a car driving 1 m forward
    moved = project(rotated + t)
    expected = (moved - project(rotated)).norm(dim=-1).quantile(0.5)
    got = rotation_compensated_parallax(pts_i[None], moved[None], rows, R[None], K[None])
    assert torch.allclose(got, expected[None], rtol=1e-9)
    assert float(got) > 5.0  # a turning car's step moves the image by pixels: E sees its translation


def test_homography_residual_ratio_tells_a_planar_scene_from_a_deep_one():
    """E = [t]x R and the road plane's homography H = K (R + t n^T / d) K^-1: on road points H fits exactly (ratio at
    the noise floor's zero, i.e. ~0); on points at all depths H fails by pixels while E fits (ratio far above 2)."""
    R, t = turn(2.0), torch.tensor([0.05, 0.0, -1.0], dtype=D)
    tx = torch.tensor([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]], dtype=D)
    E = tx @ R
    n, d = torch.tensor([0.0, 1.0, 0.0], dtype=D), 1.65  # n^T X = d on the road
    H = K @ (R + torch.outer(t, n) / d) @ torch.linalg.inv(K)
    ratios = []
    for planar in (True, False):
        X = scene(planar=planar)
        pi, pj = project(X), project(X @ R.T + t)
        rows = torch.ones(1, X.shape[0], dtype=torch.bool)
        ratios.append(float(homography_to_essential_residual(H[None], E[None], K[None], pi[None], pj[None], rows,
                                                             floor_px=0.05)))
    assert ratios[0] < 1e-6, ratios
    assert ratios[1] > 20.0, ratios


# ------------------------------------------------------------------------------------------ the scale filter
def make_filter(**kw) -> ScaleFilter:
    return ScaleFilter.from_config(ScaleFilterConfig(**kw), temporal=True, height_log_std=0.03)


def run_filter(f: ScaleFilter, cnn: list[float], temporal: list[float | None] | None = None) -> list[float]:
    out = []
    for k, z in enumerate(cnn):
        tz = temporal[k] if temporal is not None else None
        prior = f.prior(tz, None)
        est = f.estimate(prior, z, None, temporal_used=tz is not None and f.state.known)
        f.commit(est.state, est.all_rejected)
        out.append(est.scale)
    return out


def test_filter_start_is_not_the_first_observation_alone():
    """The first CNN scale is half the truth (1.0), the next ones right: with the warm-up no observation is gated out
    while the average forms, so by the 5th frame the estimate is within 5 % of 1; without it (warmup_frames=0) the
    first value locks the filter and the right ones are gated out as outliers until ``max_rejections`` frames in a
    row restart it."""
    cnn = [0.5] + [1.0] * 5
    robust = run_filter(make_filter(), cnn)
    blind = run_filter(make_filter(warmup_frames=0), cnn)
    assert abs(robust[4] - 1.0) < 0.05, robust
    assert abs(blind[2] - 0.5) < 0.05, blind


def test_filter_restarts_when_its_prediction_runs_away():
    """After a settled start, the relative scale (prediction) claims 2x each frame while the CNN keeps saying 1 m: the
    CNN is gated out against the confident prediction, but after ``max_rejections`` frames of disagreement the filter
    restarts from the observations and is back at 1 m."""
    f = make_filter()
    run_filter(f, [1.0] * 8, [None] + [1.0] * 7)
    out = run_filter(f, [1.0] * 6, [2.0] * 6)
    n = ScaleFilterConfig.max_rejections
    assert all(v > 1.9 for v in out[:n]), out  # the prediction wins at first
    assert abs(out[n] - 1.0) < 0.01, out


def test_filter_is_not_restarted_by_observations_that_contradict_each_other():
    """KITTI 07's turn into a side street (frames 137-140 with the depth campaign's network): the relative scale keeps
    the true 1 m, the road alignment reads the side street's slope as 1.8-2x, the CNN scale stays near the truth but
    has one frame at half of it. The CNN and the road alignment contradict each other (more than ``gate_sigma``
    apart), so their mean is no evidence against the prediction: the filter holds 1 m (it used to count those
    frames as a runaway prediction and restart from their fusion, ~1.4 m, carried on by the relative scale). When
    the two agree with each other instead (both 2x), the prediction is outvoted after ``max_rejections`` frames, as
    before."""
    def run(cnn: list[float], homography: list[float]) -> list[float]:
        f, out = make_filter(), []
        for k in range(8 + len(cnn)):  # a settled start at the truth, then the frames of the case
            z_cnn, z_h = (1.0, 1.0) if k < 8 else (cnn[k - 8], homography[k - 8])
            prior = f.prior(1.0 if k > 0 else None, None)
            est = f.estimate(prior, z_cnn, None, temporal_used=k > 0 and f.state.known, homography=z_h,
                             homography_log_std=0.07)
            f.commit(est.state, est.all_rejected)
            out.append(est.scale)
        return out[8:]

    contradicting = run(cnn=[1.1, 1.1, 0.55, 0.9, 1.0, 1.0], homography=[1.8, 1.8, 1.9, 2.0, 2.0, 2.0])
    assert all(abs(v - 1.0) < 0.05 for v in contradicting), contradicting
    agreeing = run(cnn=[2.0] * 6, homography=[2.0] * 6)
    n = ScaleFilterConfig.max_rejections
    assert all(abs(v - 1.0) < 0.05 for v in agreeing[:n]), agreeing
    assert abs(agreeing[n] - 2.0) < 0.01, agreeing


# ------------------------------------------------------------------------------------------ camera height
@pytest.fixture(scope="module")
def straight(straight_pairs):
    """Seven pairs of straight driving with exact flow and depth."""
    return straight_pairs(8)


def test_estimated_camera_height_is_the_networks_road_height(straight):
    """No height given: the estimate is the depth network's own road height — exactly the true 1.65 m on exact depth,
    1.3x that on depth 30 % too far (the network's ruler, the same on every frame)."""
    w, ff, fb, d, rel = straight
    for factor in (1.0, 1.3):
        cfg = TrackerConfig(mode="e", scale=ScaleConfig(depth_views=1), road_plane=RoadPlaneConfig(points="depth"),
                            camera_height=CameraHeightConfig(estimate=True))
        res = VisualOdometry(cfg).run(ff, fb, factor * d, w.intrinsics(), batch_size=3)
        heights = [r.diagnostics.camera_height for r in res]
        assert heights[0] is None  # fewer frames than min_frames
        assert heights[-1] == pytest.approx(factor * CAMERA_HEIGHT, rel=1e-4), heights


def test_cnn_bias_is_not_learnt_without_a_metric_observation(straight):
    """Camera height given, but nothing measures the road (no plane points, no images): the CNN's bias is not
    observable, so one frame's depth 30 % short must not be learnt as a bias that shortens every later step (it
    used to be, through the relative scale). Exact depth elsewhere: after the wrong frame the steps return to the
    truth (the relative scale carries the error, the CNN pulls it back, and no bias holds it)."""
    w, ff, fb, d, rel = straight
    bad = d.clone()
    bad[3] = 0.7 * d[3]
    cfg = TrackerConfig(mode="e", scale=ScaleConfig(depth_views=1, camera_height=CAMERA_HEIGHT),
                        road_plane=RoadPlaneConfig(points="none"), camera_height=CameraHeightConfig(estimate=False))
    res = VisualOdometry(cfg).run(ff, fb, bad, w.intrinsics(), batch_size=3)
    true = rel[:, :3, 3].norm(dim=-1)
    got = torch.stack([r.T_prev_cur[:3, 3].norm() for r in res])
    assert all(r.diagnostics.cnn_bias in (None, 1.0) for r in res), [r.diagnostics.cnn_bias for r in res]
    err = (got / true - 1).abs()
    assert (err[:3] < 1e-5).all() and err[3] > 0.05, err
    assert (err[4:].diff() < 0).all() and err[-1] < err[3] / 1.5, err


def test_pnp_length_goes_through_the_filter():
    """A planar scene (every frame PnP) whose 6th frame has its depth 50 % too far: PnP's own length is then 1.5x the
    truth (``fuse_pnp=false``, the paper); through the filter that observation is gated out and the three-frame
    relative scale gives the true length, flagged in ``scale_source``. Every other frame exact either way."""
    w = SyntheticWorld(seed=0, num_frames=12, scenario="planar", height=96, width=320)
    frames = [w.render(i, right=False) for i in range(8)]
    ff, fb = torch.stack([f["flow_fwd"] for f in frames]), torch.stack([f["flow_bwd"] for f in frames])
    d = torch.stack([f["depth"] for f in frames])
    P = w.poses()
    true = (torch.linalg.inv(P[:-1]) @ P[1:])[:8, :3, 3].norm(dim=-1)
    bad = d.clone()
    bad[5] = 1.5 * d[5]
    ratios = {}
    for fuse in (False, True):
        cfg = TrackerConfig(scale=ScaleConfig(depth_views=1, fuse_pnp=fuse),
                            camera_height=CameraHeightConfig(estimate=False), motion="car")  # PnP on the plane
        res = VisualOdometry(cfg).run(ff, fb, bad, w.intrinsics(), batch_size=3)
        assert all(r.diagnostics.tracker == "PnP" for r in res)
        ratios[fuse] = torch.stack([r.T_prev_cur[:3, 3].norm() for r in res]) / true
        if fuse:
            assert "rejected:cnn" in res[5].diagnostics.scale_source
    others = [k for k in range(8) if k != 5]
    assert (ratios[False][others] - 1).abs().max() < 1e-5 and abs(float(ratios[False][5]) - 1.5) < 1e-5
    assert (ratios[True] - 1).abs().max() < 1e-4, ratios[True]
