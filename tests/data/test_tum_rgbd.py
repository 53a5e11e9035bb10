"""TUM RGB-D reader on tiny layouts: synthetic-world frames with known poses, nearest-time association at 100 Hz,
the published freiburg1/2/3 calibrations chosen by folder name, undistortion against OpenCV, error messages."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from dfvo.data.image_io import DatasetError, DatasetNotFoundError
from dfvo.data.intrinsics_check import IntrinsicsError
from dfvo.data.tum_rgbd import TUM_CAMERAS, TumRgbdSequence, open_tum, tum_camera_from_name
from dfvo.geometry.camera import resize_intrinsics
from dfvo.synthetic import SyntheticWorld

Rotation = pytest.importorskip("scipy.spatial.transform", reason="SciPy (test-only reference) not installed").Rotation
cv2 = pytest.importorskip("cv2", reason="OpenCV (test-only reference) not installed")

N, H, W = 7, 64, 208
T0 = 1305031102.175304  # first colour frame of freiburg1_xyz
DT = 1 / 30


@pytest.fixture(scope="module")
def world() -> SyntheticWorld:
    return SyntheticWorld(seed=2, num_frames=N, height=H, width=W)


def gt_line(t: float, T: np.ndarray) -> str:
    q = Rotation.from_matrix(T[:3, :3]).as_quat()  # (x, y, z, w), independent reference
    return f"{t:.6f} " + " ".join(f"{v:.17g}" for v in (*T[:3, 3], *q))


def build_tum(root: Path, frames: list[np.ndarray], poses: np.ndarray | None, gt_from: int = 0) -> np.ndarray:
    """Write ROOT/rgb/*.png, rgb.txt and (with ``poses``) a 100 Hz groundtruth.txt starting at frame ``gt_from``."""
    (root / "rgb").mkdir(parents=True)
    stamps = np.round(T0 + DT * np.arange(len(frames)), 6)
    lines = ["# color images", "# file: 'rgbd_dataset.bag'", "# timestamp filename"]
    for img, t in zip(frames, stamps):
        Image.fromarray(img).save(root / "rgb" / f"{t:.6f}.png")
        lines.append(f"{t:.6f} rgb/{t:.6f}.png")
    (root / "rgb.txt").write_text("\n".join(lines) + "\n")
    if poses is not None:
        decoy = np.eye(4)
        decoy[:3, 3] = (0.3, 0.0, -0.4)
        rows = ["# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"]
        for i in range(gt_from, len(frames)):  # true sample 3 ms after the frame, decoys 7 ms before and 13 ms after
            rows += [gt_line(stamps[i] - 0.007, decoy @ poses[i]), gt_line(stamps[i] + 0.003, poses[i]),
                     gt_line(stamps[i] + 0.013, poses[i] @ decoy)]
        (root / "groundtruth.txt").write_text("\n".join(rows) + "\n")
    return stamps


def rgb8(world: SyntheticWorld, i: int) -> np.ndarray:
    return (world.image(i).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)


def test_poses_timestamps_given_intrinsics(tmp_path: Path, world: SyntheticWorld) -> None:
    poses = world.poses().double().numpy()
    root = tmp_path / "rgbd_dataset_freiburg1_synthetic"
    stamps = build_tum(root, [rgb8(world, i) for i in range(N)], poses, gt_from=1)
    fx, fy, cx, cy = (float(v) for v in world.intrinsics()[[0, 1, 0, 1], [0, 1, 2, 2]])
    seq = open_tum(root, fx=fx, fy=fy, cx=cx, cy=cy)
    assert seq.name == root.name and seq.length == N - 1
    np.testing.assert_allclose(seq.poses, poses[1:], atol=1e-9)
    np.testing.assert_allclose(seq.timestamps, stamps[1:], rtol=0, atol=1e-7)
    assert torch.allclose(seq.K, world.intrinsics().float())
    assert torch.allclose(seq.load(2), torch.from_numpy(rgb8(world, 3)).permute(2, 0, 1).float() / 255, atol=1e-6)
    # policies and ranges
    full = TumRgbdSequence(root, fx, fy, cx, cy, unmatched="nan")
    assert len(full) == N and np.isnan(full.poses[0]).all() and "6 of 7 frames matched" in full.report
    assert open_tum(root, fx=fx, fy=fy, cx=cx, cy=cy, unmatched="none").poses is None
    part = TumRgbdSequence(root, fx, fy, cx, cy, frames=slice(0, 6, 2))  # rows 0, 2, 4 -> 2, 4
    assert list(part.frame_ids) == [2, 4] and "dropped 1 frames before" in part.report
    # given intrinsics are checked against the stored frames; the published fr1 ones do not fit 208x64 frames
    with pytest.raises(IntrinsicsError, match=r"^data.cy=99 is outside the 64-px-high image"):
        open_tum(root, fx=fx, fy=fy, cx=cx, cy=99)
    with pytest.raises(IntrinsicsError, match=r"^cx=318.6 in the published fr1 calibration is outside the 208-px"):
        open_tum(root)
    with pytest.raises(ValueError, match="give all of data.fx, data.fy, data.cx, data.cy, or none"):
        open_tum(root, fx=fx)


def pattern(h: int, w: int) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    img = np.stack([0.5 + 0.45 * np.sin(x / 9 + y / 13), 0.5 + 0.45 * np.cos(x / 7 - y / 11),
                    0.5 + 0.45 * np.sin((x + y) / 15)], -1)
    return (img * 255).round().astype(np.uint8)


@pytest.mark.parametrize("folder, key", [("rgbd_dataset_freiburg1_xyz", "fr1"), ("rgbd_dataset_freiburg2_desk", "fr2"),
                                         ("rgbd_dataset_freiburg3_long_office_household", "fr3")])
def test_published_calibration_by_folder_name(tmp_path: Path, folder: str, key: str) -> None:
    img = pattern(480, 640)
    build_tum(tmp_path / folder, [img, img], None)
    seq = TumRgbdSequence(tmp_path / folder)
    fx, fy, cx, cy, dist = TUM_CAMERAS[key]
    assert seq.camera == key and "intrinsics: " + key in seq.report and seq.poses is None
    assert torch.allclose(seq.K.double(), torch.tensor([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]], dtype=torch.float64))
    if key == "fr3":  # stored undistorted
        assert seq.prep.undistort is None
        assert torch.allclose(seq.image(0), torch.from_numpy(img).permute(2, 0, 1) / 255, atol=1e-6)
    else:  # undistorted like OpenCV does it with the published coefficients
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        ref = cv2.undistort(img.astype(np.float32) / 255, K, np.array(dist))
        out = seq.image(0).permute(1, 2, 0).numpy()
        diff = np.abs(out - ref)[20:-20, 20:-20]
        assert diff.mean() < 1e-3 and diff.max() < 0.02
        assert np.abs(out - img / 255)[20:-20, 20:-20].mean() > 0.02  # the distortion is visible
    small = open_tum(tmp_path / folder, height=240, width=320)
    expected = resize_intrinsics(torch.tensor([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), (480, 640), (240, 320))
    assert small.load(1).shape == (3, 240, 320) and torch.allclose(small.K, expected)
    assert open_tum(tmp_path / folder, camera="fr3").K[0, 0] == pytest.approx(535.4)  # explicit choice wins


def test_camera_names_and_errors(tmp_path: Path, world: SyntheticWorld) -> None:
    assert tum_camera_from_name("rgbd_dataset_freiburg2_pioneer_360") == "fr2"
    assert tum_camera_from_name("fr3_walking_xyz") == "fr3"
    assert tum_camera_from_name("freiburg12") is None and tum_camera_from_name("office") is None
    img = pattern(480, 640)
    build_tum(tmp_path / "office", [img, img], None)
    with pytest.raises(ValueError, match=r"cannot tell the camera from 'auto' / the folder name 'office'"):
        open_tum(tmp_path / "office")
    with pytest.raises(DatasetNotFoundError, match="TUM RGB-D sequence: folder"):
        open_tum(tmp_path / "missing")
    (tmp_path / "office" / "groundtruth.txt").write_text("# ground truth\n1305031102.2 1 2 3 0 0 zero 1\n")
    with pytest.raises(DatasetError, match=r"^TUM ground truth: .*groundtruth.txt:2: non-numeric value"):
        open_tum(tmp_path / "office", camera="fr1")
    (tmp_path / "office" / "rgb.txt").write_text("1305031102.175304 rgb/none.png\n1305031102.2 rgb/none2.png\n")
    with pytest.raises(DatasetNotFoundError, match=r"names 2 missing files, first .*none.png"):
        open_tum(tmp_path / "office", camera="fr1")
