"""KITTI raw snippets (real drive and hand-made layouts), OXTS poses against hand-derived motion, bad input."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from dfvo.data.image_io import DatasetError, DatasetNotFoundError, read_image
from dfvo.data.kitti_raw import (
    KittiRawSnippets,
    imu_to_camera,
    open_drives,
    oxts_camera_poses,
    oxts_to_imu_poses,
)
from dfvo.geometry.camera import resize_intrinsics

DATE, DRIVE = "2011_09_26", "2011_09_26_drive_0001_sync"
ER = 6378137.0
F, B = 30.0, 0.5  # a 53-degree lens on the 30x20 test frames (the reader checks the intrinsics)


def _fmt(vals: list[float]) -> str:
    return " ".join(f"{v:.12e}" for v in vals)


def make_raw(root: Path, n: int = 4, n_right: int | None = None, p2_tx: float = 0.06 * F,
             imu_to_velo_t: tuple[float, float, float] = (-0.8, 0.3, -0.8), with_p3: bool = True) -> Path:
    """Write ROOT/DATE/{calib files, DRIVE/image_02|03/data}; camera axes: x=-y_imu, y=-z_imu, z=x_imu."""
    date = root / DATE
    drive = date / DRIVE
    for cam, count in (("image_02", n), ("image_03", n if n_right is None else n_right)):
        (drive / cam / "data").mkdir(parents=True)
        for i in range(count):
            arr = np.full((20, 30, 3), 10 * i + (5 if cam == "image_03" else 0), np.uint8)
            Image.fromarray(arr).save(drive / cam / "data" / f"{i:010d}.png")
    lines = ["calib_time: 09-Jan-2012 13:57:47", "R_rect_00: " + _fmt([1, 0, 0, 0, 1, 0, 0, 0, 1]),
             "P_rect_02: " + _fmt([F, 0, 15.2, p2_tx, 0, F, 9.7, 0, 0, 0, 1, 0])]
    if with_p3:
        lines.append("P_rect_03: " + _fmt([F, 0, 15.2, p2_tx - B * F, 0, F, 9.7, 0, 0, 0, 1, 0]))
    (date / "calib_cam_to_cam.txt").write_text("\n".join(lines) + "\n")
    # velo = imu axes; camera0 = permuted velo axes at the velo origin
    (date / "calib_imu_to_velo.txt").write_text("R: " + _fmt([1, 0, 0, 0, 1, 0, 0, 0, 1]) + "\nT: "
                                                + _fmt(list(imu_to_velo_t)) + "\n")
    (date / "calib_velo_to_cam.txt").write_text("R: " + _fmt([0, -1, 0, 0, 0, -1, 1, 0, 0]) + "\nT: "
                                                + _fmt([0, 0, 0]) + "\n")
    return drive


def write_oxts(drive: Path, packets: list[tuple[float, float, float, float, float, float]]) -> None:
    folder = drive / "oxts" / "data"
    folder.mkdir(parents=True)
    for i, p in enumerate(packets):
        (folder / f"{i:010d}.txt").write_text(_fmt(list(p) + [0.0] * 24) + "\n")


LAT0, LON0, ALT0 = 49.0, 8.4, 110.0
DLAT_PER_M = math.degrees(1.0 / ER)  # northward metres to degrees (Mercator with scale cos(lat0) at lat0)
DLON_PER_M = math.degrees(1.0 / (ER * math.cos(math.radians(LAT0))))


# ---------------------------------------------------------------- OXTS poses, hand-derived


def test_oxts_north_facing_north_is_forward(tmp_path: Path) -> None:
    drive = make_raw(tmp_path, n=3)
    yaw = math.pi / 2  # heading north
    write_oxts(drive, [(LAT0 + DLAT_PER_M * d, LON0, ALT0, 0, 0, yaw) for d in (0.0, 5.0, 10.0)])
    poses = oxts_camera_poses(drive)
    assert poses is not None and poses.shape == (3, 4, 4)
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-9)
    for k, d in enumerate((0.0, 5.0, 10.0)):
        np.testing.assert_allclose(poses[k, :3, 3], [0.0, 0.0, d], atol=2e-3)  # along camera +z
        np.testing.assert_allclose(poses[k, :3, :3], np.eye(3), atol=1e-9)


def test_oxts_north_facing_east_is_left_and_altitude_is_up(tmp_path: Path) -> None:
    drive = make_raw(tmp_path, n=4)
    write_oxts(drive, [(LAT0, LON0, ALT0, 0, 0, 0.0),                       # heading east
                       (LAT0 + DLAT_PER_M * 7.0, LON0, ALT0, 0, 0, 0.0),    # 7 m north = 7 m to the left
                       (LAT0, LON0 + DLON_PER_M * 3.0, ALT0, 0, 0, 0.0),    # 3 m east = 3 m forward
                       (LAT0, LON0, ALT0 + 2.0, 0, 0, 0.0)])                # 2 m up = camera -y
    poses = oxts_camera_poses(drive)
    np.testing.assert_allclose(poses[1, :3, 3], [-7.0, 0.0, 0.0], atol=2e-3)
    np.testing.assert_allclose(poses[2, :3, 3], [0.0, 0.0, 3.0], atol=2e-3)
    np.testing.assert_allclose(poses[3, :3, 3], [0.0, -2.0, 0.0], atol=1e-9)


def test_oxts_left_turn_with_lever_arm(tmp_path: Path) -> None:
    # camera 1 m ahead of the IMU (T_velo_imu translation (-1,0,0), no rectified offset); turn left 90 deg in place
    drive = make_raw(tmp_path, n=2, p2_tx=0.0, imu_to_velo_t=(-1.0, 0.0, 0.0))
    write_oxts(drive, [(LAT0, LON0, ALT0, 0, 0, 0.3), (LAT0, LON0, ALT0, 0, 0, 0.3 + math.pi / 2)])
    T = oxts_camera_poses(drive)[1]
    # camera centre: (1,0,0) -> (0,1,0) in IMU0 axes, i.e. (-1, 0, -1) in camera-0 axes
    np.testing.assert_allclose(T[:3, 3], [-1.0, 0.0, -1.0], atol=1e-9)
    np.testing.assert_allclose(T[:3, 2], [-1.0, 0.0, 0.0], atol=1e-9)  # optical axis now points to camera-0 left
    np.testing.assert_allclose(T[:3, 1], [0.0, 1.0, 0.0], atol=1e-9)   # yaw keeps "down"


def test_oxts_rotation_order_is_rz_ry_rx() -> None:
    oxts = np.zeros((2, 30))
    oxts[:, 0] = LAT0
    oxts[1, 3:6] = (0.1, -0.2, 0.3)
    R = oxts_to_imu_poses(oxts)[1, :3, :3]
    cr, sr, cp, sp, cy, sy = math.cos(0.1), math.sin(0.1), math.cos(-0.2), math.sin(-0.2), math.cos(0.3), math.sin(0.3)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    np.testing.assert_allclose(R, Rz @ Ry @ Rx, atol=1e-12)


def test_oxts_poses_reach_the_snippets(tmp_path: Path) -> None:
    drive = make_raw(tmp_path, n=3)
    write_oxts(drive, [(LAT0 + DLAT_PER_M * d, LON0, ALT0, 0, 0, math.pi / 2) for d in (0.0, 1.0, 2.0)])
    s = KittiRawSnippets(tmp_path, None, None)[0]
    torch.testing.assert_close(s["pose"][2, 3], torch.tensor(1.0), atol=2e-3, rtol=0)
    torch.testing.assert_close(s["pose_prev"], torch.eye(4), atol=1e-6, rtol=0)
    torch.testing.assert_close(s["pose_next"][2, 3], torch.tensor(2.0), atol=2e-3, rtol=0)


def test_oxts_count_mismatch(tmp_path: Path) -> None:
    drive = make_raw(tmp_path, n=3)
    write_oxts(drive, [(LAT0, LON0, ALT0, 0, 0, 0)] * 2)
    with pytest.raises(DatasetError, match=r"oxts/data has 2 packets but image_02/data has 3"):
        KittiRawSnippets(tmp_path, None, None)


# ---------------------------------------------------------------- hand-made layout


def test_snippets_and_stereo_from_layout(tmp_path: Path) -> None:
    make_raw(tmp_path, n=5)
    ds = KittiRawSnippets(tmp_path / DATE, None, None, drives=["2011_09_26_drive_0001"])  # a DATE folder as root
    assert len(ds) == 3
    s = ds[1]  # frame 2
    assert int(s["index"]) == 2 and "pose" not in s
    assert s["image_prev"][0, 0, 0] * 255 == pytest.approx(10) and s["image_next"][0, 0, 0] * 255 == pytest.approx(30)
    assert s["image_right"][0, 0, 0] * 255 == pytest.approx(25)
    torch.testing.assert_close(s["T_right_left"][:3, 3], torch.tensor([-B, 0.0, 0.0]))
    torch.testing.assert_close(s["K"], torch.tensor([[F, 0, 15.2], [0, F, 9.7], [0, 0, 1.0]]))
    assert len(KittiRawSnippets(tmp_path, None, None, temporal=False)) == 5
    mono = KittiRawSnippets(tmp_path, None, None, stereo=False)[0]
    assert "image_right" not in mono and "T_right_left" not in mono


# ---------------------------------------------------------------- real drive


def test_real_drive(kitti_raw_root: Path) -> None:
    ds = KittiRawSnippets(kitti_raw_root.parent, 192, 640)
    assert len(ds) == 106  # 108 frames, targets 1..106
    drive = ds.drives[0]
    assert drive.native_size == (375, 1242)
    assert drive.baseline == pytest.approx((44.85728 + 339.5242) / 721.5377, abs=1e-6)
    K = torch.tensor([[721.5377, 0.0, 609.5593], [0.0, 721.5377, 172.854], [0.0, 0.0, 1.0]])
    torch.testing.assert_close(drive.K, resize_intrinsics(K, (375, 1242), (192, 640)))
    a, b = ds[0], ds[1]
    assert set(a) == {"image", "image_prev", "image_next", "image_right", "K", "T_right_left", "index"}
    assert a["image"].shape == (3, 192, 640)
    torch.testing.assert_close(a["image_next"], b["image"])
    torch.testing.assert_close(b["image_prev"], a["image"])
    assert (a["image"] - a["image_right"]).abs().mean() > 0.01  # really the other camera
    full = KittiRawSnippets(kitti_raw_root, None, None, drives=[f"{DATE}/{DRIVE}"], temporal=False)
    torch.testing.assert_close(full[0]["image"], read_image(kitti_raw_root / DRIVE / "image_02" / "data" /
                                                            "0000000000.jpg"))


def test_real_imu_to_camera_is_forward_looking(kitti_raw_root: Path) -> None:
    T = imu_to_camera(kitti_raw_root)
    R = T[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-5)
    assert (R @ np.array([1.0, 0, 0]))[2] > 0.99   # IMU forward = camera +z
    assert (R @ np.array([0, 0, 1.0]))[1] < -0.99  # IMU up = camera -y
    assert oxts_camera_poses(kitti_raw_root / DRIVE) is None  # this copy has no oxts


# ---------------------------------------------------------------- bad input


def test_missing_root_and_no_drives(tmp_path: Path) -> None:
    with pytest.raises(DatasetNotFoundError, match="nowhere"):
        KittiRawSnippets(tmp_path / "nowhere", 192, 640)
    (tmp_path / DATE).mkdir()
    with pytest.raises(DatasetError, match="no DATE/DATE_drive_XXXX_sync"):
        KittiRawSnippets(tmp_path, 192, 640)


def test_unknown_drive(tmp_path: Path) -> None:
    make_raw(tmp_path)
    with pytest.raises(DatasetError, match=r"drive '2011_09_26_drive_0099_sync' not found"):
        KittiRawSnippets(tmp_path, None, None, drives=["2011_09_26_drive_0099_sync"])


def test_drive_by_its_number(tmp_path: Path) -> None:
    make_raw(tmp_path, n=3)
    for name in ("0001", "1", "0001_sync"):  # the number alone names the one drive of that number
        ds = KittiRawSnippets(tmp_path, None, None, drives=[name], temporal=False)
        assert len(ds) == 3
    with pytest.raises(DatasetError, match=r"drive '0002' not found .*seq=DATE_drive_NNNN or its number NNNN"):
        KittiRawSnippets(tmp_path, None, None, drives=["0002"])
    other = tmp_path / "2011_09_28" / "2011_09_28_drive_0001_sync" / "image_02" / "data"  # a second date, drive 1 too
    other.mkdir(parents=True)
    with pytest.raises(DatasetError, match=r"drive '0001' is ambiguous .*seq=2011_09_26_drive_0001\)"):
        KittiRawSnippets(tmp_path, None, None, drives=["0001"])


def test_left_right_mismatch(tmp_path: Path) -> None:
    make_raw(tmp_path, n=4, n_right=3)
    with pytest.raises(DatasetError, match=r"image_02/data has 4 images but image_03/data has 3"):
        KittiRawSnippets(tmp_path, None, None)
    assert len(KittiRawSnippets(tmp_path, None, None, stereo=False)) == 2


def test_empty_image_folder(tmp_path: Path) -> None:
    drive = make_raw(tmp_path, n=0)
    with pytest.raises(DatasetError, match=rf"{drive / 'image_02' / 'data'}.*contains no images"):
        KittiRawSnippets(tmp_path, None, None)


def test_missing_or_incomplete_calibration(tmp_path: Path) -> None:
    make_raw(tmp_path, with_p3=False)
    with pytest.raises(DatasetError, match=r"calib_cam_to_cam.txt has no 'P_rect_03:' line"):
        KittiRawSnippets(tmp_path, None, None)
    (tmp_path / DATE / "calib_cam_to_cam.txt").unlink()
    with pytest.raises(DatasetNotFoundError, match="calib_cam_to_cam.txt"):
        KittiRawSnippets(tmp_path, None, None)


def test_truncated_frame_named(tmp_path: Path) -> None:
    drive = make_raw(tmp_path, n=3)
    bad = drive / "image_02" / "data" / "0000000002.png"
    bad.write_bytes(bad.read_bytes()[:30])
    with pytest.raises(DatasetError, match="0000000002.png"):
        KittiRawSnippets(tmp_path, None, None)[0]


@pytest.mark.parametrize("bad", [0, 1])
def test_oxts_packet_with_nan_is_a_frame_without_ground_truth(tmp_path: Path, caplog: pytest.LogCaptureFixture,
                                                              bad: int) -> None:
    """Issue 42: a packet with a NaN latitude (the first one too) leaves its frame without ground truth, names the
    packet file, and keeps the others exact (metres from the first finite packet)."""
    drive = make_raw(tmp_path, n=3)
    write_oxts(drive, [(LAT0 + DLAT_PER_M * d, LON0, ALT0, 0, 0, math.pi / 2) for d in (0.0, 1.0, 2.0)])
    packet = drive / "oxts" / "data" / f"{bad:010d}.txt"
    packet.write_text("nan " + packet.read_text().split(" ", 1)[1])
    with caplog.at_level("WARNING", "dfvo.data"):
        poses = oxts_camera_poses(drive)
    assert np.isnan(poses[bad]).all()
    good = [k for k in range(3) if k != bad]
    np.testing.assert_allclose(poses[good[0]], np.eye(4), atol=1e-9)
    np.testing.assert_allclose(poses[good[1], 2, 3], good[1] - good[0], atol=2e-3)  # forward = north
    assert [r.getMessage() for r in caplog.records] == [
        f"oxts packet {packet}: NaN or infinite position or attitude; its frame is evaluated without ground truth"]


def test_monocular_drive_without_right_camera_or_imu_calibration(tmp_path: Path,
                                                                 caplog: pytest.LogCaptureFixture) -> None:
    """Issue 42: a monocular read needs neither image_03 nor P_rect_03, and a drive whose IMU calibration is missing
    runs without ground truth (with one warning line naming the file) instead of being refused."""
    drive = make_raw(tmp_path, n=3, with_p3=False)
    write_oxts(drive, [(LAT0, LON0, ALT0, 0, 0, 0)] * 3)
    (drive / "image_03" / "data").rename(tmp_path / "away")
    (drive.parent / "calib_imu_to_velo.txt").unlink()
    with pytest.raises(DatasetError, match="image_03"):  # a stereo read needs it
        KittiRawSnippets(tmp_path, None, None, stereo=True)
    with caplog.at_level("WARNING", "dfvo.data"):
        ds = KittiRawSnippets(tmp_path, None, None, stereo=False, temporal=True)
    assert len(ds) == 1 and ds.drives[0].poses is None and ds.drives[0].baseline is None
    drive = open_drives(tmp_path, stereo=False)[0]  # what a monocular inference run opens
    assert len(drive.left) == 3 and drive.right is None and drive.poses is None
    assert "calib_imu_to_velo.txt" in caplog.text and "has no ground truth" in caplog.text
