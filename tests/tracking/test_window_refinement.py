"""The sliding-window bundle adjustment (``tracker.window``): on exact tracks of a known scene its solver returns the
true rotations and ratios of the step lengths from perturbed steps, its Jacobians match finite differences, tracks
are carried by the flow (one per cell, stopped by an inconsistent flow), a refinement beyond the limits or with too
few tracks is not used, the loop's streaming and batched runs give identical poses with it on, and ``infer.py``
reports what it refined."""

from __future__ import annotations

import math

import pytest
import torch

from dfvo.geometry.essential_refine import so3_exp
from dfvo.geometry.se3 import pose_from_rt, se3_inverse
from dfvo.tracking.config import WindowConfig
from dfvo.tracking.window_refinement import (
    WindowProblem,
    WindowRefiner,
    _compose,
    _Geometry,
    _reprojection,
    _whitening,
    judge_refinement,
    solve_window,
)

K = torch.tensor([[500.0, 0.0, 320.0], [0.0, 500.0, 96.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def _scene(n: int = 4, m: int = 300, seed: int = 0):
    """True window poses T_0j (forward motion ~1 m a frame with a slight turn), points seen in all frames, and
    their exact pixels (M,n,2)."""
    g = torch.Generator().manual_seed(seed)
    steps = []
    for k in range(n - 1):
        R = so3_exp(torch.tensor([0.002 * k, 0.01, -0.001], dtype=torch.float64))
        steps.append(pose_from_rt(R[None], torch.tensor([[0.02, -0.01, 1.0]], dtype=torch.float64))[0])
    poses = [torch.eye(4, dtype=torch.float64)]
    for S in steps:
        poses.append(poses[-1] @ S)
    poses = torch.stack(poses)
    X = torch.stack([torch.rand(m, generator=g, dtype=torch.float64) * 16 - 8,
                     torch.rand(m, generator=g, dtype=torch.float64) * 3 - 1.0,
                     torch.rand(m, generator=g, dtype=torch.float64) * 30 + 8], -1)  # frame 0
    obs = []
    for T in poses:
        Xc = (se3_inverse(T) @ torch.cat([X, torch.ones(m, 1, dtype=torch.float64)], -1).T).T[:, :3]
        uv = (Xc @ K.T)[:, :2] / Xc[:, 2:]
        obs.append(uv)
    return poses, torch.stack(steps), torch.stack(obs, 1), X[:, 2]


def _prob(steps, obs, zcnn, rot_std=0.01, len_std=0.05):
    cov = torch.diag(torch.tensor([rot_std] * 3 + [len_std] * 3, dtype=torch.float64) ** 2)
    L = torch.stack([_whitening(cov)] * len(steps))
    return WindowProblem(steps, L, obs, zcnn, K)


def test_exact_tracks_recover_the_true_shape_from_perturbed_steps() -> None:
    """The tracker's steps 2 and 3 are 0.2 deg and 3 % off, the network's depth 10 % off: on exact tracks the window
    returns the true rotations and the true ratios of the step lengths; the one scale left free by monocular
    geometry is the steps' (between their true length and 3 % above), not the network's."""
    poses, steps, obs, z0 = _scene()
    bad = steps.clone()
    for k in range(1, len(bad)):
        R = so3_exp(torch.tensor([0.0, math.radians(0.2), 0.0], dtype=torch.float64))
        bad[k, :3, :3] = R @ bad[k, :3, :3]
        bad[k, :3, 3] *= 1.03
    prob = _prob(bad, obs, z0 * 1.1)
    cfg = WindowConfig(enabled=True, pixel_sigma=0.01, iterations=30, depth_log_std=1.0)
    est, _ = solve_window(prob, cfg, inflation=1.0)
    est_steps = se3_inverse(est[:-1]) @ est[1:]
    dR = est_steps[:, :3, :3] @ steps[:, :3, :3].transpose(-1, -2)
    ang = torch.rad2deg(torch.arccos(((dR.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)))
    assert ang.max() < 1e-3  # the perturbation was 0.2 deg
    lengths, true = est_steps[:, :3, 3].norm(dim=-1), steps[:, :3, 3].norm(dim=-1)
    torch.testing.assert_close(lengths / lengths[0], true / true[0], atol=1e-5, rtol=0)  # given: 1, 1.03, 1.03
    assert 1.0 < float(lengths[0] / true[0]) < 1.03
    direction = est_steps[:, :3, 3] / lengths[:, None]
    torch.testing.assert_close(direction, steps[:, :3, 3] / true[:, None], atol=1e-5, rtol=0)


def test_reprojection_jacobians_match_finite_differences() -> None:
    poses, steps, obs, z0 = _scene(n=3, m=20)
    prob = _prob(steps, obs, z0)
    geo = _Geometry(prob)
    g = torch.Generator().manual_seed(3)
    poses = _compose(poses, torch.randn(3, 6, generator=g, dtype=torch.float64) * 0.01)
    rho = 1.0 / (z0 * (1 + 0.1 * torch.rand(len(z0), generator=g, dtype=torch.float64)))
    r, J_view, J_anchor, J_rho, front = _reprojection(geo, poses, rho, K)
    assert bool(front.all())
    h = 1e-6
    for frame in (1, 2):
        for d in range(6):
            xi = torch.zeros(3, 6, dtype=torch.float64)
            xi[frame, d] = h
            rp = _reprojection(geo, _compose(poses, xi), rho, K)[0]
            xi[frame, d] = -h
            rm = _reprojection(geo, _compose(poses, xi), rho, K)[0]
            num = (rp - rm) / (2 * h)
            ana = torch.where((geo.view == frame)[:, None], J_view[:, :, d], torch.zeros_like(num)) + \
                torch.where((geo.src == frame)[:, None], J_anchor[:, :, d], torch.zeros_like(num))
            torch.testing.assert_close(ana, num, atol=1e-4, rtol=1e-5)
    dr = h * 1e-2
    num = (_reprojection(geo, poses, rho + dr, K)[0] - _reprojection(geo, poses, rho - dr, K)[0]) / (2 * dr)
    torch.testing.assert_close(J_rho, num, atol=1e-3, rtol=1e-5)


def _refiner(**kw) -> WindowRefiner:
    return WindowRefiner(WindowConfig(enabled=True, **kw), inflation=1.0, max_depth=80.0, depth_crop_top=0.0)


def test_tracks_are_carried_by_the_flow_and_new_ones_fill_empty_cells() -> None:
    ref = _refiner(frames=3, cell_px=8)
    H, W = 64, 96
    flow = torch.zeros(1, 2, H, W)
    flow[:, 0] = 2.5  # every pixel moves 2.5 px right, 1 px down
    flow[:, 1] = 1.0
    incon = torch.zeros(1, 1, H, W)
    depth = torch.full((1, 1, H, W), 10.0)
    T = pose_from_rt(torch.eye(3, dtype=torch.float64)[None], torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))[0]
    cov = torch.eye(6, dtype=torch.float64) * 1e-4
    p0 = torch.tensor([[10.0, 10.0], [11.0, 11.0], [40.0, 20.0]], dtype=torch.float64)  # two in one 8-px cell
    ref.update(T, cov, True, p0, p0 + torch.tensor([2.5, 1.0], dtype=torch.float64), flow, incon, depth, K)
    assert len(ref.obs) == 2  # one track per cell
    torch.testing.assert_close(ref.obs[:, -1], torch.tensor([[12.5, 11.0], [42.5, 21.0]], dtype=torch.float64))
    assert torch.isnan(ref.obs[:, 0]).all() and (ref.zcnn[:, -2] == 10.0).all()
    # the next pair: both tracks carried 2.5 px on; a new correspondence in a cell of a carried track starts nothing,
    # one in an empty cell starts a track, one outside the image none
    q = torch.tensor([[12.5, 11.0], [70.0, 30.0], [94.5, 63.5]], dtype=torch.float64)
    ref.update(T, cov, True, q, q + torch.tensor([2.5, 1.0], dtype=torch.float64), flow, incon, depth, K)
    assert len(ref.obs) == 3
    torch.testing.assert_close(ref.obs[:2, -1], torch.tensor([[15.0, 12.0], [45.0, 22.0]], dtype=torch.float64))
    torch.testing.assert_close(ref.obs[2, -2:], torch.tensor([[70.0, 30.0], [72.5, 31.0]], dtype=torch.float64))
    assert bool(ref.alive.all())
    # too few tracks for min_tracks (50): the step is not refined, and says why
    res = ref.update(T, cov, True, q[:0], q[:0], flow, torch.full_like(incon, 9.0), depth, K)
    assert res.T_prev_cur is None and res.rejected.startswith("window: 0 tracks reach this frame")
    # a constant-motion frame empties the window
    res = ref.update(T, None, False, q, q, flow, incon, depth, K)
    assert res.T_prev_cur is None and len(ref.obs) == 0 and ref.steps == []


def test_inconsistent_flow_ends_a_track() -> None:
    ref = _refiner(frames=3, max_inconsistency=0.5)
    H, W = 64, 96
    flow, incon, depth = torch.ones(1, 2, H, W), torch.zeros(1, 1, H, W), torch.full((1, 1, H, W), 10.0)
    T, cov = torch.eye(4, dtype=torch.float64), torch.eye(6, dtype=torch.float64)
    p = torch.tensor([[10.0, 10.0], [50.0, 40.0]], dtype=torch.float64)
    ref.update(T, cov, True, p, p + 1, flow, incon, depth, K)
    incon[..., 35:, :] = 0.6  # the second track's position (51, 41) is inconsistent in the next pair's flow
    ref.update(T, cov, True, p[:0], p[:0], flow, incon, depth, K)
    assert ref.alive.tolist() == [True, False]
    assert bool(torch.isfinite(ref.obs[0, -1]).all()) and bool(torch.isnan(ref.obs[1, -1]).all())


def test_a_refinement_beyond_the_limits_is_not_used() -> None:
    cfg = WindowConfig(enabled=True, max_rotation_change_deg=0.5, max_length_change=0.25)
    T = pose_from_rt(torch.eye(3, dtype=torch.float64)[None], torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))[0]

    def moved(deg: float, scale: float) -> torch.Tensor:
        R = so3_exp(torch.tensor([0.0, math.radians(deg), 0.0], dtype=torch.float64))
        return pose_from_rt(R[None], T[None, :3, 3] * scale)[0]

    ok = judge_refinement(T, moved(0.4, 1.2), 80, cfg)
    assert ok.T_prev_cur is not None and ok.rejected is None
    assert abs(ok.length_ratio - 1.2) < 1e-12 and abs(ok.rotation_change_deg - 0.4) < 1e-9
    for deg, scale in ((0.6, 1.0), (0.0, 1.3), (0.0, 0.7)):
        bad = judge_refinement(T, moved(deg, scale), 80, cfg)
        assert bad.T_prev_cur is None and "refinement not used" in bad.rejected, (deg, scale)
    still = torch.eye(4, dtype=torch.float64)
    assert judge_refinement(still, still, 80, cfg).T_prev_cur is not None  # a stop stays a stop
    assert judge_refinement(still, T, 80, cfg).T_prev_cur is None


def test_window_config_refuses_impossible_settings() -> None:
    with pytest.raises(ValueError, match="tracker.window: frames=2"):
        WindowConfig(frames=2)
    with pytest.raises(ValueError, match="pixel_sigma"):
        WindowConfig(pixel_sigma=0.0)


def test_streaming_equals_batched_and_exact_flow_stays_exact() -> None:
    from dfvo.synthetic import SyntheticWorld
    from dfvo.tracking import TrackerConfig, VisualOdometry
    from dfvo.tracking.config import CovarianceConfig, ScaleConfig

    n = 8
    w = SyntheticWorld(seed=0, num_frames=n + 1, scenario="drive")
    frames = [w.render(i) for i in range(n)]
    ff = torch.stack([f["flow_fwd"] for f in frames])
    fb = torch.stack([f["flow_bwd"] for f in frames])
    d = torch.stack([f["depth"] for f in frames])
    K_w = w.intrinsics()

    def cfg() -> TrackerConfig:
        return TrackerConfig(scale=ScaleConfig(method="simple", depth_views=1),
                             covariance=CovarianceConfig(inflation=1.0, correlated=True),
                             window=WindowConfig(enabled=True, frames=4))

    batched = VisualOdometry(cfg()).run(ff, fb, d, K_w, batch_size=3)
    vo = VisualOdometry(cfg())
    stream = [vo.step(ff[k:k + 1], fb[k:k + 1], d[k:k + 1], K_w[None]) for k in range(n)]
    for a, b in zip(batched, stream, strict=True):
        assert torch.allclose(a.T_w_cur, b.T_w_cur, atol=1e-9)
    refined = [r for r in batched if r.diagnostics.window_length_ratio is not None]
    assert len(refined) >= n - 3  # from the third frame of the window on
    assert all(r.diagnostics.window_tracks >= 50 for r in refined)
    P = w.poses()
    err = torch.stack([(r.T_prev_cur[:3, 3] - (torch.linalg.inv(P[k]) @ P[k + 1])[:3, 3]).norm()
                       for k, r in enumerate(batched)])
    # exact flow and depth: the tracker's steps are exact to 1e-6 m; the window's to ~1e-4 m (tracks carried by
    # bilinear samples of the flow between pixel centres are not exact where the flow field curves)
    assert err.max() < 2e-4


def test_infer_with_the_window_reports_what_it_refined(tmp_path) -> None:
    import csv
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[2]
    n = 8
    env = dict(os.environ, OMP_NUM_THREADS="1", HYDRA_FULL_ERROR="0")
    proc = subprocess.run([sys.executable, "infer.py", f"out_dir={tmp_path}", f"data.num_frames={n}",
                           "img_res.height=96", "img_res.width=320", "progress=false", "num_threads=1",
                           "flow=oracle", "depth=oracle", "tracker.window.enabled=true",
                           "tracker.window.min_tracks=20"],
                          cwd=repo, capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((tmp_path / "summary.json").read_text())
    window = summary["fallback"]["window"]
    assert window["refined"] + window["not_refined"] == n - 1 and window["refined"] >= n - 3
    rows = list(csv.DictReader((tmp_path / "frames.csv").open()))
    ratios = [float(r["window_length_ratio"]) for r in rows if r.get("window_length_ratio") not in (None, "")]
    assert len(ratios) == window["refined"] and all(abs(x - 1.0) < 0.05 for x in ratios)
    assert json.loads((tmp_path / "metrics.json").read_text())["rpe_m"] < 2e-3
