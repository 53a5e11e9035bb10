"""Flow files (.flo, .pfm, KITTI 16-bit PNG) on the real samples of ../shared/data/flow_samples and round trips.

Pinned values were decoded by hand (``struct`` on the raw bytes, OpenCV on the PNG) and are re-derived here the
same independent way where possible.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch

from dfvo.data.flow_io import (
    read_flo,
    read_flow,
    read_kitti_flow,
    read_pfm,
    read_pfm_flow,
    read_png16,
    write_flo,
    write_flow,
    write_kitti_flow,
    write_pfm,
    write_pfm_flow,
)

SAMPLES = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "flow_samples"


def _sample(rel: str) -> Path:
    path = SAMPLES / rel
    if not path.exists():
        pytest.skip(f"needs {path} (the project's ../shared data folder); not present on this machine")
    return path


def _flo_raw(path: Path, y: int, x: int) -> tuple[float, float]:
    data = path.read_bytes()
    w = struct.unpack("<i", data[4:8])[0]
    return struct.unpack("<ff", data[12 + 8 * (y * w + x): 20 + 8 * (y * w + x)])


# ----------------------------------------------------------------------------------------------------- .flo
def test_flyingchairs_flo_values_and_byte_exact_round_trip(tmp_path: Path) -> None:
    path = _sample("FlyingChairs_release/data/00001_flow.flo")
    flow, valid = read_flo(path)
    assert flow.shape == (2, 384, 512) and flow.dtype == torch.float32 and bool(valid.all())
    # hand-decoded: top-left corner, the static background, and the fastest chair pixel
    assert flow[:, 0, 0].tolist() == [-19.5, 13.75]
    assert flow[:, 383, 511].tolist() == [-0.59375, -1.34375]
    assert flow[:, 359, 114].tolist() == [-75.65625, 18.75]
    for y, x in [(0, 0), (17, 400), (359, 114)]:
        assert flow[:, y, x].tolist() == list(_flo_raw(path, y, x))
    write_flo(tmp_path / "f.flo", flow, valid)
    assert (tmp_path / "f.flo").read_bytes() == path.read_bytes()


def test_middlebury_unknown_flow_is_invalid(tmp_path: Path) -> None:
    path = _sample("middlebury/RubberWhale_flow10.flo")
    flow, valid = read_flo(path)
    assert flow.shape == (2, 388, 584)
    raw = np.frombuffer(path.read_bytes(), "<f4", offset=12).reshape(388, 584, 2)
    unknown = (np.abs(raw) > 1e9).any(-1)
    assert unknown.sum() == 3622 and np.array_equal(~valid[0].numpy(), unknown)
    assert _flo_raw(path, 0, 0)[0] > 1e9 and not bool(valid[0, 0, 0])
    assert flow[:, 100, 100].tolist() == pytest.approx([0.5221473, -0.1286633], abs=1e-7)
    assert torch.all(flow[:, ~valid[0]] == 0)
    write_flo(tmp_path / "r.flo", flow, valid)
    back, v2 = read_flo(tmp_path / "r.flo")
    assert torch.equal(v2, valid) and torch.equal(back, flow)


def test_toolbox_flo_values() -> None:
    path = _sample("pfm/0000000-flow_01.flo")
    flow, valid = read_flo(path)
    assert flow.shape == (2, 50, 50) and bool(valid.all())
    assert flow[:, 10, 10].tolist() == [0.28125, -0.15625]
    assert flow[:, 49, 49].tolist() == [-18.84375, 13.5]


def test_flo_rejects_bad_files(tmp_path: Path) -> None:
    (tmp_path / "x.flo").write_bytes(b"PIEH" + struct.pack("<ii", 4, 3) + b"\0" * 10)
    with pytest.raises(ValueError, match=r"x\.flo.*4x3"):
        read_flo(tmp_path / "x.flo")
    (tmp_path / "y.flo").write_bytes(b"junkjunkjunk")
    with pytest.raises(ValueError, match=r"y\.flo.*PIEH"):
        read_flo(tmp_path / "y.flo")
    with pytest.raises(FileNotFoundError, match="nope.flo"):
        read_flo(tmp_path / "nope.flo")


# ----------------------------------------------------------------------------------------------------- .pfm
def test_toolbox_pfm_orientation_and_byte_exact_round_trip(tmp_path: Path) -> None:
    path = _sample("pfm/0000000-occ_weights_01.pfm")
    occ = read_pfm(path)
    assert occ.shape == (50, 50) and occ.dtype == np.float32 and set(np.unique(occ)) == {0.0, 1.0}
    assert int(occ.sum()) == 88
    # top-down rows: a vertical run in column 24 at the top, a horizontal run in row 11
    assert np.all(occ[0:7, 24] == 1) and occ[7, 24] == 0 and np.all(occ[11, 33:48] == 1)
    # the occluded pixels are where the toolbox's flow is zero: 83 of 88 in this orientation, 41 flipped
    flow, _ = read_flo(_sample("pfm/0000000-flow_01.flo"))
    zero = (flow == 0).all(0).numpy()
    assert (zero & (occ > 0)).sum() == 83 and (zero & (occ[::-1] > 0)).sum() == 41
    write_pfm(tmp_path / "o.pfm", occ)
    assert (tmp_path / "o.pfm").read_bytes() == path.read_bytes()


@pytest.mark.parametrize("little_endian", [True, False])
@pytest.mark.parametrize("channels", [1, 3])
def test_pfm_round_trip_against_a_manual_decoder(tmp_path: Path, little_endian: bool, channels: int) -> None:
    rng = np.random.default_rng(channels)
    arr = rng.normal(size=(5, 7, 3) if channels == 3 else (5, 7)).astype(np.float32)
    write_pfm(tmp_path / "a.pfm", arr, little_endian=little_endian)
    data = (tmp_path / "a.pfm").read_bytes()
    magic, dims, scale, body = data.split(b"\n", 3)
    assert magic == (b"PF" if channels == 3 else b"Pf") and dims == b"7 5" and (float(scale) < 0) == little_endian
    manual = np.frombuffer(body, "<f4" if little_endian else ">f4").reshape(arr.shape)[::-1]  # stored bottom-up
    assert np.array_equal(manual, arr)
    assert np.array_equal(read_pfm(tmp_path / "a.pfm"), arr)


def test_pfm_big_endian_written_by_hand(tmp_path: Path) -> None:
    rows_bottom_up = np.array([[[1, 2, 0], [3, 4, 0]], [[5, 6, 0], [7, 8, 0]]], ">f4")  # 2x2x3
    (tmp_path / "b.pfm").write_bytes(b"PF\n2 2\n1.0\n" + rows_bottom_up.tobytes())
    flow, valid = read_pfm_flow(tmp_path / "b.pfm")
    assert flow[:, 0, 0].tolist() == [5, 6] and flow[:, 1, 1].tolist() == [3, 4] and bool(valid.all())
    with pytest.raises(ValueError, match="3 channels"):
        write_pfm(tmp_path / "g.pfm", np.zeros((2, 2), np.float32))
        read_pfm_flow(tmp_path / "g.pfm")
    (tmp_path / "t.pfm").write_bytes(b"PF\n20 20\n-1\n" + b"\0" * 8)
    with pytest.raises(ValueError, match=r"t\.pfm.*20x20x3"):
        read_pfm(tmp_path / "t.pfm")


def test_flow_pfm_round_trip(tmp_path: Path) -> None:
    flow = torch.randn(2, 6, 9) * 30
    write_pfm_flow(tmp_path / "f.pfm", flow, little_endian=False)
    back, valid = read_pfm_flow(tmp_path / "f.pfm")
    assert torch.equal(back, flow) and bool(valid.all())
    assert np.all(read_pfm(tmp_path / "f.pfm")[..., 2] == 0)


# ------------------------------------------------------------------------------------------- KITTI PNG
def test_kitti_png_values_against_opencv() -> None:
    cv2 = pytest.importorskip("cv2")
    path = _sample("kitti_flow/training/flow_occ/000000_10.png")
    flow, valid = read_kitti_flow(path)
    assert flow.shape == (2, 375, 1242) and valid.shape == (1, 375, 1242)
    assert int(valid.sum()) == 75453
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)  # BGR: B = valid, G = v, R = u
    assert raw[247, 231].tolist() == [1, 34808, 22319]
    assert flow[:, 247, 231].tolist() == [(22319 - 2**15) / 64, (34808 - 2**15) / 64] == [-163.265625, 31.875]
    assert not bool(valid[0, 0, 0]) and flow[:, 0, 0].tolist() == [0.0, 0.0]
    ref_valid = raw[..., 0] > 0
    ref = (raw[..., [2, 1]].astype(np.float64) - 2**15) / 64
    assert np.array_equal(valid[0].numpy(), ref_valid)
    assert np.array_equal(flow.permute(1, 2, 0).numpy()[ref_valid], ref[ref_valid])


def test_kitti_png_round_trip(tmp_path: Path) -> None:
    path = _sample("kitti_flow/training/flow_occ/000000_10.png")
    flow, valid = read_kitti_flow(path)
    write_kitti_flow(tmp_path / "k.png", flow, valid)
    assert np.array_equal(read_png16(tmp_path / "k.png"), read_png16(path))
    g = torch.Generator().manual_seed(0)
    f = torch.round((torch.rand(2, 13, 21, generator=g) * 400 - 200) * 64) / 64
    v = torch.rand(1, 13, 21, generator=g) > 0.3
    write_kitti_flow(tmp_path / "f.png", f, v)
    back, v2 = read_kitti_flow(tmp_path / "f.png")
    assert torch.equal(v2, v) and torch.equal(back[:, v[0]], f[:, v[0]]) and torch.all(back[:, ~v[0]] == 0)


def test_png_matches_opencv_and_rejects_8bit(tmp_path: Path) -> None:
    cv2 = pytest.importorskip("cv2")
    rng = np.random.default_rng(1)
    bgr = rng.integers(0, 2**16, size=(17, 29, 3), dtype=np.uint16)
    cv2.imwrite(str(tmp_path / "cv.png"), bgr)  # libpng picks adaptive row filters: exercises the decoder
    assert np.array_equal(read_png16(tmp_path / "cv.png"), bgr[..., ::-1])
    write_kitti_flow(tmp_path / "mine.png", np.stack([np.full((5, 6), -3.25), np.full((5, 6), 10.5)]))
    raw = cv2.imread(str(tmp_path / "mine.png"), cv2.IMREAD_UNCHANGED)
    assert np.all(raw[..., 2] == 2**15 - 208) and np.all(raw[..., 1] == 2**15 + 672) and np.all(raw[..., 0] == 1)
    cv2.imwrite(str(tmp_path / "x.png"), np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(ValueError, match=r"x\.png.*16-bit"):
        read_kitti_flow(tmp_path / "x.png")


def _paeth(a: int, b: int, c: int) -> int:
    p = a + b - c
    pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
    return a if pa <= pb and pa <= pc else b if pb <= pc else c


def test_png_decoder_handles_all_row_filters(tmp_path: Path) -> None:
    """Encode each row with a different PNG filter (0-4) by a direct loop; the decoder must invert them."""
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
            raw.append((cur[i] - [0, a, b, (a + b) // 2, _paeth(a, b, c)][ftype]) % 256)

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))

    header = chunk(b"IHDR", struct.pack(">IIBBBBB", 7, 10, 16, 2, 0, 0, 0))
    (tmp_path / "f.png").write_bytes(b"\x89PNG\r\n\x1a\n" + header + chunk(b"IDAT", zlib.compress(bytes(raw)))
                                     + chunk(b"IEND", b""))
    assert np.array_equal(read_png16(tmp_path / "f.png"), img)


# ------------------------------------------------------------------------------------------- dispatch
@pytest.mark.parametrize("suffix", [".flo", ".pfm", ".png"])
def test_read_write_flow_by_suffix(tmp_path: Path, suffix: str) -> None:
    flow = torch.round(torch.randn(2, 4, 5) * 64) / 64 * 10
    valid = torch.ones(1, 4, 5, dtype=torch.bool)
    valid[0, 1, 2] = False
    write_flow(tmp_path / f"f{suffix}", flow, valid)
    back, v = read_flow(tmp_path / f"f{suffix}")
    assert torch.equal(v, valid) and torch.equal(back[:, valid[0]], flow[:, valid[0]])
    with pytest.raises(ValueError, match="unknown flow file type"):
        read_flow(tmp_path / "f.txt")
