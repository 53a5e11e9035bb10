"""KITTI Eigen-split depth ground truth: velodyne scans projected into the rectified colour cameras.

Layout (the KITTI raw layout of :mod:`dfvo.data.kitti_raw`)::

    ROOT/DATE/calib_cam_to_cam.txt       R_rect_00 (3x3), P_rect_02 / P_rect_03 (3x4), S_rect_02 / S_rect_03 (W H)
    ROOT/DATE/calib_velo_to_cam.txt      R, T: T_cam0_velo (velodyne → unrectified camera 0)
    ROOT/DATE/DATE_drive_XXXX_sync/velodyne_points/data/FFFFFFFFFF.bin   float32 x, y, z, reflectance per point
    ROOT/DATE/DATE_drive_XXXX_sync/image_02/data/FFFFFFFFFF.png|jpg      left colour camera (image_03: right)

Split file: one frame per line, ``DATE/DATE_drive_XXXX_sync FRAME SIDE`` (``FRAME`` with or without its 10-digit
padding, ``SIDE`` ``l`` = camera 2, ``r`` = camera 3), e.g. ``2011_09_26/2011_09_26_drive_0002_sync 0000000069 l``.

Convention (the Eigen-split protocol):
    - A point ``X_velo`` (homogeneous, reflectance ignored) maps to ``x = P_rect_0c @ R_rect_00 @ T_cam0_velo @ X``;
      its depth is ``x[2]``, the z of the point in rectified camera c (``P_rect_0c = K [I | t]``, so the third row
      adds camera c's z offset), and its pixel ``(round(x[0]/x[2]), round(x[1]/x[2]))`` + ``pixel_offset``.
    - Points behind the scanner (``x_velo < 0``) or the camera (depth <= 0), or outside the image, are dropped.
      When several points land on one pixel the nearest wins. Pixels without a point have depth 0 (invalid).
    - The image size is ``S_rect_0c`` of the calibration (the rectified image's size), else the image file's.
    - Crops (fractions of the image, rows then columns): Garg ``[0.40810811, 0.99189189] x [0.03594771,
      0.96405229]``, Eigen ``[0.3324324, 0.91351351] x [0.0359477, 0.96405229]``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from dfvo.data.calibration import get_matrix, read_calib_file, read_raw_rectification, read_rigid_transform
from dfvo.data.image_io import DatasetError, image_size, require_dir, require_file

__all__ = ["EigenFrame", "read_split", "list_velodyne_frames", "read_velodyne", "write_velodyne",
           "velodyne_projection", "project_velodyne", "crop_mask", "CROPS"]

CROPS = {"garg": (0.40810811, 0.99189189, 0.03594771, 0.96405229),
         "eigen": (0.3324324, 0.91351351, 0.0359477, 0.96405229)}
SIDES = {"l": 2, "r": 3}


@dataclass
class EigenFrame:
    """One frame of a split: ``drive`` (``DATE/DATE_drive_XXXX_sync``), ``frame`` number, ``camera`` (2 or 3)."""

    drive: str
    frame: int
    camera: int

    def drive_dir(self, root: Path) -> Path:
        return root / self.drive

    def velodyne(self, root: Path) -> Path:
        return root / self.drive / "velodyne_points" / "data" / f"{self.frame:010d}.bin"

    def image(self, root: Path) -> Path:
        folder = root / self.drive / f"image_0{self.camera}" / "data"
        for ext in (".png", ".jpg", ".jpeg"):
            if (folder / f"{self.frame:010d}{ext}").is_file():
                return folder / f"{self.frame:010d}{ext}"
        raise DatasetError(f"KITTI raw: no image {self.frame:010d}.png|jpg in {folder}")

    def calib_dir(self, root: Path) -> Path:
        return (root / self.drive).parent


def read_split(path: str | Path) -> list[EigenFrame]:
    """Frames of a split file (lines ``DATE/DATE_drive_XXXX_sync FRAME [l|r]``; side defaults to ``l``)."""
    path = require_file(path, "depth split")
    frames = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        tok = line.split()
        if not tok:
            continue
        side = tok[2] if len(tok) > 2 else "l"
        if len(tok) not in (2, 3) or not tok[1].isdigit() or side not in SIDES:
            raise DatasetError(f"split {path} line {n}: {line!r}; expected 'DATE/DATE_drive_XXXX_sync FRAME l|r', "
                               "e.g. '2011_09_26/2011_09_26_drive_0002_sync 0000000069 l'")
        frames.append(EigenFrame(tok[0].strip("/"), int(tok[1]), SIDES[side]))
    if not frames:
        raise DatasetError(f"split {path} lists no frame")
    return frames


def list_velodyne_frames(root: str | Path) -> list[EigenFrame]:
    """Every ``DATE/DRIVE/velodyne_points/data/*.bin`` under a KITTI raw root, as left-camera frames (sorted)."""
    root = require_dir(root, "KITTI raw root")
    bins = sorted(root.glob("*/*_sync/velodyne_points/data/*.bin"))
    if not bins:
        raise DatasetError(f"KITTI raw root {root} has no DATE/DATE_drive_XXXX_sync/velodyne_points/data/*.bin scans "
                           "(give a split file with depth.split=)")
    return [EigenFrame(f"{b.parents[3].name}/{b.parents[2].name}", int(b.stem), 2) for b in bins]


def read_velodyne(path: str | Path) -> np.ndarray:
    """(N,4) float32 points ``x, y, z, reflectance`` of a KITTI velodyne ``.bin`` scan (velodyne frame, metres)."""
    path = require_file(path, "velodyne scan")
    data = np.fromfile(path, dtype="<f4")
    if data.size % 4:
        raise DatasetError(f"velodyne scan {path}: {path.stat().st_size} bytes is not a whole number of points "
                           "(expected float32 x, y, z, reflectance per point)")
    return data.reshape(-1, 4)


def write_velodyne(path: str | Path, points: np.ndarray) -> None:
    """Write (N,3) or (N,4) points as a KITTI velodyne ``.bin`` (reflectance 0 when absent)."""
    pts = np.asarray(points, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] not in (3, 4):
        raise ValueError(f"write_velodyne expects (N,3) or (N,4) points, got {pts.shape}")
    if pts.shape[1] == 3:
        pts = np.concatenate([pts, np.zeros((len(pts), 1), np.float32)], 1)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    pts.astype("<f4").tofile(path)


def velodyne_projection(calib_dir: str | Path, camera: int = 2) -> tuple[np.ndarray, tuple[int, int] | None]:
    """``(P_velo_to_image (3,4) float64, (H, W) from S_rect_0c or None)`` of a KITTI raw date folder."""
    calib_dir = Path(calib_dir)
    cam_file = require_file(calib_dir / "calib_cam_to_cam.txt", "KITTI raw camera calibration")
    velo_file = require_file(calib_dir / "calib_velo_to_cam.txt", "KITTI raw velodyne calibration")
    calib = read_calib_file(cam_file)
    P = get_matrix(calib, f"P_rect_0{camera}", (3, 4), cam_file)
    size = None
    if f"S_rect_0{camera}" in calib:
        w, h = get_matrix(calib, f"S_rect_0{camera}", (1, 2), cam_file)[0]
        size = (int(round(h)), int(round(w)))
    return P @ read_raw_rectification(cam_file) @ read_rigid_transform(velo_file), size


def project_velodyne(points: np.ndarray, P_velo_to_image: np.ndarray, size: tuple[int, int],
                     pixel_offset: int = 0) -> torch.Tensor:
    """Sparse depth (1,H,W) float32 of velodyne points (N,>=3) seen through ``P_velo_to_image`` (3,4).

    Args:
        points: velodyne-frame points (x forward, metres); columns beyond 3 are ignored.
        P_velo_to_image: ``P_rect_0c @ R_rect_00 @ T_cam0_velo``.
        size: (H, W) of the image.
        pixel_offset: added to the rounded pixel coordinates (-1 reproduces the published Eigen ground truth).

    Returns:
        (1,H,W) depth in metres, 0 where no point lands; the nearest point wins per pixel.
    """
    H, W = int(size[0]), int(size[1])
    pts = np.asarray(points, dtype=np.float64)[:, :3]
    pts = pts[pts[:, 0] >= 0]
    x = np.concatenate([pts, np.ones((len(pts), 1))], 1) @ P_velo_to_image.T
    z = x[:, 2]
    front = z > 0
    x, z = x[front], z[front]
    u = np.round(x[:, 0] / z).astype(np.int64) + int(pixel_offset)
    v = np.round(x[:, 1] / z).astype(np.int64) + int(pixel_offset)
    inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    u, v, z = u[inside], v[inside], z[inside]
    depth = np.full(H * W, np.inf)
    np.minimum.at(depth, v * W + u, z)
    depth[~np.isfinite(depth)] = 0.0
    return torch.from_numpy(depth.reshape(1, H, W).astype(np.float32))


def crop_mask(size: tuple[int, int], crop: str) -> torch.Tensor:
    """(1,H,W) bool evaluation crop: ``"garg"``, ``"eigen"`` or ``"none"`` (see the module docstring)."""
    H, W = int(size[0]), int(size[1])
    mask = torch.zeros(1, H, W, dtype=torch.bool)
    if crop == "none":
        mask[:] = True
        return mask
    if crop not in CROPS:
        raise ValueError(f"depth.crop={crop!r}; expected one of {sorted(CROPS)} or 'none'")
    t, b, l, r = CROPS[crop]
    mask[:, int(t * H):int(b * H), int(l * W):int(r * W)] = True
    return mask


def frame_size(root: Path, frame: EigenFrame, calib_size: tuple[int, int] | None) -> tuple[int, int]:
    """(H, W) of a frame: the calibration's ``S_rect`` size, else the image file's."""
    return calib_size if calib_size is not None else image_size(frame.image(root))
