"""Trajectory file I/O (KITTI, TUM): round trips and line-numbered errors for malformed files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dfvo.eval import read_kitti_poses, read_tum_poses, write_kitti_poses, write_tum_poses
from dfvo.eval.trajectory_io import quaternion_to_rotation, rotation_to_quaternion


def _random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = quaternion_to_rotation(q)
    poses[:, :3, 3] = rng.normal(0, 100, size=(n, 3))
    return poses


def test_kitti_round_trip(tmp_path: Path) -> None:
    poses = _random_poses(30)
    write_kitti_poses(tmp_path / "a.txt", poses)
    lines = (tmp_path / "a.txt").read_text().splitlines()
    assert len(lines) == 30 and all(len(line.split()) == 12 for line in lines)
    assert np.allclose(read_kitti_poses(tmp_path / "a.txt"), poses, atol=1e-6)


def test_kitti_reads_hand_written_line(tmp_path: Path) -> None:
    (tmp_path / "p.txt").write_text("1 0 0 1.5 0 1 0 -2 0 0 1 3\n\n")
    poses = read_kitti_poses(tmp_path / "p.txt")
    assert poses.shape == (1, 4, 4)
    assert np.array_equal(poses[0, :3, 3], [1.5, -2, 3]) and np.array_equal(poses[0, 3], [0, 0, 0, 1])


def test_quaternion_round_trip_including_180_degrees() -> None:
    poses = _random_poses(200, seed=1)
    rots = np.concatenate([poses[:, :3, :3], np.diag([1.0, -1, -1])[None], np.diag([-1.0, 1, -1])[None],
                           np.diag([-1.0, -1, 1])[None], np.eye(3)[None]])
    q = rotation_to_quaternion(rots)
    assert np.allclose(np.linalg.norm(q, axis=1), 1.0)
    assert np.allclose(quaternion_to_rotation(q), rots, atol=1e-12)
    # 90 deg about z: (qx,qy,qz,qw) = (0,0,sin45,cos45) by hand.
    rz = np.array([[[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]])
    assert np.allclose(rotation_to_quaternion(rz), [[0, 0, np.sqrt(0.5), np.sqrt(0.5)]])


def test_tum_round_trip(tmp_path: Path) -> None:
    poses = _random_poses(25, seed=2)
    stamps = np.linspace(100.0, 102.4, 25)
    write_tum_poses(tmp_path / "t.txt", poses, stamps)
    t, back = read_tum_poses(tmp_path / "t.txt")
    assert np.allclose(t, stamps) and np.allclose(back, poses, atol=1e-6)


@pytest.mark.parametrize(
    ("content", "reader", "pattern"),
    [
        ("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1\n", read_kitti_poses, r":2: expected 12 numbers, got 11"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 x 0 1 0 0 0 0 1 0\n", read_kitti_poses, r":2: non-numeric.*'1 0 0 x"),
        ("", read_kitti_poses, "empty"),
        ("0 1 2 3 0 0 0 1\n0 1 2 3 0 0 1\n", lambda p: read_tum_poses(p), r":2: expected 8 numbers, got 7"),
        ("0 1 2 nan 0 0 0 1\n", lambda p: read_tum_poses(p), r":1: non-finite"),
    ],
)
def test_malformed_files_name_line_and_content(tmp_path: Path, content: str, reader, pattern: str) -> None:
    path = tmp_path / "bad.txt"
    path.write_text(content)
    with pytest.raises(ValueError, match=pattern) as info:
        reader(path)
    assert "bad.txt" in str(info.value)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="nope.txt"):
        read_kitti_poses(tmp_path / "nope.txt")
