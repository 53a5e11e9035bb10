"""KITTI raw drives: monocular snippets and stereo pairs for training, OXTS ground-truth poses when present.

Layout::

    ROOT/DATE/calib_cam_to_cam.txt                      P_rect_02, P_rect_03 (3x4), R_rect_00
    ROOT/DATE/calib_velo_to_cam.txt, calib_imu_to_velo.txt   R, T (only needed for OXTS poses)
    ROOT/DATE/DATE_drive_XXXX_sync/image_02/data/*.png|jpg   left colour camera (image_03: right)
    ROOT/DATE/DATE_drive_XXXX_sync/oxts/data/*.txt           GPS/IMU packets, optional

``root`` may also be a single DATE folder.

Convention:
    - Samples follow :mod:`dfvo.data` keys: ``image`` (frame i of camera 2), ``image_prev``/``image_next``
      (frames i∓1, temporal mode: i runs over 1..N-2), ``image_right`` and ``T_right_left`` (stereo), ``K``
      (3,3) of camera 2 at the working resolution, ``index``, and ``pose``/``pose_prev``/``pose_next`` (T_w_c of
      the rectified camera 2, first frame of the drive = identity) when OXTS data exists.
    - OXTS to pose follows the KITTI raw devkit: Mercator projection with the scale ``cos(lat_0)`` of the first
      packet, ``R = Rz(yaw) Ry(pitch) Rx(roll)``, IMU frame x forward, y left, z up.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from dfvo.data.calibration import (
    camera_from_rectified_cam0,
    checked_intrinsics,
    read_raw_projections,
    read_raw_rectification,
    read_rigid_transform,
    stereo_baseline,
    stereo_transform,
)
from dfvo.data.frame_cache import DecodedFrames
from dfvo.data.image_io import (
    DatasetError,
    DatasetNotFoundError,
    image_size,
    list_images,
    read_image,
    require_dir,
    require_file,
)
from dfvo.data.stereo_hints import hint_depth
from dfvo.data.transforms import check_working_size, resize_with_intrinsics

log = logging.getLogger("dfvo.data")

EARTH_RADIUS_M = 6378137.0


def _rot_x(a: np.ndarray) -> np.ndarray:
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def _rot_y(a: np.ndarray) -> np.ndarray:
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def _rot_z(a: np.ndarray) -> np.ndarray:
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def oxts_to_imu_poses(oxts: np.ndarray) -> np.ndarray:
    """IMU poses from OXTS packets, relative to the first packet with finite numbers.

    Args:
        oxts: (N,>=6) rows ``lat (deg), lon (deg), alt (m), roll, pitch, yaw (rad), ...``.

    Returns:
        (N,4,4) float64 ``T_imu0_imui`` (the first finite packet's = identity); the world frame is east-north-up
        before the normalisation by that pose. A packet with a NaN or infinity among its first six numbers gives a
        NaN row (a frame without ground truth).
    """
    if oxts.ndim != 2 or oxts.shape[1] < 6:
        raise ValueError(f"oxts must be (N, >=6) [lat, lon, alt, roll, pitch, yaw, ...], got {oxts.shape}")
    known = np.isfinite(oxts[:, :6]).all(axis=1)
    if not known.any():
        return np.full((len(oxts), 4, 4), np.nan)
    first = int(np.argmax(known))
    lat, lon, alt = oxts[:, 0], oxts[:, 1], oxts[:, 2]
    scale = np.cos(np.deg2rad(lat[first]))
    T = np.tile(np.eye(4), (len(oxts), 1, 1))
    T[:, 0, 3] = scale * np.deg2rad(lon) * EARTH_RADIUS_M
    T[:, 1, 3] = scale * EARTH_RADIUS_M * np.log(np.tan(np.deg2rad(90.0 + lat) / 2.0))
    T[:, 2, 3] = alt
    T[:, :3, :3] = _rot_z(oxts[:, 5]) @ _rot_y(oxts[:, 4]) @ _rot_x(oxts[:, 3])
    T[~known] = np.nan
    return np.linalg.inv(T[first]) @ T


def read_oxts_folder(folder: str | Path) -> np.ndarray:
    """All packets of an ``oxts/data`` folder (one ``*.txt`` per frame, sorted by name) as (N,30) float64; packets
    with non-finite numbers are kept (their frames get no ground truth) and named in one warning line."""
    folder = require_dir(folder, "KITTI raw oxts")
    files = sorted(folder.glob("*.txt"))
    if not files:
        raise DatasetError(f"KITTI raw oxts: folder {folder} has no *.txt packets")
    rows = []
    for f in files:
        try:
            vals = [float(tok) for tok in f.read_text().split()]
        except ValueError as err:
            raise DatasetError(f"oxts packet {f}: expected numbers ({err})") from err
        if len(vals) < 6:
            raise DatasetError(f"oxts packet {f}: expected at least 6 numbers (lat lon alt roll pitch yaw), "
                               f"found {len(vals)}")
        rows.append(vals[:30] + [0.0] * (30 - min(len(vals), 30)))
    packets = np.asarray(rows, dtype=np.float64)
    bad = np.flatnonzero(~np.isfinite(packets[:, :6]).all(axis=1))
    if len(bad):
        log.warning("oxts packet %s%s: NaN or infinite position or attitude; %s without ground truth", files[bad[0]],
                    f" and {len(bad) - 1} more" if len(bad) > 1 else "",
                    "its frame is evaluated" if len(bad) == 1 else f"these {len(bad)} frames are evaluated")
    return packets


def raw_timestamps(path: Path, count: int) -> np.ndarray | None:
    """(N,) float64 seconds (UTC, since 1970) of a raw drive's ``timestamps.txt`` (``2011-09-26 13:04:32.345808896``
    a line); None (with a warning when the file exists) when it is missing, unreadable or not one line per image."""
    if not path.is_file():
        return None
    lines = [line.strip() for line in path.read_text().splitlines() if line.strip()]
    try:
        ns = np.array([np.datetime64(line.replace(" ", "T"), "ns") for line in lines]).astype(np.int64)
    except ValueError as err:
        log.warning("%s: expected one date and time a line (%s); the frames run without timestamps", path, err)
        return None
    if len(ns) != count:
        log.warning("%s has %d timestamps for %d images; the frames run without timestamps", path, len(ns), count)
        return None
    return ns / 1e9


def imu_to_camera(date_dir: str | Path, camera: int = 2) -> np.ndarray:
    """(4,4) ``T_cam_imu`` of rectified camera ``camera`` from the three calibration files of a date folder."""
    date_dir = Path(date_dir)
    cam_file = require_file(date_dir / "calib_cam_to_cam.txt", "KITTI raw camera calibration")
    T_velo_imu = read_rigid_transform(require_file(date_dir / "calib_imu_to_velo.txt", "KITTI raw IMU calibration"))
    T_cam0_velo = read_rigid_transform(require_file(date_dir / "calib_velo_to_cam.txt", "KITTI raw velo calibration"))
    P = read_raw_projections(cam_file, (camera,))[camera]
    return camera_from_rectified_cam0(P) @ read_raw_rectification(cam_file) @ T_cam0_velo @ T_velo_imu


def oxts_camera_poses(drive_dir: str | Path, camera: int = 2) -> np.ndarray | None:
    """Ground-truth ``T_w_c`` (N,4,4) of a raw drive's rectified camera, first = identity; None without oxts, or
    (with a warning) without the IMU/velodyne calibration files that move the oxts poses to the camera."""
    drive_dir = Path(drive_dir)
    oxts_dir = drive_dir / "oxts" / "data"
    if not oxts_dir.is_dir():
        return None
    T_imu0_imu = oxts_to_imu_poses(read_oxts_folder(oxts_dir))
    try:
        T_cam_imu = imu_to_camera(drive_dir.parent, camera)
    except DatasetNotFoundError as err:  # the frames can still be tracked; only the ground truth needs it
        log.warning("%s: the oxts poses cannot be moved to the camera, so %s has no ground truth", err, drive_dir.name)
        return None
    return T_cam_imu @ T_imu0_imu @ np.linalg.inv(T_cam_imu)


def _find_drives(root: Path, drives: list[str] | None, held_out: Sequence[str] = ()) -> list[Path]:
    """Drive folders ``DATE/DATE_drive_XXXX_sync`` under ``root`` (a dataset root or one DATE folder): ``drives``,
    or every drive but those named in ``held_out`` (left out with one log line; naming one in ``drives`` trains on
    it, with a warning)."""
    date_dirs = [root] if (root / "calib_cam_to_cam.txt").is_file() else sorted(p for p in root.iterdir() if p.is_dir())
    available = {d.name: d for date in date_dirs for d in sorted(date.glob("*_drive_*_sync")) if d.is_dir()}
    held = {_sync_name(h) for h in held_out}
    if drives is None:
        if not available:
            raise DatasetError(f"KITTI raw root {root} contains no DATE/DATE_drive_XXXX_sync folders")
        left_out = sorted(set(available) & held)
        if left_out:
            log.info("KITTI raw under %s: %d held-out test drive(s) left out of training (data.held_out_drives): %s",
                     root, len(left_out), ", ".join(left_out))
        kept = [d for name, d in available.items() if name not in held]
        if not kept:
            raise DatasetError(f"KITTI raw root {root} holds only held-out test drives ({', '.join(left_out)}); name "
                               "the drives to train on with data.drives=[...] or change data.held_out_drives")
        return kept
    folders = [_drive_folder(str(name), root, available) for name in drives]
    for folder in folders:
        if folder.name in held:
            log.warning("KITTI raw drive %s is a held-out test drive (data.held_out_drives): training on it, so its "
                        "test metrics are no longer held out", folder.name)
    return folders


def _sync_name(name: str) -> str:
    key = Path(str(name)).name
    return key if key.endswith("_sync") else f"{key}_sync"


def _drive_folder(name: str, root: Path, available: dict[str, Path]) -> Path:
    """The folder of drive ``name``: its full name (``2011_09_26_drive_0001`` with or without ``_sync``), or its
    number alone (``0001`` or ``1``) when exactly one date under ``root`` has a drive of that number."""
    key = _sync_name(name)
    if key in available:
        return available[key]
    number = key.removesuffix("_sync")
    if number.isdecimal() and number.isascii():
        matches = sorted(k for k in available if k.endswith(f"_drive_{int(number):04d}_sync"))
        if len(matches) == 1:
            return available[matches[0]]
        if len(matches) > 1:
            raise DatasetError(f"KITTI raw drive {name!r} is ambiguous under {root}: {matches}; give the full name "
                               f"(e.g. seq={matches[0].removesuffix('_sync')})")
    raise DatasetError(f"KITTI raw drive {name!r} not found under {root} (expected a folder DATE/DATE_drive_NNNN_sync "
                       f"named by seq=DATE_drive_NNNN or its number NNNN; available: {sorted(available)})")


class _Drive:
    """File lists, calibration and optional poses of one raw drive (camera 2 left, camera 3 right)."""

    def __init__(self, drive_dir: Path, stereo: bool, size: tuple[int, int] | None) -> None:
        self.dir = drive_dir
        self.left = list_images(drive_dir / "image_02" / "data", "KITTI raw left camera (image_02/data)")
        self.right = None
        if stereo:
            self.right = list_images(drive_dir / "image_03" / "data", "KITTI raw right camera (image_03/data)")
            if len(self.right) != len(self.left):
                raise DatasetError(f"{drive_dir}: image_02/data has {len(self.left)} images but image_03/data has "
                                   f"{len(self.right)}; expected equal counts")
        cam_file = require_file(drive_dir.parent / "calib_cam_to_cam.txt", "KITTI raw camera calibration")
        proj = read_raw_projections(cam_file, (2, 3) if stereo else (2,))  # a monocular run needs no P_rect_03
        self.native_size = image_size(self.left[0])
        K = torch.as_tensor(checked_intrinsics(cam_file, "P_rect_02", self.native_size), dtype=torch.float32)
        self.baseline = stereo_baseline(proj[2], proj[3]) if stereo else None  # after the check: it divides by fx
        self.fx_native = float(K[0, 0])
        self.size = size if size is not None else self.native_size
        _, self.K = resize_with_intrinsics(torch.zeros(1, *self.native_size), K, *self.size)
        poses = oxts_camera_poses(drive_dir, 2)
        if poses is not None and len(poses) != len(self.left):
            raise DatasetError(f"{drive_dir}: oxts/data has {len(poses)} packets but image_02/data has "
                               f"{len(self.left)} images; expected one packet per image")
        self.poses = poses
        self.timestamps = raw_timestamps(drive_dir / "image_02" / "timestamps.txt", len(self.left))
        self.cached: dict[str, DecodedFrames] | None = None
        self.hints: DecodedFrames | None = None

    def load(self, path: Path) -> torch.Tensor:
        return read_image(path, size=self.size, expected_size=self.native_size)

    def use_cache(self, cache_dir: str | Path) -> None:
        """Read the frames from memory-mapped caches of the decoded images in ``cache_dir``
        (:class:`dfvo.data.frame_cache.DecodedFrames`; written on first use)."""
        name = self.dir.name  # DATE_drive_NNNN_sync
        self.cached = {"left": DecodedFrames(self.left, self.size, self.load, cache_dir, f"{name}_image_02")}
        if self.right is not None:
            self.cached["right"] = DecodedFrames(self.right, self.size, self.load, cache_dir, f"{name}_image_03")

    def use_hints(self, cache_dir: str | Path) -> None:
        """Stereo depth hints of the left frames (:mod:`dfvo.data.stereo_hints`), computed once into a memory-mapped
        cache in ``cache_dir``."""
        if self.right is None:
            raise DatasetError(f"{self.dir}: depth hints need the right camera (image_03/data)")
        partner = dict(zip(self.left, self.right))
        self.hints = DecodedFrames(self.left, self.size, lambda p: hint_depth(p, partner[p], self.fx_native,
                                                                              self.baseline, self.size),
                                   cache_dir, f"{self.dir.name}_sgbm_hints", channels=1,
                                   key_paths=[*self.left, *self.right])

    def frame(self, camera: str, i: int) -> torch.Tensor:
        """Frame ``i`` of ``camera`` (``left``: image_02, ``right``: image_03), (3,H,W) float32 in [0,1]."""
        if self.cached is not None:
            return self.cached[camera][i]
        return self.load((self.left if camera == "left" else self.right)[i])


def open_drives(root: str | Path, drives: list[str] | None = None, *, stereo: bool = True,
                size: tuple[int, int] | None = None, held_out: Sequence[str] = ()) -> list[_Drive]:
    """The drives under ``root`` (``drives`` by name, or all but ``held_out``) with their file lists, calibration,
    oxts poses and timestamps; ``stereo``: the right camera too (image_03, P_rect_03); ``size``: the (height,
    width) frames are read at (None: native). :class:`KittiRawSnippets` and a monocular inference run read them.

    Raises:
        DatasetNotFoundError, DatasetError: as :class:`KittiRawSnippets`.
    """
    return [_Drive(d, stereo, size) for d in _find_drives(require_dir(root, "KITTI raw root"), drives, held_out)]


class KittiRawSnippets(Dataset):
    """Training samples from KITTI raw drives: frame i of camera 2 with i±1 and/or its camera-3 partner.

    Args:
        root: dataset root (holding DATE folders) or one DATE folder.
        height: working height (None with width None: native resolution).
        width: working width.
        drives: drive folder names (``2011_09_26_drive_0001_sync``; ``_sync`` and a ``DATE/`` prefix optional);
            None: every drive found.
        stereo: add ``image_right`` and ``T_right_left``.
        temporal: add ``image_prev``/``image_next`` (targets are then frames 1..N-2 of each drive).
        cache_dir: read the decoded frames from memory-mapped caches there (written on first use:
            :mod:`dfvo.data.frame_cache`); None: decode every frame when it is read.
        held_out: drive names left out when ``drives`` is None (training: :data:`dfvo.data.held_out.HELD_OUT_DRIVES`).
        hints: add ``depth_hint`` (1,H,W), the stereo matcher's depth of the target frame in metres (0: none;
            :mod:`dfvo.data.stereo_hints`), computed once into ``cache_dir`` (which it needs).

    Raises:
        DatasetNotFoundError: missing root, image folder or calibration file.
        DatasetError: no drives / images, unknown drive, mismatched left/right or image/oxts counts, calibration
            without P_rect_02/P_rect_03.
    """

    def __init__(self, root: str | Path, height: int | None, width: int | None, drives: list[str] | None = None,
                 stereo: bool = True, temporal: bool = True, cache_dir: str | Path | None = None,
                 held_out: Sequence[str] = (), hints: bool = False) -> None:
        if not (stereo or temporal):
            raise ValueError("KittiRawSnippets: at least one of stereo / temporal must be True")
        self.root = require_dir(root, "KITTI raw root")
        size = check_working_size(height, width, f"KittiRawSnippets({self.root})")
        self.stereo, self.temporal = stereo, temporal
        self.drives = open_drives(self.root, drives, stereo=stereo, size=size, held_out=held_out)
        if cache_dir is not None:
            for drive in self.drives:
                drive.use_cache(cache_dir)
        if hints:
            if cache_dir is None or size is None:
                raise ValueError("KittiRawSnippets: depth hints need a cache folder and a working size "
                                 "(data.frame_cache_dir, data.height, data.width)")
            for drive in self.drives:
                drive.use_hints(cache_dir)
        margin = 1 if temporal else 0
        self.samples: list[tuple[int, int]] = [(k, i) for k, drive in enumerate(self.drives)
                                               for i in range(margin, len(drive.left) - margin)]
        if not self.samples:
            raise DatasetError(f"KITTI raw under {self.root}: no drive has enough frames for snippets "
                               f"(temporal={temporal} needs at least 3 per drive)")

    def __len__(self) -> int:
        return len(self.samples)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        k, i = self.samples[index]
        drive = self.drives[k]
        sample: dict[str, torch.Tensor] = {"image": drive.frame("left", i), "K": drive.K.clone(),
                                           "index": torch.tensor(i)}
        if self.temporal:
            sample["image_prev"] = drive.frame("left", i - 1)
            sample["image_next"] = drive.frame("left", i + 1)
        if self.stereo and drive.right is not None:
            sample["image_right"] = drive.frame("right", i)
            sample["T_right_left"] = stereo_transform(drive.baseline)
        if drive.hints is not None:
            sample["depth_hint"] = drive.hints[i]
        if drive.poses is not None:
            sample["pose"] = torch.as_tensor(drive.poses[i], dtype=torch.float32)
            if self.temporal:
                sample["pose_prev"] = torch.as_tensor(drive.poses[i - 1], dtype=torch.float32)
                sample["pose_next"] = torch.as_tensor(drive.poses[i + 1], dtype=torch.float32)
        return sample
