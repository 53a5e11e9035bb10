"""Flow metrics, KITTI flow PNG format (checked against OpenCV as a reference), Eigen depth metrics."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from dfvo.eval import compute_depth_metrics, compute_flow_metrics, read_kitti_flow, read_png16, write_kitti_flow


def test_flow_metrics_hand_values() -> None:
    gt = torch.zeros(1, 2, 1, 4)
    pred = torch.zeros(1, 2, 1, 4)
    pred[0, 0, 0] = torch.tensor([0.5, 2.0, 4.0, 10.0])
    m = compute_flow_metrics(pred, gt)
    assert m["aepe"] == pytest.approx(16.5 / 4)
    assert m["out_1"] == pytest.approx(75.0) and m["out_3"] == pytest.approx(50.0) and m["out_5"] == pytest.approx(25.0)
    assert m["fl"] == pytest.approx(50.0) and m["num_pixels"] == 4
    # Fl needs both > 3 px and > 5 % of |gt|: with |gt| = 100 px an error of 4 px is not an outlier.
    gt2 = torch.zeros(1, 2, 1, 4)
    gt2[0, 1] = 100.0
    pred2 = gt2.clone()
    pred2[0, 0, 0] = torch.tensor([0.5, 2.0, 4.0, 10.0])
    assert compute_flow_metrics(pred2, gt2)["fl"] == pytest.approx(25.0)
    valid = torch.tensor([True, True, False, False]).view(1, 1, 1, 4)
    assert compute_flow_metrics(pred, gt, valid)["aepe"] == pytest.approx(1.25)
    with pytest.raises(ValueError, match="no pixel"):
        compute_flow_metrics(pred, gt, torch.zeros_like(valid))


def test_flow_png_round_trip(tmp_path: Path) -> None:
    g = torch.Generator().manual_seed(0)
    flow = torch.round((torch.rand(2, 13, 21, generator=g) * 400 - 200) * 64) / 64
    valid = torch.rand(1, 13, 21, generator=g) > 0.3
    write_kitti_flow(tmp_path / "f.png", flow, valid)
    back, v = read_kitti_flow(tmp_path / "f.png")
    assert torch.equal(v, valid)
    assert torch.equal(back[:, valid[0]], flow[:, valid[0]])
    assert torch.all(back[:, ~valid[0]] == 0)


def test_flow_png_matches_opencv(tmp_path: Path) -> None:
    cv2 = pytest.importorskip("cv2")
    rng = np.random.default_rng(1)
    bgr = rng.integers(0, 2**16, size=(17, 29, 3), dtype=np.uint16)
    bgr[..., 0] = rng.integers(0, 2, size=(17, 29))
    cv2.imwrite(str(tmp_path / "cv.png"), bgr)  # libpng picks adaptive row filters: exercises the decoder
    assert np.array_equal(read_png16(tmp_path / "cv.png"), bgr[..., ::-1])
    flow = np.stack([np.full((5, 6), -3.25), np.full((5, 6), 10.5)])
    write_kitti_flow(tmp_path / "mine.png", flow)
    raw = cv2.imread(str(tmp_path / "mine.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16
    assert np.all(raw[..., 2] == 2**15 - 208) and np.all(raw[..., 1] == 2**15 + 672) and np.all(raw[..., 0] == 1)


def test_flow_png_rejects_8bit(tmp_path: Path) -> None:
    from PIL import Image

    Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(tmp_path / "x.png")
    with pytest.raises(ValueError, match="x.png.*16-bit"):
        read_kitti_flow(tmp_path / "x.png")


def test_depth_metrics_hand_values() -> None:
    gt = torch.tensor([1.0, 2.0, 4.0]).view(1, 1, 1, 3)
    pred = torch.tensor([2.0, 2.0, 2.0]).view(1, 1, 1, 3)
    m = compute_depth_metrics(pred, gt, median_scaling=False)
    assert m["abs_rel"] == pytest.approx(0.5)
    assert m["sq_rel"] == pytest.approx(2.0 / 3.0)
    assert m["rmse"] == pytest.approx(math.sqrt(5.0 / 3.0))
    assert m["rmse_log"] == pytest.approx(math.sqrt(2 * math.log(2) ** 2 / 3))
    assert m["a1"] == pytest.approx(1 / 3) and m["a2"] == pytest.approx(1 / 3) and m["a3"] == pytest.approx(1 / 3)
    assert m["scale"] == 1.0


def test_depth_median_scaling_and_caps() -> None:
    gt = torch.tensor([[1.0, 2.0, 4.0, 0.0, 100.0]]).view(1, 1, 1, 5)
    pred = gt * 0.5
    m = compute_depth_metrics(pred, gt, max_depth=80.0, median_scaling=True)
    assert m["scale"] == pytest.approx(2.0)  # medians over valid pixels only (0 and 100 m excluded)
    assert m["abs_rel"] == pytest.approx(0.0, abs=1e-12) and m["a1"] == 1.0
    # Predictions are clamped to max_depth: 200 m against 10 m GT counts as 20 m, |20-10|/10 = 1.
    gt2 = torch.tensor([10.0, 10.0]).view(1, 1, 1, 2)
    pred2 = torch.tensor([200.0, 10.0]).view(1, 1, 1, 2)
    m2 = compute_depth_metrics(pred2, gt2, max_depth=20.0, median_scaling=False)
    assert m2["abs_rel"] == pytest.approx((10.0 / 10.0) / 2)
    with pytest.raises(ValueError, match="no image"):
        compute_depth_metrics(pred2, gt2 * 0, median_scaling=False)
    with pytest.raises(ValueError, match=r"\(B,1,H,W\)"):
        compute_depth_metrics(pred2[0], gt2[0])


def _paeth(a: int, b: int, c: int) -> int:
    p = a + b - c
    pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
    return a if pa <= pb and pa <= pc else b if pb <= pc else c


def test_png_decoder_handles_all_row_filters(tmp_path: Path) -> None:
    """Encode each row with a different PNG filter (0-4) by a direct loop; the decoder must invert them."""
    import struct
    import zlib

    rng = np.random.default_rng(4)
    img = rng.integers(0, 2**16, size=(10, 7, 3), dtype=np.uint16)
    rows = np.ascontiguousarray(img.astype(">u2")).view(np.uint8).reshape(10, 42).astype(int)
    raw = bytearray()
    for y in range(10):
        ftype, cur = y % 5, rows[y]
        prev = rows[y - 1] if y > 0 else np.zeros(42, int)
        raw.append(ftype)
        for i in range(42):
            a, b, c = (cur[i - 6] if i >= 6 else 0), prev[i], (prev[i - 6] if i >= 6 else 0)
            pred = [0, a, b, (a + b) // 2, _paeth(a, b, c)][ftype]
            raw.append((cur[i] - pred) % 256)

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))

    header = chunk(b"IHDR", struct.pack(">IIBBBBB", 7, 10, 16, 2, 0, 0, 0))
    body = chunk(b"IDAT", zlib.compress(bytes(raw))) + chunk(b"IEND", b"")
    (tmp_path / "f.png").write_bytes(b"\x89PNG\r\n\x1a\n" + header + body)
    assert np.array_equal(read_png16(tmp_path / "f.png"), img)
