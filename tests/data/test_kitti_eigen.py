"""KITTI Eigen-split ground truth: split files, velodyne scans, the velodyne→image projection, crops."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from dfvo.data.image_io import DatasetError
from dfvo.data.kitti_eigen import (
    EigenFrame,
    crop_mask,
    list_velodyne_frames,
    project_velodyne,
    read_split,
    read_velodyne,
    velodyne_projection,
    write_velodyne,
)

KITTI_RAW_DATE = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "kitti_raw" / "2011_09_26"


def test_read_split(tmp_path: Path) -> None:
    (tmp_path / "s.txt").write_text("2011_09_26/2011_09_26_drive_0002_sync 0000000069 l\n"
                                    "2011_09_26/2011_09_26_drive_0002_sync 5 r\n\n"
                                    "2011_09_28/2011_09_28_drive_0001_sync 12\n")
    frames = read_split(tmp_path / "s.txt")
    assert frames == [EigenFrame("2011_09_26/2011_09_26_drive_0002_sync", 69, 2),
                      EigenFrame("2011_09_26/2011_09_26_drive_0002_sync", 5, 3),
                      EigenFrame("2011_09_28/2011_09_28_drive_0001_sync", 12, 2)]
    assert frames[0].velodyne(Path("/r")) == Path(
        "/r/2011_09_26/2011_09_26_drive_0002_sync/velodyne_points/data/0000000069.bin")
    (tmp_path / "bad.txt").write_text("2011_09_26/2011_09_26_drive_0002_sync 69 l\ndrive x l\n")
    with pytest.raises(DatasetError, match=r"bad\.txt line 2"):
        read_split(tmp_path / "bad.txt")


def test_velodyne_round_trip_and_listing(tmp_path: Path) -> None:
    pts = np.random.default_rng(0).normal(size=(10, 4)).astype(np.float32)
    path = tmp_path / "2011_01_01" / "2011_01_01_drive_0001_sync" / "velodyne_points" / "data" / "0000000003.bin"
    write_velodyne(path, pts)
    assert path.stat().st_size == 160 and np.array_equal(read_velodyne(path), pts)
    assert np.array_equal(np.fromfile(path, "<f4").reshape(-1, 4), pts)  # raw float32 x, y, z, r
    assert list_velodyne_frames(tmp_path) == [EigenFrame("2011_01_01/2011_01_01_drive_0001_sync", 3, 2)]
    path.write_bytes(b"\0" * 10)
    with pytest.raises(DatasetError, match="not a whole number of points"):
        read_velodyne(path)
    with pytest.raises(DatasetError, match="velodyne_points"):
        list_velodyne_frames(tmp_path / "2011_01_01" / "2011_01_01_drive_0001_sync")


def _numbers(path: Path, key: str) -> np.ndarray:
    for line in path.read_text().splitlines():
        if line.startswith(key + ":"):
            return np.array(line.split(":", 1)[1].split(), float)
    raise KeyError(key)


def test_projection_matrix_of_the_real_calibration() -> None:
    if not KITTI_RAW_DATE.exists():
        pytest.skip(f"needs {KITTI_RAW_DATE} (the project's ../shared data folder); not present on this machine")
    P, size = velodyne_projection(KITTI_RAW_DATE, 2)
    cam, velo = KITTI_RAW_DATE / "calib_cam_to_cam.txt", KITTI_RAW_DATE / "calib_velo_to_cam.txt"
    R_rect = np.eye(4)
    R_rect[:3, :3] = _numbers(cam, "R_rect_00").reshape(3, 3)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = _numbers(velo, "R").reshape(3, 3), _numbers(velo, "T")
    assert np.allclose(P, _numbers(cam, "P_rect_02").reshape(3, 4) @ R_rect @ T, atol=1e-12)
    assert size == (375, 1242)
    # a point 20 m ahead of the scanner, on its axis, projects near the image centre row, at ~20 m depth
    x = P @ np.array([20.0, 0, 0, 1])
    assert 19.5 < x[2] < 20.5 and 0 < x[0] / x[2] < 1242 and 100 < x[1] / x[2] < 250


def test_project_velodyne_nearest_point_wins() -> None:
    # identity-like projection: velodyne x forward = depth; image u = 10*y/x + 5, v = 10*z/x + 4
    P = np.array([[5.0, 10, 0, 0], [4, 0, 10, 0], [1, 0, 0, 0]])
    pts = np.array([[10.0, 0, 0, 0],       # -> (5, 4), depth 10
                    [5.0, 0, 0, 0],        # -> (5, 4), depth 5: nearer, wins
                    [8.0, 1.6, 0.8, 0],    # -> (7, 5), depth 8
                    [-3.0, 0, 0, 0],       # behind the scanner: dropped
                    [1.0, 10, 0, 0]])      # -> u = 105: outside
    d = project_velodyne(pts, P, (8, 9))
    assert d.shape == (1, 8, 9) and d.dtype == torch.float32
    assert d[0, 4, 5] == 5 and d[0, 5, 7] == 8 and int((d > 0).sum()) == 2
    shifted = project_velodyne(pts, P, (8, 9), pixel_offset=-1)
    assert shifted[0, 3, 4] == 5 and shifted[0, 4, 6] == 8 and int((shifted > 0).sum()) == 2


def test_crop_masks() -> None:
    garg = crop_mask((375, 1242), "garg")[0]
    rows, cols = torch.nonzero(garg.any(1)).flatten(), torch.nonzero(garg.any(0)).flatten()
    assert (int(rows[0]), int(rows[-1]), int(cols[0]), int(cols[-1])) == (153, 370, 44, 1196)
    eigen = crop_mask((375, 1242), "eigen")[0]
    assert int(torch.nonzero(eigen.any(1)).flatten()[0]) == 124
    assert bool(crop_mask((10, 20), "none").all())
    with pytest.raises(ValueError, match="depth.crop='middle'"):
        crop_mask((10, 20), "middle")
