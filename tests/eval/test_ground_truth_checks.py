"""Ground-truth stretches of constant rotation rate (interpolated poses), and the per-pair RPE behind them."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from dfvo.eval import (
    constant_rate_segments,
    pair_rotations_deg,
    pairs_in_segments,
    read_kitti_poses,
    relative_pose_error,
    relative_pose_errors,
)


def _rot(axis: int, deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def _chain(steps: list[np.ndarray]) -> np.ndarray:
    """Poses T_w_c from relative steps (4,4), starting at the identity."""
    poses = [np.eye(4)]
    for step in steps:
        poses.append(poses[-1] @ step)
    return np.stack(poses)


def _step(R: np.ndarray, forward: float = 1.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[2, 3] = R, forward
    return T


def _drive(num_pairs: int, constant: tuple[int, int] | None, seed: int = 0) -> np.ndarray:
    """A drive whose rotation rate changes every frame (0.1 deg per axis, at least 0.02 deg apart on yaw), except
    the pairs of ``constant`` = (first, count), which repeat one rate exactly."""
    rng = np.random.default_rng(seed)
    rates = rng.normal(0.0, 0.1, size=(num_pairs, 3))
    rates[:, 1] += 0.05 * (np.arange(num_pairs) % 2)  # the yaw rate alternates: never steady outside
    if constant is not None:
        first, count = constant
        rates[first:first + count] = [0.007, -0.039, -0.041]
    steps = [_step(_rot(0, a) @ _rot(1, b) @ _rot(2, c)) for a, b, c in rates]
    return _chain(steps)


def test_pair_rotations_are_the_hand_derived_angles() -> None:
    """A yaw of 0.5 deg per pair, then a roll of 0.2 deg: rotation vectors (0, 0.5, 0) and (0, 0, 0.2)."""
    poses = _chain([_step(_rot(1, 0.5)), _step(_rot(1, 0.5)), _step(_rot(2, 0.2))])
    np.testing.assert_allclose(pair_rotations_deg(poses), [[0, 0.5, 0], [0, 0.5, 0], [0, 0, 0.2]], atol=1e-9)


def test_constant_rate_stretch_found_exactly() -> None:
    """12 pairs of one repeated rate inside a drive whose rate changes every frame: exactly those pairs."""
    poses = _drive(60, (20, 12))
    assert constant_rate_segments(poses) == [(20, 12)]
    assert constant_rate_segments(_drive(60, None)) == []
    assert constant_rate_segments(poses, min_pairs=13) == []  # shorter than asked for
    mask = pairs_in_segments([(20, 12)], 59)
    assert mask.sum() == 12 and mask[20] and mask[31] and not mask[19] and not mask[32]


def test_relative_pose_errors_per_pair() -> None:
    """One step's yaw off by 0.1 deg: that pair's rotation error is 0.1 deg, the others 0; the mean is RPE."""
    gt = _drive(20, None)
    steps = [np.linalg.inv(gt[k]) @ gt[k + 1] for k in range(20)]
    steps[7] = steps[7] @ _step(_rot(1, 0.1), forward=0.0)
    pred = _chain(steps)
    pairs, t_err, r_err = relative_pose_errors(gt, pred)
    assert list(pairs) == list(range(20))
    np.testing.assert_allclose(r_err, [0.1 if k == 7 else 0.0 for k in range(20)], atol=1e-5)  # acos near 1
    np.testing.assert_allclose(t_err, 0.0, atol=1e-9)
    assert relative_pose_error(gt, pred) == pytest.approx((t_err.mean(), r_err.mean()))


def test_kitti_ground_truth_stretches(kitti_poses_full: Path) -> None:
    """The real ground truth: KITTI 06 turns at one rate over its first 12 pairs (frames 0-12, 0.039 deg of yaw a
    frame to 2e-3 deg) while the rest of the sequence changes its rate by ~0.1 deg a frame; 07 has no such stretch."""
    g06 = read_kitti_poses(kitti_poses_full / "06.txt")
    assert constant_rate_segments(g06) == [(0, 12)]
    np.testing.assert_allclose(pair_rotations_deg(g06)[:12, 1], -0.039, atol=0.002)
    assert constant_rate_segments(read_kitti_poses(kitti_poses_full / "07.txt")) == []


def test_study_reports_a_run_inside_and_outside(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """studies/gt_constant_rate.py on a run whose rotation errs only inside the stretch: all of its rotation RPE
    inside, none outside."""
    from studies.gt_constant_rate import main

    gt = _drive(30, (0, 10))
    steps = [np.linalg.inv(gt[k]) @ gt[k + 1] for k in range(30)]
    for k in range(10):
        steps[k] = steps[k] @ _step(_rot(1, 0.05), forward=0.0)
    run = tmp_path / "run"
    run.mkdir()
    np.savetxt(run / "seq.txt", _chain(steps)[:, :3, :].reshape(-1, 12))
    np.savetxt(tmp_path / "gt.txt", gt[:, :3, :].reshape(-1, 12))
    (run / "summary.json").write_text(json.dumps({"pose_file": "seq.txt"}))
    main(["--gt", str(tmp_path / "gt.txt"), "--run", str(run)])
    out = json.loads(capsys.readouterr().out)
    assert out["ground_truth"][str(tmp_path / "gt.txt")]["segments"][0]["pairs"] == 10
    result = out["runs"][0]
    assert result["inside_segments"]["pairs"] == 10 and result["inside_segments"]["rpe_deg"] == pytest.approx(0.05)
    assert result["outside_segments"]["rpe_deg"] == pytest.approx(0.0, abs=1e-6)
