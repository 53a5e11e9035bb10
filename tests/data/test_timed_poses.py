"""Nearest-timestamp association and quaternion poses (the pieces the EuRoC and TUM readers share)."""

from __future__ import annotations

import numpy as np
import pytest

from dfvo.data.image_io import DatasetError
from dfvo.data.timed_poses import associate_nearest, attach_ground_truth, poses_from_quaternions

Rotation = pytest.importorskip("scipy.spatial.transform", reason="SciPy (test-only reference) not installed").Rotation


def brute_force(query: np.ndarray, ref: np.ndarray, tol: float) -> np.ndarray:
    out = []
    for q in query:
        d = np.abs(ref - q)
        out.append(int(np.argmin(d)) if d.min() <= tol else -1)
    return np.array(out)


def test_association_matches_brute_force() -> None:
    rng = np.random.default_rng(0)
    ref = rng.uniform(0, 10, 300)  # unsorted
    query = np.concatenate([rng.uniform(-1, 11, 200), [ref[5], -5.0, 20.0]])
    for tol in (0.001, 0.01, 0.1):
        np.testing.assert_array_equal(associate_nearest(query, ref, tol), brute_force(query, ref, tol))
    assert list(associate_nearest(np.array([1.0]), np.array([]), 1.0)) == [-1]
    assert list(associate_nearest(np.array([0.0, 3.0]), np.array([2.5]), 0.5)) == [-1, 0]


def test_association_exact_in_nanoseconds() -> None:
    # float64 seconds cannot tell 1403636579.763555584 from ...585; int64 nanoseconds can
    ref = np.array([1403636579763555584, 1403636579763555585], dtype=np.int64)
    query = np.array([1403636579763555585, 1403636579763555584, 1403636579763555586 + 10], dtype=np.int64)
    assert list(associate_nearest(query, ref, 0)) == [1, 0, -1]
    assert list(associate_nearest(query, ref, 10)) == [1, 0, -1]  # 11 ns away
    assert list(associate_nearest(query, ref, 11)) == [1, 0, 1]


def test_quaternion_poses_match_scipy() -> None:
    rng = np.random.default_rng(1)
    rot = Rotation.random(20, random_state=2)
    t = rng.normal(size=(20, 3))
    q = rot.as_quat() * rng.uniform(0.5, 2.0, (20, 1))  # (x, y, z, w), not normalised
    T = poses_from_quaternions(t, q)
    np.testing.assert_allclose(T[:, :3, :3], rot.as_matrix(), atol=1e-12)
    np.testing.assert_array_equal(T[:, :3, 3], t)
    np.testing.assert_array_equal(T[:, 3], np.tile([0, 0, 0, 1.0], (20, 1)))
    with pytest.raises(ValueError, match="zero quaternion in row 1"):
        poses_from_quaternions(t[:2], np.array([[0, 0, 0, 1.0], [0, 0, 0, 0]]))


def test_policies() -> None:
    gt = np.tile(np.eye(4), (5, 1, 1))
    gt[:, 0, 3] = np.arange(5)
    times = np.arange(6, dtype=float)
    match = np.array([-1, 0, 1, 2, 3, -1])
    keep, poses, report = attach_ground_truth(times, match, gt, "trim", "seq", 0.01)
    assert list(keep) == [1, 2, 3, 4] and list(poses[:, 0, 3]) == [0, 1, 2, 3]
    assert report == ("seq: 4 of 6 frames matched to ground truth within 0.01 s; dropped 1 frames before and 1 after "
                      "the ground truth (unmatched=trim), kept frames 1..4")
    keep, poses, _ = attach_ground_truth(times, match, gt, "nan", "seq", 0.01)
    assert len(keep) == 6 and np.isnan(poses[[0, 5]]).all() and poses[1, 0, 3] == 0
    with pytest.raises(DatasetError, match=r"2 frames inside the ground-truth span .* frame 2, t = 2.000000 s"):
        attach_ground_truth(times, np.array([0, 1, -1, -1, 3, 4]), gt, "trim", "seq", 0.01)
    with pytest.raises(ValueError, match=r"unmatched='drop'; expected one of \('trim', 'nan', 'none'\)"):
        attach_ground_truth(times, match, gt, "drop", "seq", 0.01)
