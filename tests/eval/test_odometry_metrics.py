"""KITTI odometry metrics, alignment, ATE/RPE against hand-derived values and independent direct loops."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dfvo.eval import (
    align_trajectory,
    evaluate_trajectory,
    kitti_segment_errors,
    read_kitti_poses,
    umeyama,
)


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def _curvy(n: int = 400, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    for i in range(1, n):
        step = np.eye(4)
        step[:3, :3] = _rot(np.array([0.05, 1.0, 0.02]), rng.normal(0, 0.02))
        step[:3, 3] = [rng.normal(0, 0.05), rng.normal(0, 0.01), 1.0 + rng.normal(0, 0.1)]
        poses[i] = poses[i - 1] @ step
    return poses


def _devkit_reference(gt: np.ndarray, pred: np.ndarray) -> tuple[float, float, int]:
    """Literal loop translation of the KITTI devkit's calcSequenceErrors (t_err ratio, r_err rad/m, count)."""
    dist = [0.0]
    for i in range(1, len(gt)):
        dist.append(dist[-1] + float(np.linalg.norm(gt[i, :3, 3] - gt[i - 1, :3, 3])))
    errs = []
    for first in range(0, len(gt), 10):
        for length in (100, 200, 300, 400, 500, 600, 700, 800):
            last = -1
            for i in range(first, len(dist)):
                if dist[i] > dist[first] + length:
                    last = i
                    break
            if last == -1:
                continue
            d_gt = np.linalg.inv(gt[first]) @ gt[last]
            d_pred = np.linalg.inv(pred[first]) @ pred[last]
            e = np.linalg.inv(d_pred) @ d_gt
            d = 0.5 * (e[0, 0] + e[1, 1] + e[2, 2] - 1.0)
            errs.append((np.linalg.norm(e[:3, 3]) / length, math.acos(max(min(d, 1.0), -1.0)) / length))
    arr = np.array(errs)
    return float(arr[:, 0].mean()), float(arr[:, 1].mean()), len(errs)


def _direct_ate_rpe(gt: np.ndarray, pred: np.ndarray) -> tuple[float, float, float]:
    sq, rpe_t, rpe_r = 0.0, 0.0, 0.0
    for i in range(len(gt)):
        sq += float(np.sum((gt[i, :3, 3] - pred[i, :3, 3]) ** 2))
    for i in range(len(gt) - 1):
        rg = np.linalg.solve(gt[i], gt[i + 1])
        rp = np.linalg.solve(pred[i], pred[i + 1])
        e = np.linalg.solve(rg, rp)
        rpe_t += float(np.linalg.norm(e[:3, 3]))
        rpe_r += math.degrees(math.acos(max(min(0.5 * (np.trace(e[:3, :3]) - 1), 1.0), -1.0)))
    return math.sqrt(sq / len(gt)), rpe_t / (len(gt) - 1), rpe_r / (len(gt) - 1)


def _similarity(poses: np.ndarray, s: float, r: np.ndarray, t: np.ndarray) -> np.ndarray:
    out = poses.copy()
    out[:, :3, :3] = r @ poses[:, :3, :3]
    out[:, :3, 3] = s * poses[:, :3, 3] @ r.T + t
    return out


@pytest.mark.parametrize("kind", ["offset", "scaled", "rotated"])
def test_7dof_recovers_hand_built_transforms(kind: str) -> None:
    gt = _curvy(300)
    r = _rot(np.array([0.3, -1.0, 0.5]), 0.7) if kind == "rotated" else np.eye(3)
    s = 0.37 if kind == "scaled" else 1.0
    t = np.array([5.0, -2.0, 11.0]) if kind == "offset" else np.zeros(3)
    pred = _similarity(gt, s, r, t)
    aligned, params = align_trajectory(gt, pred, "7dof")
    assert np.abs(aligned - gt).max() < 1e-9
    assert params["scale"] == pytest.approx(1.0 / s, rel=1e-9)
    res = evaluate_trajectory(gt, pred, "7dof")
    assert res["ate_m"] < 1e-9 and res["rpe_m"] < 1e-9 and res["t_err_pct"] < 1e-9


def test_umeyama_recovers_known_similarity() -> None:
    rng = np.random.default_rng(3)
    src = rng.normal(size=(50, 3))
    r, s, t = _rot(np.array([1.0, 2.0, 3.0]), 1.1), 2.5, np.array([1.0, 2.0, 3.0])
    s_est, r_est, t_est = umeyama(src, s * src @ r.T + t)
    assert s_est == pytest.approx(s, rel=1e-12)
    assert np.allclose(r_est, r, atol=1e-12) and np.allclose(t_est, t, atol=1e-12)
    assert umeyama(src, src @ r.T + t, with_scale=False)[0] == 1.0


def test_constant_drift_gives_hand_derived_t_err() -> None:
    # GT: straight line, exactly 1 m per frame for 1000 m. Prediction: 1.01 m per frame, no alignment.
    n = 1001
    gt = np.tile(np.eye(4), (n, 1, 1))
    gt[:, 2, 3] = np.arange(n, dtype=float)
    pred = gt.copy()
    pred[:, 2, 3] *= 1.01
    # dist[first+L] - dist[first] == L is not > L, so the devkit's end frame is first+L+1: the error is
    # 0.01*(L+1) m over a segment of nominal length L. Segments of length L start at 0,10,... <= 999-L.
    total, count = 0.0, 0
    for length in range(100, 900, 100):
        k = (999 - length) // 10 + 1
        total += k * 0.01 * (length + 1) / length
        count += k
    res = evaluate_trajectory(gt, pred, "none")
    assert res["scale_warning"] is None  # a 1 % scale error is inside the 10 % warning tolerance
    assert res["num_segments"] == count
    assert res["t_err_pct"] == pytest.approx(100 * total / count, rel=1e-12)
    assert res["r_err_deg_per_100m"] == pytest.approx(0.0, abs=1e-12)
    assert res["per_length"]["100"]["t_err_pct"] == pytest.approx(100 * 0.01 * 101 / 100, rel=1e-12)
    assert res["per_length"]["800"]["num_segments"] == (999 - 800) // 10 + 1
    # Mean over all segments differs from the mean of per-length means here (counts differ per length).
    per_len_mean = np.mean([v["t_err_pct"] for v in res["per_length"].values()])
    assert abs(per_len_mean - res["t_err_pct"]) > 1e-6


def test_warns_when_mono_scale_is_not_aligned() -> None:
    gt = _curvy(200)
    pred = gt.copy()
    pred[:, :3, 3] *= 0.3
    with pytest.warns(UserWarning, match="7-DoF scale"):
        res = evaluate_trajectory(gt, pred, "6dof")
    assert res["scale_warning"] is not None and res["sim3_scale"] == pytest.approx(1 / 0.3)
    assert evaluate_trajectory(gt, pred, "7dof")["scale_warning"] is None
    assert evaluate_trajectory(gt, pred, "scale")["align_scale"] == pytest.approx(1 / 0.3)


def test_short_trajectory_has_null_kitti_metrics() -> None:
    gt = _curvy(50)
    res = evaluate_trajectory(gt, gt, "7dof")
    assert res["t_err_pct"] is None and res["r_err_deg_per_100m"] is None
    assert res["ate_m"] < 1e-9 and res["num_frames"] == 50


def test_bad_inputs_raise() -> None:
    gt = _curvy(20)
    with pytest.raises(ValueError, match="align"):
        evaluate_trajectory(gt, gt, "sim3")
    with pytest.raises(ValueError, match="19"):
        evaluate_trajectory(gt, gt[:-1], "7dof")


def _perturb(gt: np.ndarray, sigma: float, seed: int = 0) -> np.ndarray:
    """Accumulate per-frame noise on the relative motions (drift grows like real VO)."""
    rng = np.random.default_rng(seed)
    rel = np.linalg.inv(gt[:-1]) @ gt[1:]
    noise_r = rng.normal(size=(len(rel), 3))
    noise_t = rng.normal(size=(len(rel), 3))
    out = [gt[0]]
    for i, m in enumerate(rel):
        e = np.eye(4)
        e[:3, :3] = _rot(noise_r[i], np.linalg.norm(noise_r[i]) * sigma * 1e-3)
        e[:3, 3] = noise_t[i] * sigma * 1e-2
        out.append(out[-1] @ m @ e)
    return np.stack(out)


def test_full_kitti_gt_properties(kitti_poses_full) -> None:
    gt = read_kitti_poses(kitti_poses_full / "07.txt")
    zero = evaluate_trajectory(gt, gt, "none")
    assert zero["t_err_pct"] < 1e-9 and zero["ate_m"] < 1e-9 and zero["rpe_m"] < 1e-9
    assert zero["r_err_deg_per_100m"] < 1e-4  # acos near 1 loses precision (same formula as the devkit)
    t_errs, r_errs, ates = [], [], []
    for sigma in (0.5, 1.0, 2.0, 4.0):
        res = evaluate_trajectory(gt, _perturb(gt, sigma), "6dof")
        t_errs.append(res["t_err_pct"])
        r_errs.append(res["r_err_deg_per_100m"])
        ates.append(res["ate_m"])
    assert np.all(np.diff(t_errs) > 0) and np.all(np.diff(r_errs) > 0) and np.all(np.diff(ates) > 0)


def test_matches_devkit_loop_and_direct_ate_rpe(kitti_poses_full) -> None:
    gt = read_kitti_poses(kitti_poses_full / "04.txt")
    pred = _perturb(gt, 2.0, seed=5)
    t_ref, r_ref, n_ref = _devkit_reference(gt, pred)
    res = evaluate_trajectory(gt, pred, "none")
    assert res["num_segments"] == n_ref
    assert res["t_err_pct"] == pytest.approx(t_ref * 100, rel=1e-9)
    assert res["r_err_deg_per_100m"] == pytest.approx(math.degrees(r_ref) * 100, rel=1e-9)
    ate, rpe_t, rpe_r = _direct_ate_rpe(gt, pred)
    assert res["ate_m"] == pytest.approx(ate, abs=1e-6)
    assert res["rpe_m"] == pytest.approx(rpe_t, abs=1e-6)
    assert res["rpe_deg"] == pytest.approx(rpe_r, abs=1e-6)
    seg = kitti_segment_errors(gt, pred)
    assert np.all(seg["last"] > seg["first"])


@pytest.mark.parametrize("align", ["6dof", "7dof", "scale"])
def test_alignment_invariance_full_gt(kitti_poses_full, align: str) -> None:
    gt = read_kitti_poses(kitti_poses_full / "05.txt")
    pred = _perturb(gt, 1.0, seed=2)
    base = evaluate_trajectory(gt, pred, align)
    s = 1.0 if align == "6dof" else 0.3
    r = np.eye(3) if align == "scale" else _rot(np.array([0.2, 1.0, -0.4]), 2.0)
    t = np.zeros(3) if align == "scale" else np.array([30.0, -4.0, 100.0])
    moved = evaluate_trajectory(gt, _similarity(pred, s, r, t), align)
    for key in ("t_err_pct", "r_err_deg_per_100m", "ate_m", "rpe_m", "rpe_deg"):
        assert moved[key] == pytest.approx(base[key], rel=1e-6, abs=1e-9)


@pytest.mark.parametrize("align", ["scale", "none", "7dof"])
def test_trajectories_are_compared_relative_to_their_first_frame(align: str) -> None:
    """As the DF-VO toolkit: both trajectories are re-based to their first frame before alignment, so a
    prediction that starts elsewhere (here: a rigidly moved copy, scaled by 2.5 for align=scale/7dof) scores
    exactly zero. Without the re-base, scale-only alignment about the origin cannot undo the offset."""
    gt = _curvy(300, seed=3)
    offset = np.eye(4)
    offset[:3, :3] = _rot(np.array([0.3, 1.0, -0.2]), 0.7)
    offset[:3, 3] = [12.0, -3.0, 40.0]
    scaled = gt.copy()
    if align != "none":
        scaled[:, :3, 3] *= 2.5
    start = np.eye(4)
    start[:3, 3] = [5.0, 0.0, -2.0]
    gt_moved = start @ gt
    res = evaluate_trajectory(gt_moved, offset @ scaled, align=align)
    assert res["ate_m"] < 1e-9 and res["rpe_m"] < 1e-9
    # r_err goes through the devkit's acos(0.5 (trace - 1)), whose floor near 0 is ~sqrt(eps) rad
    assert res["t_err_pct"] < 1e-9 and res["r_err_deg_per_100m"] < 1e-5


def test_aligned_prediction_leaves_frames_without_ground_truth_out() -> None:
    """Issue 42: the trajectory plots of a run whose ground truth has a NaN frame (a bad oxts packet) are made, the
    alignment from the other frames, the frame itself NaN in the re-based ground truth."""
    from dfvo.eval.odometry_metrics import aligned_prediction

    gt = np.tile(np.eye(4), (5, 1, 1))
    gt[:, 2, 3] = np.arange(5.0)
    pred = gt.copy()
    pred[:, 2, 3] *= 0.5  # half the scale
    gt[0] = np.nan  # the first frame has no ground truth: re-based to frame 1
    gt_b, pred_b, aligned, params = aligned_prediction(gt, pred, align="7dof")
    assert np.isnan(gt_b[0]).all() and np.isfinite(gt_b[1:]).all()
    np.testing.assert_allclose(gt_b[1:, 2, 3], [0, 1, 2, 3], atol=1e-12)
    assert params["scale"] == pytest.approx(2.0)
    np.testing.assert_allclose(aligned[1:, 2, 3], gt_b[1:, 2, 3], atol=1e-9)
