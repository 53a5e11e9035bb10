"""Optical-flow files: Middlebury ``.flo``, ``.pfm`` (FlyingThings3D) and KITTI 16-bit flow PNG; read and written.

Convention:
    - Flow is returned as ``(flow (2,H,W) float32, valid (1,H,W) bool)`` torch tensors in pixels (channel 0 = u,
      right; channel 1 = v, down), rows top to bottom; invalid pixels hold flow 0. Writers take ``(2,H,W)``
      flow (numpy or torch) and an optional ``(H,W)`` / ``(1,H,W)`` validity (all valid when omitted).
    - ``.flo`` (Middlebury): ``b"PIEH"`` (the float 202021.25), int32 width, int32 height, then ``H*W*2``
      little-endian float32 (u, v interleaved, row-major). Values above 1e9 in magnitude (or not finite) mark
      unknown flow (Middlebury's ``UNKNOWN_FLOW``); the writer stores invalid pixels as 1e10.
    - ``.pfm``: a text header ``PF`` (3 channels) or ``Pf`` (1 channel), ``width height``, and a scale whose
      sign gives the byte order (negative = little-endian), then float32 rows stored **bottom row first**.
      :func:`read_pfm` returns rows top to bottom. FlyingThings3D flow PFMs are 3-channel (u, v, 0).
    - KITTI flow PNG: 16-bit RGB, ``R = u*64 + 2^15``, ``G = v*64 + 2^15``, ``B = valid (0/1)``. The 16-bit
      PNG codec here is self-contained (zlib + numpy): Pillow reduces 16-bit RGB to 8 bits, OpenCV is optional.
"""

from __future__ import annotations

import re
import struct
import zlib
from pathlib import Path

import numpy as np
import torch

__all__ = ["FLO_UNKNOWN_THRESHOLD", "read_flo", "write_flo", "read_pfm", "write_pfm", "read_pfm_flow",
           "write_pfm_flow", "read_png16", "write_png16", "read_kitti_flow", "write_kitti_flow", "read_flow",
           "write_flow"]

FLO_MAGIC = 202021.25
FLO_UNKNOWN_THRESHOLD = 1e9
_FLO_UNKNOWN_VALUE = 1e10


def _require(path: str | Path, what: str) -> Path:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} {path} does not exist")
    return path


def _flow_array(flow: np.ndarray | torch.Tensor, what: str) -> np.ndarray:
    arr = np.asarray(flow.detach().cpu() if isinstance(flow, torch.Tensor) else flow, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[0] != 2:
        raise ValueError(f"{what} expects flow of shape (2,H,W), got {arr.shape}")
    return arr


def _valid_array(valid: np.ndarray | torch.Tensor | None, hw: tuple[int, int], what: str) -> np.ndarray:
    if valid is None:
        return np.ones(hw, bool)
    arr = np.asarray(valid.detach().cpu() if isinstance(valid, torch.Tensor) else valid)
    if arr.size != hw[0] * hw[1]:
        raise ValueError(f"{what}: valid must be (H,W) or (1,H,W) with H,W = {hw}, got {arr.shape}")
    return arr.reshape(hw).astype(bool)


def _as_tensors(flow_hw2: np.ndarray, valid: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    flow = np.where(valid[..., None], flow_hw2, 0.0).astype(np.float32)
    return torch.from_numpy(np.ascontiguousarray(flow.transpose(2, 0, 1))), torch.from_numpy(valid[None].copy())


# --------------------------------------------------------------------------------------------------- .flo
def read_flo(path: str | Path) -> tuple[torch.Tensor, torch.Tensor]:
    """Read a Middlebury ``.flo`` file: ``(flow (2,H,W) float32, valid (1,H,W) bool)`` (unknown flow invalid)."""
    path = _require(path, ".flo flow file")
    data = path.read_bytes()
    if len(data) < 12 or data[:4] != b"PIEH":
        raise ValueError(f"{path}: not a Middlebury .flo file (expected the tag 'PIEH' = {FLO_MAGIC} first)")
    w, h = struct.unpack("<ii", data[4:12])
    if w <= 0 or h <= 0 or len(data) != 12 + 8 * w * h:
        raise ValueError(f"{path}: .flo header says {w}x{h} (expects {12 + 8 * max(w, 0) * max(h, 0)} bytes), "
                         f"the file has {len(data)} bytes")
    flow = np.frombuffer(data, "<f4", count=2 * w * h, offset=12).reshape(h, w, 2).astype(np.float64)
    valid = np.isfinite(flow).all(-1) & (np.abs(flow) < FLO_UNKNOWN_THRESHOLD).all(-1)
    return _as_tensors(flow, valid)


def write_flo(path: str | Path, flow: np.ndarray | torch.Tensor,
              valid: np.ndarray | torch.Tensor | None = None) -> None:
    """Write ``(2,H,W)`` flow as a Middlebury ``.flo`` file; invalid pixels are stored as unknown (1e10)."""
    arr = _flow_array(flow, "write_flo")
    v = _valid_array(valid, arr.shape[1:], "write_flo")
    hw2 = np.where(v[..., None], arr.transpose(1, 2, 0), _FLO_UNKNOWN_VALUE).astype("<f4")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_bytes(b"PIEH" + struct.pack("<ii", arr.shape[2], arr.shape[1]) + hw2.tobytes())


# --------------------------------------------------------------------------------------------------- .pfm
_PFM_HEADER = re.compile(rb"^(PF|Pf)\s+(\d+)\s+(\d+)\s+([-+0-9.eE]+)\s")


def read_pfm(path: str | Path) -> np.ndarray:
    """Read a PFM file as float32, rows top to bottom: ``(H,W)`` for ``Pf``, ``(H,W,3)`` for ``PF``."""
    path = _require(path, "PFM file")
    data = path.read_bytes()
    m = _PFM_HEADER.match(data[:256])
    if m is None:
        raise ValueError(f"{path}: not a PFM file (expected a header 'PF' or 'Pf', 'width height', 'scale')")
    channels = 3 if m.group(1) == b"PF" else 1
    w, h, scale = int(m.group(2)), int(m.group(3)), float(m.group(4))
    if scale == 0:
        raise ValueError(f"{path}: PFM scale is 0 (its sign must give the byte order)")
    count = w * h * channels
    if len(data) - m.end() < 4 * count:
        raise ValueError(f"{path}: PFM header says {w}x{h}x{channels} float32, the file has "
                         f"{len(data) - m.end()} bytes of data")
    arr = np.frombuffer(data, "<f4" if scale < 0 else ">f4", count=count, offset=m.end())
    arr = arr.reshape((h, w, channels) if channels == 3 else (h, w))
    return np.ascontiguousarray(arr[::-1]).astype(np.float32)


def write_pfm(path: str | Path, data: np.ndarray | torch.Tensor, little_endian: bool = True) -> None:
    """Write an ``(H,W)`` or ``(H,W,3)`` array as a PFM file (rows stored bottom first, scale ``-1`` or ``1``)."""
    arr = np.asarray(data.detach().cpu() if isinstance(data, torch.Tensor) else data, dtype=np.float32)
    if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[2] != 3):
        raise ValueError(f"write_pfm expects an (H,W) or (H,W,3) array, got {arr.shape}")
    header = f"{'PF' if arr.ndim == 3 else 'Pf'}\n{arr.shape[1]} {arr.shape[0]}\n{-1 if little_endian else 1}\n"
    body = np.ascontiguousarray(arr[::-1]).astype("<f4" if little_endian else ">f4").tobytes()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_bytes(header.encode("ascii") + body)


def read_pfm_flow(path: str | Path) -> tuple[torch.Tensor, torch.Tensor]:
    """Read a flow PFM (FlyingThings3D: 3 channels u, v, 0): ``(flow (2,H,W), valid (1,H,W))`` (finite = valid)."""
    arr = read_pfm(path)
    if arr.ndim != 3:
        raise ValueError(f"{path}: a flow PFM needs 3 channels (u, v, 0; header 'PF'), this one has 1 ('Pf')")
    flow = arr[..., :2].astype(np.float64)
    return _as_tensors(flow, np.isfinite(flow).all(-1))


def write_pfm_flow(path: str | Path, flow: np.ndarray | torch.Tensor, little_endian: bool = True) -> None:
    """Write ``(2,H,W)`` flow as a 3-channel PFM (u, v, 0), the FlyingThings3D layout."""
    arr = _flow_array(flow, "write_pfm_flow")
    write_pfm(path, np.concatenate([arr, np.zeros_like(arr[:1])]).transpose(1, 2, 0), little_endian)


# ------------------------------------------------------------------------------------------ 16-bit PNG
def _chunk(tag: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)


def write_png16(path: str | Path, image: np.ndarray) -> None:
    """Write an ``(H,W,3)`` uint16 array as a 16-bit RGB PNG (no row filter, zlib level 6)."""
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint16:
        raise ValueError(f"write_png16 expects an (H,W,3) uint16 array, got {image.shape} {image.dtype}")
    h, w, _ = image.shape
    rows = np.ascontiguousarray(image.astype(">u2")).view(np.uint8).reshape(h, w * 6)
    raw = np.concatenate([np.zeros((h, 1), np.uint8), rows], axis=1).tobytes()
    header = struct.pack(">IIBBBBB", w, h, 16, 2, 0, 0, 0)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_bytes(b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", header) + _chunk(b"IDAT", zlib.compress(raw, 6))
                           + _chunk(b"IEND", b""))


def _unfilter_row(ftype: int, row: np.ndarray, prev: np.ndarray, bpp: int, where: str) -> np.ndarray:
    """Undo one PNG row filter (0 none, 1 sub, 2 up, 3 average, 4 Paeth) given the previous decoded row."""
    if ftype == 0:
        return row
    if ftype == 2:
        return (row.astype(np.uint16) + prev).astype(np.uint8)
    if ftype == 1:  # sub: a running sum per byte position within the pixel, modulo 256
        return (np.cumsum(row.reshape(-1, bpp).astype(np.uint64), axis=0) % 256).astype(np.uint8).reshape(-1)
    if ftype not in (3, 4):
        raise ValueError(f"{where}: unknown PNG filter type {ftype}")
    out = bytearray(row.tobytes())
    up = prev.tobytes()
    for i in range(len(out)):  # average and Paeth depend on the decoded left neighbour: sequential
        a = out[i - bpp] if i >= bpp else 0
        if ftype == 3:
            out[i] = (out[i] + ((a + up[i]) >> 1)) & 0xFF
        else:
            b, c = up[i], (up[i - bpp] if i >= bpp else 0)
            p = a + b - c
            pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
            out[i] = (out[i] + (a if pa <= pb and pa <= pc else b if pb <= pc else c)) & 0xFF
    return np.frombuffer(bytes(out), np.uint8)


def read_png16(path: str | Path) -> np.ndarray:
    """Read a non-interlaced 16-bit RGB PNG into an ``(H,W,3)`` uint16 array."""
    path = _require(path, "flow PNG")
    data = path.read_bytes()
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError(f"{path}: not a PNG file")
    pos, idat, header = 8, [], None
    while pos + 8 <= len(data):
        (length,) = struct.unpack(">I", data[pos:pos + 4])
        tag, body = data[pos + 4:pos + 8], data[pos + 8:pos + 8 + length]
        pos += 12 + length
        if tag == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif tag == b"IDAT":
            idat.append(body)
        elif tag == b"IEND":
            break
    if header is None:
        raise ValueError(f"{path}: PNG without IHDR")
    w, h, depth, color, _, _, interlace = header
    if depth != 16 or color != 2 or interlace != 0:
        raise ValueError(f"{path}: expected a 16-bit RGB non-interlaced PNG (KITTI flow format), got bit depth "
                         f"{depth}, colour type {color}, interlace {interlace}")
    try:
        raw = np.frombuffer(zlib.decompress(b"".join(idat)), np.uint8).reshape(h, 1 + w * 6)
    except (zlib.error, ValueError) as err:
        raise ValueError(f"{path}: truncated or corrupt PNG image data ({err})") from err
    prev = np.zeros(w * 6, np.uint8)
    rows = np.empty((h, w * 6), np.uint8)
    for y in range(h):
        prev = rows[y] = _unfilter_row(int(raw[y, 0]), raw[y, 1:], prev, 6, f"{path} row {y}")
    return rows.view(">u2").reshape(h, w, 3).astype(np.uint16)


def write_kitti_flow(path: str | Path, flow: np.ndarray | torch.Tensor,
                     valid: np.ndarray | torch.Tensor | None = None) -> None:
    """Write ``(2,H,W)`` flow (and optional ``(H,W)``/``(1,H,W)`` validity) as a KITTI 16-bit flow PNG.

    Values are rounded to 1/64 px and clipped to the format's range (about ±512 px)."""
    arr = _flow_array(flow, "write_kitti_flow")
    v = _valid_array(valid, arr.shape[1:], "write_kitti_flow")
    enc = np.clip(np.round(np.nan_to_num(arr) * 64.0 + 2**15), 0, 2**16 - 1).astype(np.uint16)
    write_png16(path, np.stack([enc[0], enc[1], v.astype(np.uint16)], axis=-1))


def read_kitti_flow(path: str | Path) -> tuple[torch.Tensor, torch.Tensor]:
    """Read a KITTI flow PNG: ``(flow (2,H,W) float32 px, valid (1,H,W) bool)``; invalid pixels get flow 0."""
    img = read_png16(path).astype(np.float64)
    return _as_tensors((img[..., :2] - 2**15) / 64.0, img[..., 2] > 0)


# ------------------------------------------------------------------------------------------- dispatch
_READERS = {".flo": read_flo, ".pfm": read_pfm_flow, ".png": read_kitti_flow}


def read_flow(path: str | Path) -> tuple[torch.Tensor, torch.Tensor]:
    """Read a flow file by its suffix (``.flo``, ``.pfm``, ``.png`` = KITTI): ``(flow (2,H,W), valid (1,H,W))``."""
    suffix = Path(path).suffix.lower()
    if suffix not in _READERS:
        raise ValueError(f"{path}: unknown flow file type {suffix!r}; expected one of {sorted(_READERS)}")
    return _READERS[suffix](path)


def write_flow(path: str | Path, flow: np.ndarray | torch.Tensor,
               valid: np.ndarray | torch.Tensor | None = None) -> None:
    """Write ``(2,H,W)`` flow by the suffix of ``path`` (``.flo``, ``.pfm``, ``.png`` = KITTI).

    ``.pfm`` has no validity channel: invalid pixels are written as NaN (read back as invalid)."""
    suffix = Path(path).suffix.lower()
    if suffix == ".flo":
        write_flo(path, flow, valid)
    elif suffix == ".png":
        write_kitti_flow(path, flow, valid)
    elif suffix == ".pfm":
        arr = _flow_array(flow, "write_flow")
        v = _valid_array(valid, arr.shape[1:], "write_flow")
        write_pfm_flow(path, np.where(v[None], arr, np.nan))
    else:
        raise ValueError(f"{path}: unknown flow file type {suffix!r}; expected one of {sorted(_READERS)}")
