"""Trajectory file I/O (KITTI 12/13, TUM, EuRoC): round trips, evo's readers as an independent check, format
detection, the streaming writer, and line-numbered errors for malformed files."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from dfvo.io.trajectory import (
    Trajectory,
    TrajectoryWriter,
    detect_format,
    quaternion_to_rotation,
    read_euroc,
    read_kitti,
    read_kitti_poses,
    read_trajectory,
    read_tum_poses,
    rotation_to_quaternion,
    write_euroc_poses,
    write_kitti_poses,
    write_trajectory,
    write_tum_poses,
)


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


# ------------------------------------------------------------------------------------------------ KITTI 13, EuRoC


def test_kitti_13_numbers_keep_sparse_frame_indices(tmp_path: Path) -> None:
    poses = _random_poses(5, seed=3)
    ids = np.array([0, 1, 7, 20, 21])
    write_kitti_poses(tmp_path / "s.txt", poses, frame_ids=ids)
    lines = (tmp_path / "s.txt").read_text().splitlines()
    assert [line.split()[0] for line in lines] == ["0", "1", "7", "20", "21"] and len(lines[2].split()) == 13
    traj = read_kitti(tmp_path / "s.txt")
    assert np.array_equal(traj.frame_ids, ids) and traj.timestamps is None
    assert np.allclose(traj.poses, poses, atol=1e-6)
    # lines out of order are sorted by their frame index
    (tmp_path / "r.txt").write_text("\n".join([lines[3], lines[0], lines[2]]) + "\n")
    back = read_kitti(tmp_path / "r.txt")
    assert np.array_equal(back.frame_ids, [0, 7, 20]) and np.allclose(back.poses, poses[[0, 2, 3]], atol=1e-6)
    assert np.allclose(read_kitti_poses(tmp_path / "r.txt"), poses[[0, 2, 3]], atol=1e-6)


def test_euroc_round_trip_and_header(tmp_path: Path) -> None:
    poses = _random_poses(12, seed=4)
    stamps = 1403636579.763555584 + np.arange(12) * 0.005  # EuRoC-sized epoch seconds, 200 Hz
    write_euroc_poses(tmp_path / "data.csv", poses, stamps)
    text = (tmp_path / "data.csv").read_text().splitlines()
    assert text[0].startswith("#timestamp") and text[1].split(",")[0] == str(round(stamps[0] * 1e9))
    traj = read_euroc(tmp_path / "data.csv")
    assert np.allclose(traj.timestamps, stamps, atol=1e-6) and np.allclose(traj.poses, poses, atol=1e-6)


def test_euroc_real_layout_columns(tmp_path: Path) -> None:
    """The 17 columns of state_groundtruth_estimate0/data.csv (quaternion w first, then v, b_w, b_a)."""
    mav0 = tmp_path / "MH_01" / "mav0" / "state_groundtruth_estimate0"
    mav0.mkdir(parents=True)
    c, s = np.cos(np.pi / 8), np.sin(np.pi / 8)  # 45 deg about z: (w, x, y, z) = (c, 0, 0, s)
    header = ("#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
              "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], "
              "b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], "
              "b_a_RS_S_z [m s^-2]")
    rows = [f"1403636579758555392,4.688,-1.786,0.783,{c},0,0,{s},-0.027,0.033,-0.8,-0.003,0.02,0.07,-0.02,0.1,0.08",
            "1403636579763555584,4.689,-1.787,0.782,1,0,0,0,-0.027,0.033,-0.8,-0.003,0.02,0.07,-0.02,0.1,0.08"]
    (mav0 / "data.csv").write_text("\n".join([header, *rows]) + "\n")
    assert detect_format(mav0 / "data.csv") == "euroc"
    traj = read_trajectory(tmp_path / "MH_01")  # a dataset folder resolves to its ground-truth file
    assert traj.timestamps[1] - traj.timestamps[0] == pytest.approx(0.005, abs=1e-6)
    assert np.allclose(traj.poses[0, :3, 3], [4.688, -1.786, 0.783])
    r45 = np.array([[np.sqrt(0.5), -np.sqrt(0.5), 0], [np.sqrt(0.5), np.sqrt(0.5), 0], [0, 0, 1]])
    assert np.allclose(traj.poses[0, :3, :3], r45, atol=1e-12) and np.allclose(traj.poses[1, :3, :3], np.eye(3))


def test_format_detection(tmp_path: Path) -> None:
    poses = _random_poses(3, seed=5)
    write_kitti_poses(tmp_path / "a.txt", poses)
    write_kitti_poses(tmp_path / "b.txt", poses, frame_ids=[3, 4, 5])
    write_tum_poses(tmp_path / "c.txt", poses, [1.0, 2.0, 3.0])
    write_euroc_poses(tmp_path / "d.csv", poses, [1.0, 2.0, 3.0])
    (tmp_path / "e.txt").write_text("# comment first\n1 2 3 4 5 6 7 8\n")
    assert [detect_format(tmp_path / n) for n in ("a.txt", "b.txt", "c.txt", "d.csv", "e.txt")] == [
        "kitti", "kitti", "tum", "euroc", "tum"]
    for name in ("a.txt", "b.txt", "c.txt", "d.csv"):
        assert np.allclose(read_trajectory(tmp_path / name).poses, poses, atol=1e-6), name
    (tmp_path / "f.txt").write_text("1 2 3 4 5\n")
    with pytest.raises(ValueError, match=r"f.txt: cannot detect .* 5 numbers; expected 12 or 13 \(kitti\), 8"):
        read_trajectory(tmp_path / "f.txt")
    with pytest.raises(ValueError, match="format='kitty'"):
        read_trajectory(tmp_path / "a.txt", format="kitty")
    with pytest.raises(FileNotFoundError, match="folder without a trajectory file"):
        read_trajectory(tmp_path)


def test_write_trajectory_formats(tmp_path: Path) -> None:
    traj = Trajectory(_random_poses(4, seed=6), timestamps=[0.5, 0.6, 0.7, 0.8], frame_ids=[2, 3, 4, 5])
    for fmt in ("kitti", "tum", "euroc"):
        back = read_trajectory(write_trajectory(tmp_path / f"x.{fmt}", traj, fmt))
        assert np.allclose(back.poses, traj.poses, atol=1e-6)
    assert np.array_equal(read_kitti(tmp_path / "x.kitti").frame_ids, [2, 3, 4, 5])
    assert np.allclose(read_trajectory(tmp_path / "x.tum").timestamps, traj.timestamps)
    with pytest.raises(ValueError, match="tum format needs one timestamp per pose"):
        write_trajectory(tmp_path / "y.txt", Trajectory(traj.poses), "tum")
    with pytest.raises(ValueError, match=r"timestamps must have shape \(4,\)"):
        Trajectory(traj.poses, timestamps=[1.0, 2.0])


def test_streaming_writer_flushes_each_line(tmp_path: Path) -> None:
    poses = _random_poses(3, seed=7)
    w = TrajectoryWriter(tmp_path / "k" / "06.txt", "kitti")
    w.write(poses[0])
    assert len((tmp_path / "k" / "06.txt").read_text().splitlines()) == 1  # visible before close
    w.write(poses[1])
    w.close()
    assert np.allclose(read_kitti_poses(tmp_path / "k" / "06.txt"), poses[:2], atol=1e-6)
    with TrajectoryWriter(tmp_path / "t.txt", "tum") as t:
        for i, T in enumerate(poses):
            t.write(T, timestamp=10.0 + i * 0.1)
        assert t.count == 3
    stamps, back = read_tum_poses(tmp_path / "t.txt")
    assert np.allclose(stamps, [10.0, 10.1, 10.2]) and np.allclose(back, poses, atol=1e-6)
    with TrajectoryWriter(tmp_path / "u.txt", "tum") as t, pytest.raises(ValueError, match="needs a timestamp"):
        t.write(poses[0])
    with pytest.raises(ValueError, match="pose_format='euroc'"):
        TrajectoryWriter(tmp_path / "v.txt", "euroc")


@pytest.mark.parametrize(
    ("content", "pattern"),
    [
        ("1 0 0 0 0 1 0 0 0 0 1 0\n5 1 0 0 0 0 1 0 0 0 0 1 0\n", r"bad.txt:2: expected 12 numbers, got 13"),
        ("2.5 1 0 0 0 0 1 0 0 0 0 1 0\n", r"bad.txt:1: the first of 13 numbers must be a frame index"),
        ("3 1 0 0 0 0 1 0 0 0 0 1 0\n3 1 0 0 0 0 1 0 0 0 0 1 0\n", r"bad.txt: frame index 3 appears more than once"),
        ("0 1 2 3 0 0 0 0\n", r"bad.txt:1: zero quaternion"),
    ],
)
def test_malformed_kitti13_and_tum(tmp_path: Path, content: str, pattern: str) -> None:
    (tmp_path / "bad.txt").write_text(content)
    with pytest.raises(ValueError, match=pattern):
        read_trajectory(tmp_path / "bad.txt")


def test_malformed_euroc_names_line(tmp_path: Path) -> None:
    (tmp_path / "bad.csv").write_text("#timestamp, p_RS_R_x [m]\n1,2,3,4,1,0,0,0\n2,3,4,1,0,0\n")
    with pytest.raises(ValueError, match=r"bad.csv:3: expected 8 numbers, got 6"):
        read_trajectory(tmp_path / "bad.csv")
    (tmp_path / "bad2.csv").write_text("1,2,3,4,1,0,0,x\n")
    with pytest.raises(ValueError, match=r"bad2.csv:1: non-numeric"):
        read_trajectory(tmp_path / "bad2.csv", format="euroc")


# ------------------------------------------------------------------------------------------------ evo's readers


def test_evo_reads_what_we_write(tmp_path: Path) -> None:
    fi = pytest.importorskip("evo.tools.file_interface", reason="evo (test-only dependency) is not installed")
    poses = _random_poses(20, seed=8)
    stamps = 100.0 + np.arange(20) * 0.1
    write_kitti_poses(tmp_path / "k.txt", poses)
    write_tum_poses(tmp_path / "t.txt", poses, stamps)
    write_euroc_poses(tmp_path / "e.csv", poses, stamps)
    assert np.allclose(np.stack(fi.read_kitti_poses_file(str(tmp_path / "k.txt")).poses_se3), poses, atol=1e-6)
    for name in ("t.txt", "e.csv"):
        traj = (fi.read_tum_trajectory_file if name == "t.txt" else fi.read_euroc_csv_trajectory)(str(tmp_path / name))
        assert np.allclose(traj.timestamps, stamps, atol=1e-6), name
        assert np.allclose(np.stack(traj.poses_se3), poses, atol=1e-6), name
    # and the other way round: evo writes TUM, we read it
    fi.write_tum_trajectory_file(str(tmp_path / "evo.txt"), traj)
    back = read_trajectory(tmp_path / "evo.txt")
    assert np.allclose(back.timestamps, stamps, atol=1e-6) and np.allclose(back.poses, poses, atol=1e-6)


def test_evo_and_we_read_the_real_files_alike(kitti00, kitti00_times) -> None:
    fi = pytest.importorskip("evo.tools.file_interface", reason="evo (test-only dependency) is not installed")
    for key in ("gt", "orb", "sptam"):
        ours = read_trajectory(kitti00[key])
        assert len(ours) == 4541 and ours.frame_ids is None and ours.timestamps is None
        assert np.array_equal(ours.poses, np.stack(fi.read_kitti_poses_file(str(kitti00[key])).poses_se3))
    assert kitti00_times.shape == (4541,) and np.all(np.diff(kitti00_times) > 0)


def test_frame_times_must_increase(tmp_path: Path) -> None:
    """Issue 42 (what you read is checked): a times file whose times repeat or go back (two exports concatenated, a
    clock reset) is refused in one line naming the file and the line; it paired frames with the wrong ground truth."""
    from dfvo.io.trajectory import read_times

    good = tmp_path / "good.txt"
    good.write_text("0.0\n0.1\n0.2\n")
    np.testing.assert_array_equal(read_times(good), [0.0, 0.1, 0.2])
    for name, text, line in (("back.txt", "0.0\n0.1\n0.05\n0.2\n", 3), ("same.txt", "# times\n0.0\n0.1\n0.1\n", 4)):
        path = tmp_path / name
        path.write_text(text)
        with pytest.raises(ValueError, match=rf"^{re.escape(str(path))}:{line}: time .* is not after the line before"):
            read_times(path)
