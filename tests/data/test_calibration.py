"""KITTI calibration files: malformed lines are named by file and line number (issue 16)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dfvo.data.calibration import read_calib_file, read_odometry_projections
from dfvo.data.image_io import DatasetError

P0 = "7.188560e+02 0 6.071928e+02 0 0 7.188560e+02 1.852157e+02 0 0 0 1 0"
P1 = "7.188560e+02 0 6.071928e+02 -3.861448e+02 0 7.188560e+02 1.852157e+02 0 0 0 1 0"


def test_non_numeric_matrix_line_names_file_and_line(tmp_path: Path) -> None:
    path = tmp_path / "calib.txt"
    path.write_text(f"calib_time: 09-Jan-2012 13:57:47\nP0: abc {P0[12:]}\nP1: {P1}\n")
    with pytest.raises(DatasetError, match=r"calib.txt line 2: 'P0:' is not 12 numbers \(3x4 matrix\): 'abc"):
        read_odometry_projections(path, (0, 1))
    # the other matrix of the same file still reads, and the date line stays out of the numbers
    P = read_odometry_projections(path, (1,))[1]
    assert P.shape == (3, 4) and P[0, 3] == pytest.approx(-386.1448)
    assert "calib_time" not in read_calib_file(path)


def test_wrong_count_names_line(tmp_path: Path) -> None:
    path = tmp_path / "calib.txt"
    path.write_text(f"P1: {P1}\n\nP0: {' '.join(P0.split()[:11])}\n")
    with pytest.raises(DatasetError, match=r"calib.txt line 3: 'P0:' has 11 numbers, expected 12 \(3x4\)"):
        read_odometry_projections(path, (0,))
    with pytest.raises(DatasetError, match=r"has no 'P2:' line"):
        read_odometry_projections(path, (2,))


def test_values_parsed(tmp_path: Path) -> None:
    path = tmp_path / "calib.txt"
    path.write_text(f"P0: {P0}\nP1: {P1}\n")
    proj = read_odometry_projections(path, (0, 1))
    np.testing.assert_allclose(proj[0], np.array(P0.split(), float).reshape(3, 4))
    assert read_calib_file(path).lines == {"P0": 1, "P1": 2}
