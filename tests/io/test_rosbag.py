"""ROS 2 bags (dfvo.io.rosbag, ``output.rosbag=true``) read back with the same library: one ``nav_msgs/msg/Odometry``
per frame equal to the pose file and carrying the covariance, the TF tree, the ground truth; closed on Ctrl-C."""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("rosbags", reason="output.rosbag needs the ros extra (rosbags)")

from dfvo.geometry.pose_covariance import (  # noqa: E402
    covariance_from_row,
    propagate_pose_covariance,
    ros_pose_covariance,
    ros_twist_covariance,
)
from dfvo.io.rosbag import (  # noqa: E402
    NOMINAL_PERIOD_S,
    TOPIC_GROUND_TRUTH,
    TOPIC_ODOMETRY,
    TOPIC_TF,
    OdometryBagWriter,
    rotation_to_quaternion,
)

REPO = Path(__file__).resolve().parents[2]
SMALL = ["img_res.height=96", "img_res.width=320", "progress=false", "num_threads=1", "flow=oracle", "depth=oracle"]


def read_bag(path: Path) -> dict[str, list[tuple[int, object]]]:
    """Every message of the bag by topic: (timestamp ns, deserialized message)."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    out: dict[str, list[tuple[int, object]]] = {}
    with Reader(path) as reader:
        for conn, stamp, raw in reader.messages():
            out.setdefault(conn.topic, []).append((stamp, store.deserialize_cdr(raw, conn.msgtype)))
    return out


def pose_matrix(pose: object) -> np.ndarray:
    from kornia.geometry.conversions import quaternion_to_rotation_matrix

    q = pose.orientation
    T = np.eye(4)
    T[:3, :3] = quaternion_to_rotation_matrix(torch.tensor([q.w, q.x, q.y, q.z], dtype=torch.float64)).numpy()
    T[:3, 3] = [pose.position.x, pose.position.y, pose.position.z]
    return T


def read_kitti(path: Path) -> np.ndarray:
    rows = np.loadtxt(path, ndmin=2)
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    T[:, :3, :4] = rows.reshape(-1, 3, 4)
    return T


def test_quaternions_round_trip() -> None:
    from dfvo.geometry.essential_refine import so3_exp

    gen = torch.Generator().manual_seed(0)
    for w in [torch.zeros(3), torch.tensor([3.1, 0.0, 0.0]), *torch.randn(20, 3, generator=gen)]:
        R = so3_exp(w.double()).numpy()
        x, y, z, qw = rotation_to_quaternion(R)
        assert qw >= 0 and abs(x * x + y * y + z * z + qw * qw - 1) < 1e-12
        back = pose_matrix(type("P", (), {"orientation": type("Q", (), dict(x=x, y=y, z=z, w=qw)),
                                          "position": type("V", (), dict(x=0.0, y=0.0, z=0.0))}))
        assert np.allclose(back[:3, :3], R, atol=1e-12)


def test_infer_writes_a_bag_with_one_odometry_per_frame(tmp_path: Path, infer_cli) -> None:
    """``infer.py output.rosbag=true`` on the synthetic world (true flow and depth): the bag has one Odometry, one TF
    and one ground-truth message per frame at the frames' times; the poses equal the pose file; the pose covariance
    is the propagation of frames.csv's step covariances and the twist covariance is the step's, in ROS order."""
    n = 8
    out = tmp_path / "out"
    infer_cli(f"out_dir={out}", f"data.num_frames={n}", "output.rosbag=true", "output.ros_world_frame=map", *SMALL)
    poses = read_kitti(out / "synthetic_drive_s0.txt")
    rows = list(csv.DictReader((out / "frames.csv").open()))
    bag = read_bag(out / "bag")
    odom, tf, gt = bag[TOPIC_ODOMETRY], bag[TOPIC_TF], bag[TOPIC_GROUND_TRUTH]
    assert len(odom) == len(tf) == len(gt) == len(poses) == n
    assert [s for s, _ in odom] == [round(k * 0.1 * 1e9) for k in range(n)]  # the synthetic camera's 10 Hz
    cov_w = torch.zeros(6, 6, dtype=torch.float64)
    for k, ((_, msg), (_, tfm)) in enumerate(zip(odom, tf, strict=True)):
        assert msg.header.frame_id == "map" and msg.child_frame_id == "camera"
        assert np.allclose(pose_matrix(msg.pose.pose), poses[k], atol=1e-8)
        tr = tfm.transforms[0]
        assert tr.child_frame_id == "camera" and abs(tr.transform.translation.z - poses[k][2, 3]) < 1e-8
        if k == 0:
            assert not np.asarray(msg.pose.covariance).any()
            continue
        C = covariance_from_row(rows[k])
        step = torch.from_numpy(np.linalg.inv(poses[k - 1]) @ poses[k])
        cov_w = propagate_pose_covariance(cov_w, torch.from_numpy(poses[k - 1]), C, step)
        expected_pose, expected_twist = np.asarray(ros_pose_covariance(cov_w)), np.asarray(ros_twist_covariance(C, step,
                                                                                                               0.1))
        # frames.csv keeps 6 significant digits: entries compared to 1e-4 of the matrix's largest
        assert np.allclose(msg.pose.covariance, expected_pose, rtol=1e-3, atol=1e-4 * np.abs(expected_pose).max())
        assert np.allclose(msg.twist.covariance, expected_twist, rtol=1e-3, atol=1e-4 * np.abs(expected_twist).max())
        v = (step[:3, :3].T @ step[:3, 3]).numpy() / 0.1  # in the camera's (child frame's) axes: ~10 m/s forward
        assert np.allclose([msg.twist.twist.linear.x, msg.twist.twist.linear.y, msg.twist.twist.linear.z], v,
                           atol=1e-6)
        assert np.all(np.diag(np.asarray(msg.pose.covariance).reshape(6, 6)) > 0)
    # the ground truth, relative to its first pose, matches the estimate (true flow and depth: exact to ~1e-3)
    assert np.allclose(pose_matrix(gt[-1][1].pose.pose), poses[-1], atol=1e-2)
    assert gt[0][1].child_frame_id == "camera_gt"


def test_writer_without_timestamps_and_replaced_folder(tmp_path: Path) -> None:
    """No timestamps: stamps 0.1 s apart and the twist marked unknown; the writer refuses an existing folder."""
    path = tmp_path / "bag"
    T1 = np.eye(4)
    T1[2, 3] = 1.0
    with OdometryBagWriter(path) as writer:
        writer.write(0, np.eye(4), None)
        writer.write(1, T1, np.eye(6) * 1e-4)
    bag = read_bag(path)
    stamps = [s for s, _ in bag[TOPIC_ODOMETRY]]
    assert stamps == [0, round(NOMINAL_PERIOD_S * 1e9)]
    msg = bag[TOPIC_ODOMETRY][1][1]
    assert msg.twist.covariance[0] == -1.0 and msg.twist.twist.linear.z == 0.0
    assert TOPIC_GROUND_TRUTH not in bag
    with pytest.raises(FileExistsError, match="exists already"):
        OdometryBagWriter(path)


def test_mcap_storage(tmp_path: Path) -> None:
    """``storage="mcap"``: one ``bag.mcap`` (no sqlite3 file) with the same messages as the sqlite3 bag, readable
    after each frame (its chunks written as frames come) and complete after close; another storage is one line."""
    T1 = np.eye(4)
    T1[:3, 3] = [0.1, -0.2, 1.0]
    paths = {}
    for storage in ("sqlite3", "mcap"):
        paths[storage] = tmp_path / storage
        with OdometryBagWriter(paths[storage], storage=storage, ground_truth=np.stack([np.eye(4), T1])) as writer:
            writer.write(0, np.eye(4), None, 5.0)
            if storage == "mcap":  # the first frame's messages are on disk already, one chunk
                data = (paths[storage] / "mcap.mcap").read_bytes()
                assert data.startswith(b"\x89MCAP0\r\n") and data.count(b"/dfvo/odometry") == 1
            writer.write(1, T1, np.eye(6) * 1e-4, 5.1)
    assert sorted(p.name for p in paths["mcap"].iterdir()) == ["mcap.mcap", "metadata.yaml"]
    assert "storage_identifier: mcap" in (paths["mcap"] / "metadata.yaml").read_text()
    bags = {storage: read_bag(path) for storage, path in paths.items()}
    assert set(bags["mcap"]) == set(bags["sqlite3"]) == {TOPIC_ODOMETRY, TOPIC_TF, TOPIC_GROUND_TRUTH}
    for topic, messages in bags["sqlite3"].items():
        assert [s for s, _ in bags["mcap"][topic]] == [s for s, _ in messages] == [5_000_000_000, 5_100_000_000]
        assert [repr(m) for _, m in bags["mcap"][topic]] == [repr(m) for _, m in messages]
    assert np.allclose(pose_matrix(bags["mcap"][TOPIC_ODOMETRY][1][1].pose.pose), T1, atol=1e-12)
    with pytest.raises(ValueError, match=r"^output.rosbag_storage='zip'; expected one of \['sqlite3', 'mcap'\]$"):
        OdometryBagWriter(tmp_path / "zip", storage="zip")


def test_missing_extra_is_one_line(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setitem(sys.modules, "rosbags.rosbag2", None)
    hint = r"^output.rosbag=true needs the rosbags library: pip install \"dfvo\[ros\]\"$"
    with pytest.raises(ImportError, match=hint):
        OdometryBagWriter(tmp_path / "bag")


@pytest.mark.slow
def test_interrupted_run_closes_the_bag(tmp_path: Path) -> None:
    """Ctrl-C during a long run: the bag is finalised (metadata.yaml) and holds one Odometry per pose written."""
    n = 300
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, str(REPO / "infer.py"), f"out_dir={out}", f"data.num_frames={n}",
                             "batch_size=1", "output.rosbag=true", *SMALL], cwd=tmp_path,
                            env=dict(os.environ, OMP_NUM_THREADS="1"), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    path = out / "synthetic_drive_s0.txt"
    deadline = time.time() + 300
    try:
        while time.time() < deadline and proc.poll() is None:
            if path.exists() and len(path.read_text().splitlines()) >= 4:
                break
            time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=300) == 128 + signal.SIGINT
    finally:
        if proc.poll() is None:
            proc.kill()
    poses = read_kitti(path)
    assert 4 <= len(poses) < n
    assert (out / "bag" / "metadata.yaml").is_file()
    odom = read_bag(out / "bag")[TOPIC_ODOMETRY]
    assert len(odom) == len(poses)
    assert np.allclose(pose_matrix(odom[-1][1].pose.pose), poses[-1], atol=1e-8)
