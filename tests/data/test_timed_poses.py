"""Frames to timestamped ground truth: the association (match_timestamps of dfvo.io.association behind
associate_frames), the ns -> s conversion EuRoC needs, the trajectory readers' errors as dataset errors, and the
unmatched policies."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dfvo.data.image_io import DatasetError, DatasetNotFoundError
from dfvo.data.timed_poses import associate_frames, attach_ground_truth, read_ground_truth
from dfvo.io.trajectory import read_euroc, read_tum


def brute_force(query: np.ndarray, ref: np.ndarray, tol: float) -> np.ndarray:
    out = []
    for q in query:
        d = np.abs(ref - q)
        out.append(int(np.argmin(d)) if d.min() <= tol else -1)
    return np.array(out)


def test_association_matches_brute_force_when_each_frame_has_its_own_pose() -> None:
    rng = np.random.default_rng(0)
    ref = rng.permutation(np.arange(300) * 0.033 + rng.uniform(-0.001, 0.001, 300))  # unsorted, 30 Hz
    query = np.concatenate([np.sort(ref)[::3] + rng.uniform(-0.004, 0.004, 100), [-5.0, 20.0]])
    for tol in (0.001, 0.005, 0.01):
        np.testing.assert_array_equal(associate_frames(query, ref, tol), brute_force(query, ref, tol))
    assert list(associate_frames(np.array([1.0]), np.array([]), 1.0)) == [-1]
    assert list(associate_frames(np.array([0.0, 3.0]), np.array([2.5]), 0.5)) == [-1, 0]
    # each pose serves one frame: of two frames near one pose the closer keeps it
    assert list(associate_frames(np.array([0.99, 1.02]), np.array([1.0]), 0.05)) == [0, -1]


def test_euroc_nanoseconds_become_the_same_seconds_on_both_sides(tmp_path: Path) -> None:
    """EuRoC stamps are int64 ns near 1.4e18: the frame list's ``ns * 1e-9`` and read_euroc's parse of the same digits
    give identical seconds, so a pose stamped with the frame's own nanosecond matches at zero tolerance, and one
    stamped 1 ms later matches within 1 ms but not below (float64 seconds resolve ~0.25 us here)."""
    t0 = 1403636579763555584
    frames_ns = np.array([t0, t0 + 50_000_000, t0 + 100_000_000], dtype=np.int64)
    gt_ns = [t0 + 100_000_000, t0 + 1_000_000, t0 + 50_000_000 + 1_000_000]  # unsorted: read_euroc sorts by time
    rows = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []"]
    rows += [f"{t},{k},0,0,1,0,0,0" for k, t in enumerate(gt_ns)]
    (tmp_path / "data.csv").write_text("\n".join(rows) + "\n")
    gt_s, poses = read_ground_truth(tmp_path / "data.csv", read_euroc, "EuRoC ground truth")
    assert list(poses[:, 0, 3]) == [1.0, 2.0, 0.0]  # sorted by time
    frames_s = frames_ns * 1e-9
    assert frames_s[2] == gt_s[2]  # the same nanosecond gives the same float64 seconds
    assert list(associate_frames(frames_s, gt_s, 0.0)) == [-1, -1, 2]
    assert list(associate_frames(frames_s, gt_s, 0.001 + 1e-6)) == [0, 1, 2]
    assert list(associate_frames(frames_s, gt_s, 0.001 - 1e-6)) == [-1, -1, 2]


def test_ground_truth_errors_name_file_and_line(tmp_path: Path) -> None:
    path = tmp_path / "groundtruth.txt"
    path.write_text("# ground truth\n1305031102.2 1 2 3 0 0 0 1\n1305031102.3 1 2 3 0 0 zero 1\n")
    with pytest.raises(DatasetError, match=r"^TUM ground truth: .*groundtruth.txt:3: non-numeric value"):
        read_ground_truth(path, read_tum, "TUM ground truth")
    path.write_text("1305031102.2 1 2 3 0 0 0 0\n")
    with pytest.raises(DatasetError, match=r"groundtruth.txt:1: zero quaternion"):
        read_ground_truth(path, read_tum, "TUM ground truth")
    with pytest.raises(DatasetNotFoundError, match="missing.txt"):
        read_ground_truth(tmp_path / "missing.txt", read_tum, "TUM ground truth")


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
