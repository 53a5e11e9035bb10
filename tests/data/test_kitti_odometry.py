"""KITTI Odometry loader: the real sequence 06 snippet, a hand-made colour layout, and every bad-input error."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from torch.utils.data import DataLoader

from dfvo.data.image_io import DatasetError, DatasetNotFoundError, read_image
from dfvo.data.kitti_odometry import KittiOdometry
from dfvo.geometry.camera import resize_intrinsics

FX, CX, FY, CY = 35.0, 20.5, 34.5, 11.5  # a 60-degree lens on the 40x24 test frames (the reader checks)
# P2 / P3 as KITTI writes them: K [I | t] with t relative to rectified camera 0
P = {0: [FX, 0, CX, 0, 0, FY, CY, 0, 0, 0, 1, 0],
     1: [FX, 0, CX, -FX * 0.54, 0, FY, CY, 0, 0, 0, 1, 0],
     2: [FX, 0, CX, 44.857, 0, FY, CY, 0.2163, 0, 0, 1, 0.0027],
     3: [FX, 0, CX, -339.524, 0, FY, CY, 2.1999, 0, 0, 1, 0.0027]}


def _image(k: int, h: int = 24, w: int = 40, gray: bool = False) -> np.ndarray:
    rng = np.random.default_rng(k)
    return rng.integers(0, 256, size=(h, w) if gray else (h, w, 3), dtype=np.uint8)


def make_sequence(root: Path, n: int = 5, color: bool = True, stereo: bool = True, poses: int | None = None,
                  times: int | None = None, calib: tuple[int, ...] = (0, 1, 2, 3), n_right: int | None = None) -> Path:
    """Write ROOT/sequences/00 with n frames (colour: image_2/3, else image_0/1), calib, times, poses."""
    seq = root / "sequences" / "00"
    left, right = ("image_2", "image_3") if color else ("image_0", "image_1")
    (seq / left).mkdir(parents=True)
    for i in range(n):
        Image.fromarray(_image(i, gray=not color)).save(seq / left / f"{i:06d}.png")
    if stereo:
        (seq / right).mkdir()
        for i in range(n if n_right is None else n_right):
            Image.fromarray(_image(100 + i, gray=not color)).save(seq / right / f"{i:06d}.png")
    (seq / "calib.txt").write_text("".join(f"P{c}: " + " ".join(f"{v:.12e}" for v in P[c]) + "\n" for c in calib))
    if times is not None:
        (seq / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(times)))
    if poses is not None:
        (root / "poses").mkdir()
        rows = [f"1 0 0 {0.5 * i} 0 1 0 {-0.1 * i} 0 0 1 {1.0 * i}" for i in range(poses)]
        (root / "poses" / "00.txt").write_text("\n".join(rows) + "\n")
    return seq


# ---------------------------------------------------------------- real data


def test_real_sequence_06(kitti_odom_root: Path) -> None:
    ds = KittiOdometry(kitti_odom_root, "06")
    assert len(ds) == 51 and ds.camera == "gray" and ds.stereo
    K = torch.tensor([[707.0912, 0.0, 601.8873], [0.0, 707.0912, 183.1104], [0.0, 0.0, 1.0]])
    torch.testing.assert_close(ds.intrinsics, K)
    assert ds.baseline == pytest.approx(379.8145 / 707.0912, abs=1e-9)
    assert ds.baseline == pytest.approx(0.537, abs=1e-3)
    assert ds.poses is not None and ds.poses.shape == (51, 4, 4)
    np.testing.assert_allclose(ds.poses[0], np.eye(4), atol=1e-9)
    assert ds.poses[-1, 2, 3] > 5.0  # the car drives forward along +z
    assert ds.timestamps is not None and ds.timestamps[1] == pytest.approx(0.1044989)
    s = ds[0]
    seq = kitti_odom_root / "sequences" / "06"
    assert s["image"].shape == (3, 370, 1226)
    torch.testing.assert_close(s["image"], read_image(seq / "image_0" / "000000.png"))
    torch.testing.assert_close(s["image_right"], read_image(seq / "image_1" / "000000.png"))
    assert torch.equal(s["image"][0], s["image"][2])
    torch.testing.assert_close(s["T_right_left"][:3, 3], torch.tensor([-ds.baseline, 0.0, 0.0]))
    torch.testing.assert_close(s["pose"], torch.eye(4), atol=1e-6, rtol=0)


def test_real_sequence_resized_and_sliced(kitti_odom_root: Path) -> None:
    full = KittiOdometry(kitti_odom_root, "6", stereo=False)
    ds = KittiOdometry(kitti_odom_root, "06", height=192, width=640, frames=slice(10, 20, 3), stereo=False)
    assert len(ds) == 4 and ds.frame_ids == [10, 13, 16, 19]
    torch.testing.assert_close(ds.intrinsics, resize_intrinsics(full.intrinsics, (370, 1226), (192, 640)))
    s = ds[1]
    assert s["image"].shape == (3, 192, 640) and "image_right" not in s
    assert int(s["index"]) == 13
    torch.testing.assert_close(s["pose"], torch.as_tensor(full.poses[13], dtype=torch.float32))
    assert ds.timestamps is not None and ds.timestamps[0] == full.timestamps[10]


# ---------------------------------------------------------------- hand-made layouts


def test_colour_layout_preferred_and_exact(tmp_path: Path) -> None:
    seq = make_sequence(tmp_path, n=5, poses=5, times=5)
    make_gray = seq / "image_0"  # a gray folder beside the colour one must be ignored under camera="auto"
    make_gray.mkdir()
    Image.fromarray(_image(0, gray=True)).save(make_gray / "000000.png")
    ds = KittiOdometry(tmp_path, "00")
    assert ds.camera == "color" and len(ds) == 5
    assert ds.baseline == pytest.approx((44.857 + 339.524) / FX)
    torch.testing.assert_close(ds.intrinsics, torch.tensor([[FX, 0, CX], [0, FY, CY], [0, 0, 1.0]]))
    s = ds[3]
    torch.testing.assert_close(s["image"], torch.from_numpy(_image(3)).permute(2, 0, 1) / 255.0)
    torch.testing.assert_close(s["image_right"], torch.from_numpy(_image(103)).permute(2, 0, 1) / 255.0)
    torch.testing.assert_close(s["pose"][:3, 3], torch.tensor([1.5, -0.3, 3.0]))
    batch = next(iter(DataLoader(ds, batch_size=2)))
    assert batch["image"].shape == (2, 3, 24, 40) and batch["K"].shape == (2, 3, 3)
    assert batch["pose"].shape == (2, 4, 4) and batch["T_right_left"].shape == (2, 4, 4)


def test_gray_only_without_p2_p3_is_fine(tmp_path: Path) -> None:
    make_sequence(tmp_path, color=False, calib=(0, 1))
    ds = KittiOdometry(tmp_path, "00")
    assert ds.camera == "gray" and ds.baseline == pytest.approx(0.54)
    assert ds.poses is None and ds.timestamps is None and "pose" not in ds[0]
    img = ds[0]["image"]
    assert img.shape == (3, 24, 40) and torch.equal(img[0], img[1])


# ---------------------------------------------------------------- bad input


def test_missing_sequence_folder(tmp_path: Path) -> None:
    with pytest.raises(DatasetNotFoundError, match=r"sequences/07"):
        KittiOdometry(tmp_path, "07")


def test_folder_without_images(tmp_path: Path) -> None:
    seq = tmp_path / "sequences" / "00" / "image_2"
    seq.mkdir(parents=True)
    (seq / "readme.txt").write_text("no images here")
    with pytest.raises(DatasetError, match=r"image_2.*contains no images"):
        KittiOdometry(tmp_path, "00")


def test_missing_calib_file(tmp_path: Path) -> None:
    seq = make_sequence(tmp_path)
    (seq / "calib.txt").unlink()
    with pytest.raises(DatasetNotFoundError, match="calib.txt"):
        KittiOdometry(tmp_path, "00")


def test_calib_without_needed_matrix(tmp_path: Path) -> None:
    make_sequence(tmp_path, calib=(0, 1, 2))  # colour stereo needs P3
    with pytest.raises(DatasetError, match=r"calib.txt has no 'P3:' line"):
        KittiOdometry(tmp_path, "00")
    assert len(KittiOdometry(tmp_path, "00", stereo=False)) == 5  # P2 alone suffices for monocular


def test_pose_count_mismatch(tmp_path: Path) -> None:
    make_sequence(tmp_path, n=5, poses=4)
    with pytest.raises(DatasetError, match=r"00.txt has 4 poses .* 5 images"):
        KittiOdometry(tmp_path, "00")


def test_pose_file_with_frame_indices_and_malformed_pose_file(tmp_path: Path) -> None:
    """ROOT/poses/SS.txt goes through the one KITTI pose reader (dfvo.io.trajectory): 13 numbers a line (frame
    index first) read like 12; a bad line is a DatasetError naming the file and the line."""
    make_sequence(tmp_path, n=3, poses=3)
    pose_file = tmp_path / "poses" / "00.txt"
    rows = pose_file.read_text().splitlines()
    pose_file.write_text("".join(f"{i} {row}\n" for i, row in enumerate(rows)))
    ds = KittiOdometry(tmp_path, "00")
    torch.testing.assert_close(ds[2]["pose"][:3, 3], torch.tensor([1.0, -0.2, 2.0]))
    pose_file.write_text("".join(f"{row}\n" for row in rows[:2]) + "1 0 0 x 0 1 0 0 0 0 1 0\n")
    with pytest.raises(DatasetError, match=r"00.txt:3: non-numeric"):
        KittiOdometry(tmp_path, "00")


def test_times_count_mismatch(tmp_path: Path) -> None:
    make_sequence(tmp_path, n=5, times=6)
    with pytest.raises(DatasetError, match=r"times.txt has 6 entries"):
        KittiOdometry(tmp_path, "00")


def test_malformed_times_file_names_the_line(tmp_path: Path) -> None:
    """times.txt is read by dfvo.io.trajectory.read_times: a bad line is named by file and line number."""
    seq = make_sequence(tmp_path, n=3, times=3)
    (seq / "times.txt").write_text("0.0\n1.0e-01 0.2\n2.0e-01\n")
    with pytest.raises(DatasetError, match=r"^times file: .*times.txt:2: expected 1 numbers, got 2"):
        KittiOdometry(tmp_path, "00")
    (seq / "times.txt").write_text("0.0\nabc\n2.0e-01\n")
    with pytest.raises(DatasetError, match=r"times.txt:2: non-numeric value"):
        KittiOdometry(tmp_path, "00")


def test_left_right_count_mismatch(tmp_path: Path) -> None:
    make_sequence(tmp_path, n=5, n_right=3)
    with pytest.raises(DatasetError, match=r"image_2 has 5 images but image_3 has 3"):
        KittiOdometry(tmp_path, "00")
    assert "image_right" not in KittiOdometry(tmp_path, "00", stereo=False)[0]


def test_truncated_image_named_on_access(tmp_path: Path) -> None:
    seq = make_sequence(tmp_path, n=3)
    bad = seq / "image_2" / "000002.png"
    data = bad.read_bytes()
    bad.write_bytes(data[: len(data) // 2])
    ds = KittiOdometry(tmp_path, "00")
    ds[0]
    with pytest.raises(DatasetError, match="000002.png"):
        ds[2]


def test_frame_of_wrong_size(tmp_path: Path) -> None:
    seq = make_sequence(tmp_path, n=3)
    Image.fromarray(_image(1, h=30, w=40)).save(seq / "image_2" / "000001.png")
    with pytest.raises(DatasetError, match=r"000001.png is 30x40, expected 24x40"):
        KittiOdometry(tmp_path, "00")[1]


def test_bad_settings(tmp_path: Path) -> None:
    make_sequence(tmp_path)
    with pytest.raises(ValueError, match="height and width"):
        KittiOdometry(tmp_path, "00", height=192)
    with pytest.raises(ValueError, match="camera"):
        KittiOdometry(tmp_path, "00", camera="infrared")
    with pytest.raises(DatasetError, match="selects no frame"):
        KittiOdometry(tmp_path, "00", frames=slice(10, 20))


def test_temporal_snippets(tmp_path: Path) -> None:
    make_sequence(tmp_path, n=5, poses=5)
    ds = KittiOdometry(tmp_path, "00", temporal=True)
    assert len(ds) == 3
    s = ds[0]  # frame 1
    assert int(s["index"]) == 1
    torch.testing.assert_close(s["image_prev"], torch.from_numpy(_image(0)).permute(2, 0, 1) / 255.0)
    torch.testing.assert_close(s["image_next"], torch.from_numpy(_image(2)).permute(2, 0, 1) / 255.0)
    torch.testing.assert_close(s["pose_prev"][2, 3], torch.tensor(0.0))
    torch.testing.assert_close(s["pose_next"][2, 3], torch.tensor(2.0))
    assert int(ds[-1]["index"]) == 3
    with pytest.raises(DatasetError, match="at least 3 frames"):
        KittiOdometry(tmp_path, "00", temporal=True, frames=slice(0, 2))
