"""Ground truth checked before it is trusted (dfvo.data.pose_check): each kind of bad pose against hand-made paths."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from dfvo.data.pose_check import checked_poses


def _path(n: int = 12, step: float = 1.0) -> np.ndarray:
    """A camera driving forward ``step`` m a frame while turning 2 degrees a frame about its y axis."""
    T = np.tile(np.eye(4), (n, 1, 1))
    for k in range(n):
        a = np.radians(2.0 * k)
        T[k, :3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
        T[k, :3, 3] = [0.0, 0.0, step * k]
    return T


def test_good_path_rounded_like_a_text_file_is_kept_whole(caplog: pytest.LogCaptureFixture) -> None:
    poses = np.round(_path(), 6)  # KITTI files hold about 6 significant digits
    with caplog.at_level(logging.WARNING, "dfvo.data"):
        out = checked_poses(poses, "poses.txt")
    np.testing.assert_array_equal(out, poses)
    assert not caplog.records


def test_rows_without_ground_truth_stay_and_are_not_reported(caplog: pytest.LogCaptureFixture) -> None:
    poses = _path()
    poses[3] = np.nan
    with caplog.at_level(logging.WARNING, "dfvo.data"):
        out = checked_poses(poses, "poses.txt")
    assert np.isnan(out[3]).all() and np.isfinite(np.delete(out, 3, axis=0)).all()
    assert not caplog.records


@pytest.mark.parametrize("frame, damage, words", [
    (4, lambda T: T.__setitem__((0, 3), np.nan), "not finite"),
    (5, lambda T: T.__setitem__((1, 1), np.inf), "not finite"),
    (6, lambda T: T.__setitem__((slice(0, 3), slice(0, 3)), 1.01 * T[:3, :3]), "not a rotation"),
    (7, lambda T: T.__setitem__((slice(0, 3), 0), -T[:3, 0]), "not a rotation"),  # mirrored: det -1
    (8, lambda T: T.__setitem__((0, 3), 40.0), "jumps off the path and back"),  # a GNSS glitch
])
def test_a_bad_pose_is_left_out_and_named(caplog: pytest.LogCaptureFixture, frame: int, damage, words: str) -> None:
    poses = _path()
    damage(poses[frame])
    with caplog.at_level(logging.WARNING, "dfvo.data"):
        out = checked_poses(poses, "gt.txt")
    assert np.isnan(out[frame]).all()
    np.testing.assert_array_equal(np.delete(out, frame, axis=0), np.delete(_path(), frame, axis=0))
    assert len(caplog.records) == 1
    line = caplog.records[0].getMessage()
    assert line.startswith("gt.txt:") and words in line and f"frame(s) {frame} " in line


def test_a_lasting_jump_is_named_and_kept(caplog: pytest.LogCaptureFixture) -> None:
    poses = _path()
    poses[6:, 0, 3] += 30.0  # every position from frame 6 on moved 30 m sideways
    with caplog.at_level(logging.WARNING, "dfvo.data"):
        out = checked_poses(poses, "gt.txt")
    np.testing.assert_array_equal(out, poses)
    assert len(caplog.records) == 1 and "jumps at frame(s) 6 " in caplog.records[0].getMessage()


def test_a_standing_camera_is_not_a_jump(caplog: pytest.LogCaptureFixture) -> None:
    poses = _path(step=0.0)
    poses[7:, 2, 3] = 0.5 * np.arange(1, 6)  # standing, then moving off: no median step to compare with at first
    with caplog.at_level(logging.WARNING, "dfvo.data"):
        out = checked_poses(poses, "gt.txt")
    np.testing.assert_array_equal(out, poses)
    assert not caplog.records


def test_not_poses_is_one_line() -> None:
    with pytest.raises(ValueError, match=r"gt.txt: ground-truth poses must be \(N,4,4\), got \(3, 3, 4\)"):
        checked_poses(np.zeros((3, 3, 4)), "gt.txt")
