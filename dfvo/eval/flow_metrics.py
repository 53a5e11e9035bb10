"""Optical-flow metrics (AEPE, Out-N, KITTI Fl) and KITTI's 16-bit flow PNG format.

Convention:
    Flow ``(B,2,H,W)`` or ``(2,H,W)`` in pixels (u right, v down); a validity mask of the same leading shape
    with one channel (``(B,1,H,W)`` / ``(1,H,W)``) or none (all valid). KITTI flow PNG: 16-bit RGB,
    ``R = u*64 + 2^15``, ``G = v*64 + 2^15``, ``B = valid (0/1)``. The PNG codec here is self-contained
    (zlib + numpy) so no extra dependency is needed.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np
import torch


def _epe_and_mag(flow_pred: torch.Tensor, flow_gt: torch.Tensor, valid: torch.Tensor | None):
    if flow_pred.shape != flow_gt.shape or flow_pred.dim() not in (3, 4) or flow_pred.shape[-3] != 2:
        raise ValueError(f"flows must both be (B,2,H,W) or (2,H,W), got {tuple(flow_pred.shape)} and "
                         f"{tuple(flow_gt.shape)}")
    epe = torch.linalg.vector_norm(flow_pred.double() - flow_gt.double(), dim=-3)
    mag = torch.linalg.vector_norm(flow_gt.double(), dim=-3)
    if valid is None:
        mask = torch.ones_like(epe, dtype=torch.bool)
    else:
        if valid.shape[-3] != 1 or valid.shape[:-3] + valid.shape[-2:] != epe.shape:
            raise ValueError(f"valid must be {tuple(epe.shape[:-2])}+(1,)+{tuple(epe.shape[-2:])}, got "
                             f"{tuple(valid.shape)}")
        mask = valid.squeeze(-3).bool()
    if not bool(mask.any()):
        raise ValueError("flow metrics: the validity mask selects no pixel")
    return epe[mask], mag[mask]


def compute_flow_metrics(flow_pred: torch.Tensor, flow_gt: torch.Tensor, valid: torch.Tensor | None = None,
                 thresholds: tuple[float, ...] = (1.0, 3.0, 5.0)) -> dict[str, float]:
    """AEPE, Out-N and KITTI Fl over the valid pixels of all images together.

    Returns:
        ``{"aepe", "out_<N>" (% of pixels with EPE > N px) for each threshold, "fl" (% of pixels with
        EPE > 3 px and EPE > 5 % of |flow_gt|), "num_pixels"}``.
    """
    epe, mag = _epe_and_mag(flow_pred, flow_gt, valid)
    out = {"aepe": float(epe.mean())}
    for t in thresholds:
        out[f"out_{t:g}"] = float((epe > t).double().mean() * 100)
    out["fl"] = float(((epe > 3.0) & (epe > 0.05 * mag)).double().mean() * 100)
    out["num_pixels"] = int(epe.numel())
    return out


def _chunk(tag: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)


def write_png16(path: str | Path, image: np.ndarray) -> None:
    """Write an ``(H,W,3)`` uint16 array as a 16-bit RGB PNG."""
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
    if ftype == 0:
        return row
    if ftype == 2:
        return (row.astype(np.uint16) + prev).astype(np.uint8)
    out = bytearray(row.tobytes())
    up = prev.tobytes()
    for i in range(len(out)):
        a = out[i - bpp] if i >= bpp else 0
        if ftype == 1:
            out[i] = (out[i] + a) & 0xFF
        elif ftype == 3:
            out[i] = (out[i] + ((a + up[i]) >> 1)) & 0xFF
        elif ftype == 4:
            b, c = up[i], (up[i - bpp] if i >= bpp else 0)
            p = a + b - c
            pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
            out[i] = (out[i] + (a if pa <= pb and pa <= pc else b if pb <= pc else c)) & 0xFF
        else:
            raise ValueError(f"{where}: unknown PNG filter type {ftype}")
    return np.frombuffer(bytes(out), np.uint8)


def read_png16(path: str | Path) -> np.ndarray:
    """Read a non-interlaced 16-bit RGB PNG into an ``(H,W,3)`` uint16 array."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"flow PNG {path} does not exist")
    data = path.read_bytes()
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError(f"{path}: not a PNG file")
    pos, idat, header = 8, [], None
    while pos < len(data):
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
    raw = np.frombuffer(zlib.decompress(b"".join(idat)), np.uint8).reshape(h, 1 + w * 6)
    prev = np.zeros(w * 6, np.uint8)
    rows = np.empty((h, w * 6), np.uint8)
    for y in range(h):
        prev = rows[y] = _unfilter_row(int(raw[y, 0]), raw[y, 1:], prev, 6, f"{path} row {y}")
    return rows.view(">u2").reshape(h, w, 3).astype(np.uint16)


def write_kitti_flow(path: str | Path, flow: np.ndarray | torch.Tensor,
                     valid: np.ndarray | torch.Tensor | None = None) -> None:
    """Write ``(2,H,W)`` flow (and optional ``(H,W)``/``(1,H,W)`` validity) as a KITTI 16-bit flow PNG."""
    flow = np.asarray(flow.detach().cpu() if isinstance(flow, torch.Tensor) else flow, np.float64)
    if flow.ndim != 3 or flow.shape[0] != 2:
        raise ValueError(f"write_kitti_flow expects flow of shape (2,H,W), got {flow.shape}")
    v = np.ones(flow.shape[1:], bool) if valid is None else np.asarray(
        valid.detach().cpu() if isinstance(valid, torch.Tensor) else valid).reshape(flow.shape[1:]).astype(bool)
    enc = np.clip(np.round(flow * 64.0 + 2**15), 0, 2**16 - 1).astype(np.uint16)
    write_png16(path, np.stack([enc[0], enc[1], v.astype(np.uint16)], axis=-1))


def read_kitti_flow(path: str | Path) -> tuple[torch.Tensor, torch.Tensor]:
    """Read a KITTI flow PNG: ``(flow (2,H,W) float32 px, valid (1,H,W) bool)``; invalid pixels get flow 0."""
    img = read_png16(path).astype(np.float64)
    valid = img[..., 2] > 0
    flow = (img[..., :2] - 2**15) / 64.0
    flow[~valid] = 0.0
    return torch.from_numpy(flow.transpose(2, 0, 1).astype(np.float32)), torch.from_numpy(valid[None])
