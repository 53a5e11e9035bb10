"""Depth on every k-th frame only (``depth.every``): the source computes the frames it must and NaN for the others;
the tracker takes each pair's scale, road plane and PnP points from its frame with depth (PnP backwards when only
the later frame has one), with poses as exact as with depth everywhere on the synthetic world's true flow and depth;
``infer.py depth.every=2`` runs end to end and reports the setting; a setting that leaves pairs without any depth is
one clear error."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from dfvo.inference.config import InferConfig, typed
from dfvo.sources.every_kth import EveryKthDepth
from dfvo.sources.oracle import OracleDepth
from dfvo.synthetic import SyntheticWorld
from dfvo.tracking import TrackerConfig, VisualOdometry
from dfvo.tracking.config import ScaleConfig
from dfvo.tracking.scale import has_depth

REPO = Path(__file__).resolve().parents[2]


def _pairs(scenario: str, num_frames: int, every: int):
    """Flows of the world's pairs, and the depths of each pair's earlier and later frame with NaN on the frames an
    ``every``-th-frame depth source skips."""
    w = SyntheticWorld(seed=0, num_frames=num_frames, scenario=scenario)
    frames = [w.render(i) for i in range(num_frames - 1)]
    ff = torch.stack([f["flow_fwd"] for f in frames])
    fb = torch.stack([f["flow_bwd"] for f in frames])
    src = OracleDepth(w)
    img = torch.zeros(num_frames, 3, *ff.shape[-2:])
    depths = EveryKthDepth(src, every)(img, list(range(num_frames))) if every > 1 else src(img, list(range(num_frames)))
    return w, ff, fb, depths[:-1], depths[1:]


def _step_errors(world: SyntheticWorld, results) -> torch.Tensor:
    P = world.poses()
    return torch.stack([(r.T_prev_cur[:3, 3] - (torch.linalg.inv(P[k]) @ P[k + 1])[:3, 3]).norm()
                        for k, r in enumerate(results)])


def _cfg(**kw) -> TrackerConfig:
    return TrackerConfig(scale=ScaleConfig(depth_views=2), **kw)


def test_the_source_runs_on_every_kth_frame_only() -> None:
    w = SyntheticWorld(seed=0, num_frames=7, height=32, width=64)
    calls: list[list[int]] = []

    class Counting(OracleDepth):
        def __call__(self, images, indices=None):
            calls.append(list(indices))
            return super().__call__(images, indices)

    src = EveryKthDepth(Counting(w), 3)
    assert src.name == "oracle"
    depth = src(torch.zeros(4, 3, 32, 64), [2, 3, 4, 6])
    assert calls == [[3, 6]]
    torch.testing.assert_close(depth[1], w.depth(3))
    torch.testing.assert_close(depth[3], w.depth(6))
    assert depth[[0, 2]].isnan().all() and not has_depth(depth[:1]) and has_depth(depth[1:2])
    assert src(torch.zeros(2, 3, 32, 64), [4, 5]).isnan().all() and calls == [[3, 6]]  # no call without work
    with pytest.raises(ValueError, match="needs each image's frame index"):
        src(torch.zeros(2, 3, 32, 64))
    with pytest.raises(ValueError, match="every=1"):
        EveryKthDepth(OracleDepth(w), 1)


def test_every_second_depth_keeps_the_poses_exact() -> None:
    """Half the frames without depth: pairs (odd, even) take the later frame's scale and road plane; every step is
    as exact as with depth everywhere, and streaming equals batched."""
    w, ff, fb, d, d_next = _pairs("drive", 12, 2)
    assert not has_depth(d[1:2]) and has_depth(d_next[1:2]) and has_depth(d[2:3]) and not has_depth(d_next[2:3])
    res = VisualOdometry(_cfg()).run(ff, fb, d, w.intrinsics(), batch_size=4, depths_next=d_next)
    assert all(r.diagnostics.tracker in ("E", "PnP") for r in res)
    assert _step_errors(w, res).max() < 1e-3
    # the E pairs whose earlier frame has no depth fit the road plane to the later frame's (no camera height is
    # given: it is estimated from these planes, and the road alignment is placed with them)
    odd_e = [r.diagnostics for r in res[1::2] if r.diagnostics.tracker == "E"]
    assert len(odd_e) >= 2 and all(g.plane_inliers > 100 and abs(g.camera_height_fit - 1.65) < 0.01 for g in odd_e)
    vo = VisualOdometry(_cfg())
    K = w.intrinsics()
    for k, r in enumerate(res[:5]):
        s = vo.step(ff[k:k + 1], fb[k:k + 1], d[k:k + 1], K[None], depth_cur=d_next[k:k + 1])
        assert torch.allclose(s.T_w_cur, r.T_w_cur, atol=1e-9)


def test_pnp_runs_backwards_when_only_the_later_frame_has_depth() -> None:
    """A pure rotation sends every pair to PnP (GRIC prefers H); the pairs whose earlier frame has no depth lift the
    later frame's points instead and invert the pose: as exact as forwards, with a covariance of the same size."""
    w, ff, fb, d, d_next = _pairs("rotation", 5, 2)
    _, _, _, d_all, d_all_next = _pairs("rotation", 5, 1)
    K = w.intrinsics()
    sparse = VisualOdometry(_cfg()).run(ff, fb, d, K, batch_size=4, depths_next=d_next)
    dense = VisualOdometry(_cfg()).run(ff, fb, d_all, K, batch_size=4, depths_next=d_all_next)
    assert all(r.diagnostics.tracker == "PnP" and r.diagnostics.pnp_success for r in sparse)
    assert _step_errors(w, sparse).max() < 1e-3
    for k in (1, 3):  # the backwards pairs
        a, b = sparse[k], dense[k]
        assert torch.allclose(a.T_prev_cur, b.T_prev_cur, atol=1e-3)
        cov_a, cov_b = a.covariance, b.covariance
        assert torch.allclose(cov_a, cov_a.T) and bool((torch.linalg.eigvalsh(cov_a) > 0).all())
        ratio = cov_a.diagonal() / cov_b.diagonal()
        assert bool(((ratio > 0.2) & (ratio < 5.0)).all()), ratio


def test_the_backwards_pnp_covariance_is_calibrated() -> None:
    """PnP run backwards (the current frame's points seen in the previous image) on 0.5 px pixel noise, a large step
    (0.5 rad, 5 m) where the step's and its inverse's errors differ: the mean NEES of the step over 100 trials is
    that of a 6-D chi-square (6), while the forward formula on the swapped roles is not (measured ~12.5)."""
    from dfvo.geometry.essential_refine import so3_exp
    from dfvo.geometry.pnp import solve_pnp_ransac
    from dfvo.geometry.pose_covariance import nees, step_error
    from dfvo.tracking.covariance import pnp_step_covariance

    g = torch.Generator().manual_seed(0)
    K = torch.tensor([[370.0, 0, 320], [0, 370.0, 96], [0, 0, 1]], dtype=torch.float64)
    T = torch.eye(4, dtype=torch.float64)  # the true T_prev_cur
    T[:3, :3] = so3_exp(torch.tensor([0.0, 0.5, 0.0], dtype=torch.float64))
    T[:3, 3] = torch.tensor([3.0, 0.0, 4.0], dtype=torch.float64)
    n, sigma, right, wrong = 300, 0.5, [], []
    for trial in range(100):
        z = 5 + 35 * torch.rand(n, generator=g, dtype=torch.float64)
        u = 640 * torch.rand(n, generator=g, dtype=torch.float64)
        v = 100 + 90 * torch.rand(n, generator=g, dtype=torch.float64)
        X_cur = torch.stack([(u - 320) / 370 * z, (v - 96) / 370 * z, z], -1)
        X_prev = X_cur @ T[:3, :3].T + T[:3, 3]
        pix_prev = (X_prev[:, :2] / X_prev[:, 2:]) @ K[:2, :2].T + K[:2, 2]
        pix_prev = pix_prev + sigma * torch.randn(n, 2, generator=g, dtype=torch.float64)
        r = solve_pnp_ransac(X_cur[None], pix_prev[None], torch.ones(1, n, dtype=torch.bool), K[None],
                             threshold_px=3.0, generators=[torch.Generator().manual_seed(trial)])
        T_pc = r.T_cur_prev[0].to(torch.float64)  # the current frame's points into the previous camera: T_prev_cur
        err = step_error(T_pc, T)
        right.append(nees(err, pnp_step_covariance(T_pc, X_cur, pix_prev, K, 3.0, 1e-12, backwards=True)))
        wrong.append(nees(err, pnp_step_covariance(T_pc, X_cur, pix_prev, K, 3.0, 1e-12)))
    assert 5.0 <= float(np.mean(right)) <= 7.2, np.mean(right)  # 6 +- 3 standard errors of a mean of 100
    assert float(np.mean(wrong)) > 9.0, np.mean(wrong)


def test_a_setting_that_leaves_pairs_without_depth_is_refused() -> None:
    from hydra import compose, initialize_config_dir

    def build(*overrides: str) -> InferConfig:
        with initialize_config_dir(config_dir=str(REPO / "dfvo" / "conf" / "infer"), version_base="1.3"):
            return typed(compose("infer", overrides=["data=synthetic", *overrides]))

    assert build("depth.every=2").depth.every == 2
    with pytest.raises(ValueError, match=r"depth.every=2 needs tracker.scale.depth_views=2"):
        build("depth.every=2", "tracker.scale.depth_views=1")
    with pytest.raises(ValueError, match=r"depth.every=2 needs .*tracker.mode=pnp"):
        build("depth.every=2", "tracker=pnp")
    with pytest.raises(ValueError, match=r"depth.every=0; expected a positive number"):
        build("depth.every=0")
    with pytest.raises(ValueError, match=r"depth.every=2 needs tracker.scale.method=simple"):
        build("depth.every=2", "tracker.scale.method=iterative")


def test_infer_with_depth_on_every_second_frame(tmp_path: Path) -> None:
    n = 8
    env = dict(os.environ, OMP_NUM_THREADS="1", HYDRA_FULL_ERROR="0")
    proc = subprocess.run([sys.executable, "infer.py", f"out_dir={tmp_path}", f"data.num_frames={n}",
                           "img_res.height=96", "img_res.width=320", "progress=false", "num_threads=1",
                           "flow=oracle", "depth=oracle", "depth.every=2"],
                          cwd=REPO, capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["sources"]["depth_every"] == 2 and summary["frames"] == n
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["rpe_m"] < 1e-3
    rows = (tmp_path / "synthetic_drive_s0.txt").read_text().splitlines()
    assert len(rows) == n and np.isfinite(np.array([r.split() for r in rows], dtype=float)).all()


def test_pairs_without_any_depth_still_get_a_pose() -> None:
    """Every 3rd frame with depth: pairs (1, 2) and (4, 5) have none in either frame. On the straight, (1, 2) keeps
    the E-tracker's direction with the length of the three-frame relative scale (triangulation against the previous
    pair: no depth needed; exact on exact flow). In the turn, (4, 5) sits at GRIC's border between E and PnP (the
    choice flips with the CPU's last bits: ATEN_CPU_CAPABILITY=default vs avx2): either the E-tracker with the
    temporal length, or PnP, which has no points, so constant motion flagged with the reason. Never a crash, never
    a missing pose."""
    w, ff, fb, d, d_next = _pairs("drive", 8, 3)
    assert not has_depth(d[1:2]) and not has_depth(d_next[1:2])
    res = VisualOdometry(_cfg()).run(ff, fb, d, w.intrinsics(), batch_size=4, depths_next=d_next)
    assert len(res) == 7 and all(bool(torch.isfinite(r.T_w_cur).all()) for r in res)
    straight = res[1].diagnostics
    assert straight.tracker == "E" and straight.scale_cnn is None and straight.scale_source == "temporal", straight
    assert _step_errors(w, res[:4]).max() < 1e-3
    turn = res[4].diagnostics
    if turn.tracker == "constant_motion":
        assert "PnP failed" in turn.fallback_reason, turn
    else:
        assert turn.tracker == "E" and turn.scale_cnn is None and turn.scale_source == "temporal", turn
