"""Image-folder dataset: undistortion (vs OpenCV and a hand-built distortion), exact K under resize/crop, errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from dfvo.data.image_folder import ImageFolder, Undistorter
from dfvo.data.image_io import DatasetError, DatasetNotFoundError
from dfvo.data.transforms import crop_with_intrinsics, resize_with_intrinsics
from dfvo.geometry.camera import intrinsics_matrix, project_points

cv2 = pytest.importorskip("cv2", reason="OpenCV (test-only reference) not installed")

H, W = 375, 1242
K_NATIVE = intrinsics_matrix(721.5, 718.0, 609.3, 172.8)[0].double()
POINT = torch.tensor([[[2.3, -0.7, 11.0]]], dtype=torch.float64)  # camera frame, metres


def blob(h: int, w: int, u: float, v: float, sigma: float) -> torch.Tensor:
    """(3,h,w) Gaussian blob centred at continuous pixel (u, v)."""
    y, x = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    g = torch.exp(-((x - u) ** 2 + (y - v) ** 2) / (2 * sigma**2))
    return g.expand(3, h, w).clone()


def centroid(image: torch.Tensor) -> tuple[float, float]:
    img = image[0].double()
    y, x = torch.meshgrid(torch.arange(img.shape[0], dtype=torch.float64),
                          torch.arange(img.shape[1], dtype=torch.float64), indexing="ij")
    return float((img * x).sum() / img.sum()), float((img * y).sum() / img.sum())


def project(K: torch.Tensor) -> tuple[float, float]:
    uv, _ = project_points(POINT, K[None].double())
    return float(uv[0, 0, 0]), float(uv[0, 0, 1])


# ---------------------------------------------------------------- resize / crop keep the projection


def test_resize_keeps_projection_on_blob() -> None:
    u, v = project(K_NATIVE)
    image = blob(H, W, u, v, sigma=9.0)
    small, K_small = resize_with_intrinsics(image, K_NATIVE, 192, 640)
    assert small.shape == (3, 192, 640)
    cu, cv = centroid(small)
    pu, pv = project(K_small)
    assert abs(cu - pu) < 0.02 and abs(cv - pv) < 0.02
    # the "scale cx by s" convention misses the blob by (s - 1) / 2 pixels: the test can tell them apart
    naive_cu = K_NATIVE[0, 0] * POINT[0, 0, 0] / POINT[0, 0, 2] * 640 / W + K_NATIVE[0, 2] * 640 / W
    assert abs(cu - float(naive_cu)) > 0.2


def test_crop_keeps_projection_on_blob() -> None:
    u, v = project(K_NATIVE)
    image = blob(H, W, u, v, sigma=5.0)
    crop, K_crop = crop_with_intrinsics(image, K_NATIVE, top=100, left=700, height=200, width=400)
    assert crop.shape == (3, 200, 400)
    cu, cv = centroid(crop)
    pu, pv = project(K_crop)
    assert abs(cu - pu) < 1e-6 and abs(cv - pv) < 1e-6
    batched, K_b = crop_with_intrinsics(image[None], K_NATIVE[None], 100, 700, 200, 400)
    assert batched.shape == (1, 3, 200, 400) and torch.equal(K_b[0], K_crop)
    with pytest.raises(ValueError, match="do not fit"):
        crop_with_intrinsics(image, K_NATIVE, 300, 0, 100, 100)


def test_image_folder_resize_end_to_end(tmp_path: Path) -> None:
    u, v = project(K_NATIVE)
    arr = (blob(H, W, u, v, sigma=9.0)[0].numpy() * 65535).round().astype(np.uint16)
    Image.fromarray(arr).save(tmp_path / "000.png")
    fx, fy, cx, cy = (float(K_NATIVE[0, 0]), float(K_NATIVE[1, 1]), float(K_NATIVE[0, 2]), float(K_NATIVE[1, 2]))
    ds = ImageFolder(tmp_path, fx, fy, cx, cy, height=192, width=640)
    s = ds[0]
    assert s["image"].shape == (3, 192, 640) and s["K"].shape == (3, 3)
    cu, cv = centroid(s["image"])
    pu, pv = project(s["K"])
    assert abs(cu - pu) < 0.02 and abs(cv - pv) < 0.02


# ---------------------------------------------------------------- undistortion


def _pattern(h: int, w: int) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    return np.stack([0.5 + 0.5 * np.sin(x / 7 + y / 11), 0.5 + 0.5 * np.cos(x / 5 - y / 9),
                     0.5 + 0.5 * np.sin((x + y) / 13)], -1).astype(np.float32)


@pytest.mark.parametrize("dist", [[-0.3, 0.12, 0.001, -0.002], [-0.3, 0.12, 0.001, -0.002, -0.02],
                                  [-0.3, 0.12, 0.001, -0.002, -0.02, 0.05, -0.01, 0.003]])
def test_undistortion_matches_opencv(dist: list[float]) -> None:
    h, w = 240, 320
    img = _pattern(h, w)
    K = np.array([[250.0, 0, 161.3], [0, 245.0, 118.7], [0, 0, 1]])
    ref = cv2.undistort(img, K, np.array(dist))
    out = Undistorter(torch.tensor(K), dist, h, w)(torch.from_numpy(img).permute(2, 0, 1)).permute(1, 2, 0).numpy()
    inner = np.s_[10:-10, 10:-10]
    diff = np.abs(out - ref)[inner]
    assert diff.max() < 0.01 and diff.mean() < 1e-3  # OpenCV interpolates in fixed point (1/32 px)
    assert np.abs(out - img)[inner].mean() > 0.05  # the distortion is strong enough to matter


def test_undistortion_moves_blob_to_pinhole_projection(tmp_path: Path) -> None:
    # hand-built distortion: a point at normalised (x, y) appears at K * distort(x, y); undistorting must bring
    # the blob back to K * (x, y)
    h, w = 200, 300
    fx, fy, cx, cy = 220.0, 220.0, 150.0, 100.0
    k1, k2, p1, p2 = -0.25, 0.05, 0.002, -0.001
    x, y = 0.35, -0.2
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    img = blob(h, w, fx * xd + cx, fy * yd + cy, sigma=2.0)
    Image.fromarray((img.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)).save(tmp_path / "a.png")
    ds = ImageFolder(tmp_path, fx, fy, cx, cy, dist=[k1, k2, p1, p2])
    cu, cv = centroid(ds[0]["image"])
    assert abs(cu - (fx * x + cx)) < 0.15 and abs(cv - (fy * y + cy)) < 0.15
    # without undistortion the blob stays where the lens put it, pixels away
    cu0, _ = centroid(ImageFolder(tmp_path, fx, fy, cx, cy)[0]["image"])
    assert abs(cu0 - (fx * x + cx)) > 3.0


# ---------------------------------------------------------------- folder handling and errors


def test_natural_order_and_dataloader(tmp_path: Path) -> None:
    for i in (1, 2, 10):
        Image.fromarray(np.full((8, 12, 3), i, np.uint8)).save(tmp_path / f"frame{i}.jpg", quality=100)
    ds = ImageFolder(tmp_path, 10.0, 10.0, 6.0, 4.0)
    assert [p.name for p in ds.files] == ["frame1.jpg", "frame2.jpg", "frame10.jpg"]
    assert round(float(ds[2]["image"].mean()) * 255) == 10
    assert int(ds[2]["index"]) == 2


def test_errors(tmp_path: Path) -> None:
    with pytest.raises(DatasetNotFoundError, match="missing"):
        ImageFolder(tmp_path / "missing", 1.0, 1.0, 0.0, 0.0)
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(DatasetError, match="contains no images"):
        ImageFolder(tmp_path, 1.0, 1.0, 0.0, 0.0)
    Image.fromarray(np.zeros((8, 12, 3), np.uint8)).save(tmp_path / "a.png")
    with pytest.raises(ValueError, match="k1, k2, p1, p2"):
        ImageFolder(tmp_path, 10.0, 10.0, 6.0, 4.0, dist=[0.1, 0.2, 0.3])
    with pytest.raises(ValueError, match=r"data.fx=0 .* must be positive"):
        ImageFolder(tmp_path, 0.0, 10.0, 6.0, 4.0)
    with pytest.raises(ValueError, match="height and width"):
        ImageFolder(tmp_path, 10.0, 10.0, 6.0, 4.0, width=64)
    Image.fromarray(np.zeros((9, 12, 3), np.uint8)).save(tmp_path / "b.png")
    with pytest.raises(DatasetError, match=r"b.png is 9x12, expected 8x12"):
        ImageFolder(tmp_path, 10.0, 10.0, 6.0, 4.0)[1]
    (tmp_path / "c.png").write_bytes(b"\x89PNG broken")
    with pytest.raises(DatasetError, match="c.png"):
        ImageFolder(tmp_path, 10.0, 10.0, 6.0, 4.0)[2]


def test_intrinsics_checked_against_the_stored_frames(tmp_path: Path) -> None:
    # issue 16: data.cx=3670 on a 752-px-wide image ran to exit 0; now one line names the setting
    Image.fromarray(np.zeros((480, 752), np.uint8)).save(tmp_path / "0.png")
    with pytest.raises(ValueError, match=r"^data.cx=3670 .*outside the 752-px-wide image.*expected 0 < cx < 752"):
        ImageFolder(tmp_path, 458.7, 457.3, 3670.0, 248.4)
    with pytest.raises(ValueError, match=r"data.cy=-3 .*outside the 480-px-high image"):
        ImageFolder(tmp_path, 458.7, 457.3, 367.2, -3.0)
    with pytest.raises(ValueError, match=r"data.fx=4.2 .*field of view"):  # a focal length in millimetres
        ImageFolder(tmp_path, 4.2, 4.2, 367.2, 248.4)
    ds = ImageFolder(tmp_path, 458.7, 457.3, 367.2, 248.4, dist=[0.0, 0.0, 0.0, 0.0])
    assert ds.undistort is None  # all-zero distortion: nothing to undo
