"""Pairing a prediction with its ground truth: nearest timestamps (against evo's matcher), frame indices, line order
and prefixes, with the counts and the one-line errors."""

from __future__ import annotations

import numpy as np
import pytest

from dfvo.eval import evaluate_trajectory
from dfvo.io.association import associate_trajectories, match_timestamps
from dfvo.io.trajectory import Trajectory


def _poses(n: int) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = np.arange(n, dtype=float)
    return poses


def test_match_timestamps_by_hand() -> None:
    a = np.array([0.0, 1.02, 1.98, 3.5, 5.0])
    b = np.array([0.0, 1.0, 2.0, 3.0, 4.0, 5.0])
    ia, ib = match_timestamps(a, b, 0.05)
    assert ia.tolist() == [0, 1, 2, 4] and ib.tolist() == [0, 1, 2, 5]  # 3.5 is 0.5 s from any stamp
    # three stamps nearest to the same partner (1.5 is a tie, which goes to the earlier): the closest keeps it
    ia, ib = match_timestamps(np.array([0.96, 1.01, 1.5]), b, 0.5)
    assert ia.tolist() == [1] and ib.tolist() == [1]
    ia, ib = match_timestamps(np.array([1.5, 2.2]), b, 0.5)
    assert ia.tolist() == [0, 1] and ib.tolist() == [1, 2]
    ia, ib = match_timestamps(a, b[::-1].copy(), 0.05)  # unsorted partner stamps give indices into the input
    assert (b[::-1][ib] == b[[0, 1, 2, 5]]).all()


def test_match_timestamps_agrees_with_evo() -> None:
    sync = pytest.importorskip("evo.core.sync", reason="evo (test-only dependency) is not installed")
    rng = np.random.default_rng(0)
    ref = np.cumsum(rng.uniform(0.09, 0.11, size=500))
    keep = np.sort(rng.choice(499, size=420, replace=False))  # missing poses
    est = ref[keep] + rng.uniform(-0.02, 0.02, size=len(keep))  # jitter
    est[::37] = 0.5 * (ref[keep[::37]] + ref[keep[::37] + 1])  # half-way stamps: no partner within 0.03 s
    ia, ib = match_timestamps(est, ref, 0.03)
    ea, eb = sync.matching_time_indices(est, ref, max_diff=0.03)
    assert len(set(eb)) == len(eb)  # evo keeps duplicate partners; this case has none, so the pairs must agree
    assert ia.tolist() == ea and ib.tolist() == eb
    assert len(ia) == 420 - len(keep[::37])


def test_associate_timestamps_with_jitter_and_missing_poses() -> None:
    n = 300
    t = np.arange(n) * 0.1
    gt = Trajectory(_poses(n), timestamps=t, source="gt.txt")
    keep = np.setdiff1d(np.arange(n), [0, 5, 6, 7, 150, 299])
    jitter = np.random.default_rng(1).uniform(-0.02, 0.02, size=len(keep))
    pred = Trajectory(_poses(n)[keep], timestamps=t[keep] + 1000.0 + jitter, source="pred.txt")
    msg = r"pred.txt \(294 poses\) vs gt.txt \(300 poses\): 0 poses matched.*time_offset"
    with pytest.raises(ValueError, match=msg):
        associate_trajectories(gt, pred, max_time_diff=0.03)
    assoc = associate_trajectories(gt, pred, max_time_diff=0.03, time_offset=-1000.0)
    assert assoc.method == "timestamp" and assoc.num_matched == len(keep) and assoc.valid.all()
    assert np.array_equal(assoc.gt[:, 0, 3], keep) and np.array_equal(assoc.pred, assoc.gt)
    assert assoc.max_abs_dt <= 0.02 + 1e-9
    assert assoc.describe().startswith("294 of 294 predicted poses matched by timestamp within 0.03 s (300 ground")


def test_associate_by_frame_index_and_order() -> None:
    gt = Trajectory(_poses(50), source="gt.txt")
    ids = np.array([3, 4, 5, 20, 49, 60])
    pred = Trajectory(_poses(61)[ids], frame_ids=ids, source="pred.txt")
    assoc = associate_trajectories(gt, pred)
    assert assoc.method == "frame_index" and assoc.num_matched == 5  # frame 60 has no ground truth
    assert np.flatnonzero(assoc.valid).tolist() == [3, 4, 5, 20, 49]
    assert np.array_equal(assoc.pred[assoc.valid], gt.poses[[3, 4, 5, 20, 49]])
    assert "5 of 6 predicted poses matched by frame index (50 ground-truth frames)" == assoc.describe()

    same = associate_trajectories(gt, Trajectory(_poses(50)))
    assert same.method == "order" and same.num_matched == 50
    short = Trajectory(_poses(20), source="short.txt")
    with pytest.raises(ValueError, match=r"short.txt \(20 poses\) vs gt.txt \(50 poses\).*allow_prefix=true"):
        associate_trajectories(gt, short)
    prefix = associate_trajectories(gt, short, allow_prefix=True)
    assert prefix.method == "prefix" and prefix.valid[:20].all() and not prefix.valid[20:].any()
    assert prefix.describe() == "prefix: the first 20 of 50 ground-truth poses (allow_prefix=true)"
    with pytest.raises(ValueError, match="more poses than the ground truth"):
        associate_trajectories(short, gt)


def test_sparse_evaluation_uses_only_predicted_frames() -> None:
    """Frames without a prediction hold garbage that must not leak into any metric."""
    rng = np.random.default_rng(2)
    gt = np.tile(np.eye(4), (400, 1, 1))
    gt[:, 2, 3] = np.arange(400) * 1.0
    pred = gt.copy()
    pred[:, 0, 3] += np.cumsum(rng.normal(0, 0.01, 400))
    valid = np.ones(400, bool)
    valid[[1, 2, 57, 58, 200]] = False
    garbage = pred.copy()
    garbage[~valid, :3, 3] = 1e6
    a = evaluate_trajectory(gt, pred, "7dof", valid=valid)
    b = evaluate_trajectory(gt, garbage, "7dof", valid=valid)
    for key in ("t_err_pct", "r_err_deg_per_100m", "ate_m", "rpe_m", "rpe_deg", "num_segments"):
        assert a[key] == b[key], key
    assert a["num_frames"] == 395 and a["num_gt_frames"] == 400
    full = evaluate_trajectory(gt, pred, "7dof")
    assert a["num_segments"] < full["num_segments"]  # segments starting or ending on a missing frame are skipped
    gt_long = gt.copy()
    gt_long[:, 2, 3] *= 1.001  # a segment of L m now ends L frames (not L+1) later: on an even frame
    every_other = np.zeros(400, bool)
    every_other[::2] = True
    res = evaluate_trajectory(gt_long, pred, "7dof", valid=every_other)
    assert res["rpe_m"] is None and res["rpe_deg"] is None and res["t_err_pct"] is not None


def test_frames_without_ground_truth_are_left_out_and_counted() -> None:
    """A ground truth with NaN poses (frames the ground truth does not cover, as dfvo.data's unmatched='nan' policy
    writes them) is evaluated on the frames it covers; the count is reported; a NaN prediction is an error."""
    rng = np.random.default_rng(4)
    gt = np.tile(np.eye(4), (300, 1, 1))
    gt[:, 2, 3] = np.arange(300) * 1.0
    pred = gt.copy()
    pred[:, 1, 3] += np.cumsum(rng.normal(0, 0.02, 300))
    holes = np.zeros(300, bool)
    holes[[0, 1, 150, 151, 152]] = True
    with_nan = gt.copy()
    with_nan[holes] = np.nan
    res = evaluate_trajectory(with_nan, pred, "7dof")
    ref = evaluate_trajectory(gt[~holes], pred[~holes], "7dof")
    assert res["gt_missing"] == 5 and res["num_frames"] == 295 and ref["gt_missing"] == 0
    for key in ("t_err_pct", "r_err_deg_per_100m", "ate_m", "rpe_m", "rpe_deg", "num_segments"):
        assert res[key] == ref[key], key
    bad = pred.copy()
    bad[7] = np.nan
    with pytest.raises(ValueError, match="pred pose 7 is not finite"):
        evaluate_trajectory(gt, bad, "7dof")
