"""Intrinsics plausibility checks: real calibrations pass, each common mistake gets its one-line message."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dfvo.data.intrinsics_check import IntrinsicsError, check_intrinsics, check_matrix, horizontal_fov_deg

cv2 = pytest.importorskip("cv2", reason="OpenCV (test-only reference) not installed")

EUROC = (458.654, 457.296, 367.215, 248.375)  # cam0 of the EuRoC MAV dataset, 752x480
EUROC_DIST = [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
KITTI_06 = np.array([[707.0912, 0.0, 601.8873], [0.0, 707.0912, 183.1104], [0.0, 0.0, 1.0]])  # 1226x370


def test_real_calibrations_pass() -> None:
    assert check_intrinsics(*EUROC, 752, 480, EUROC_DIST) == (*EUROC, EUROC_DIST)
    fx, fy, cx, cy, dist = check_matrix(torch.tensor(KITTI_06), 1226, 370, source="calib.txt")
    assert (fx, cx, dist) == (707.0912, 601.8873, None)
    # TUM fr1 with its 5 coefficients, and an 8-coefficient rational model
    check_intrinsics(517.3, 516.5, 318.6, 255.3, 640, 480, [0.2624, -0.9531, -0.0054, 0.0026, 1.1633])
    check_intrinsics(*EUROC, 752, 480, [0.1, -0.2, 0.0, 0.0, 0.01, 0.1, -0.1, 0.01])


@pytest.mark.parametrize("fx, w, h", [(458.654, 752, 480), (707.0912, 1226, 370), (30.0, 640, 480)])
def test_field_of_view_matches_opencv(fx: float, w: int, h: int) -> None:
    K = np.array([[fx, 0, w / 2], [0, fx, h / 2], [0, 0, 1.0]])
    fovx, _, _, _, _ = cv2.calibrationMatrixValues(K, (w, h), 1.0, 1.0)
    assert horizontal_fov_deg(fx, w) == pytest.approx(fovx, abs=1e-6)


def test_principal_point_outside_the_image() -> None:
    # issue 16's case, word for word: data.cx=3670 on a 752-px-wide image
    with pytest.raises(IntrinsicsError, match=r"^data.cx=3670 is outside the 752-px-wide image "
                                              r"\(expected 0 < cx < 752"):
        check_intrinsics(458.654, 457.296, 3670, 248.375, 752, 480)
    with pytest.raises(IntrinsicsError, match=r"^cv=480 in cam0/sensor.yaml is outside the 480-px-high image"):
        check_intrinsics(458.654, 457.296, 367.2, 480, 752, 480, names=("fu", "fv", "cu", "cv"),
                         source="cam0/sensor.yaml")


@pytest.mark.parametrize("values, pattern", [
    ((0.0, 457.3, 367.2, 248.4), r"^data.fx=0 must be positive"),
    ((458.7, -457.3, 367.2, 248.4), r"^data.fy=-457.3 must be positive"),
    (("abc", 457.3, 367.2, 248.4), r"^data.fx='abc' is not a number"),
    ((458.7, float("nan"), 367.2, 248.4), r"^data.fy=nan is not finite"),
    ((4.2, 4.2, 367.2, 248.4), r"^data.fx=4.2 gives a 178.\d-degree horizontal field of view"),  # millimetres
    ((0.61, 0.95, 0.49, 0.52), r"outside the 480-px-high image|field of view"),  # normalised units
    ((9000.0, 9000.0, 367.2, 248.4), r"^data.fx=9000 gives a 4.8-degree"),
    ((458.7, 120.0, 367.2, 248.4), r"fx/fy = 3.82, expected 0.5..2"),
    ((367.2, 457.3, 458.7, 248.4), None),  # fx and cx swapped: still a plausible camera, nothing to say
])
def test_implausible_values(values: tuple, pattern: str | None) -> None:
    if pattern is None:
        check_intrinsics(*values, 752, 480)
        return
    with pytest.raises(IntrinsicsError, match=pattern):
        check_intrinsics(*values, 752, 480)


def test_distortion_counts_and_models() -> None:
    with pytest.raises(IntrinsicsError, match=r"^data.dist has 3 coefficients; expected \[k1, k2, p1, p2\]"):
        check_intrinsics(*EUROC, 752, 480, [0.1, 0.2, 0.3])
    with pytest.raises(IntrinsicsError, match=r"has 6 coefficients"):
        check_intrinsics(*EUROC, 752, 480, [0.1] * 6)
    with pytest.raises(IntrinsicsError, match=r"data.dist='0.1 0.2' .*must be a list of numbers"):
        check_intrinsics(*EUROC, 752, 480, "0.1 0.2")
    with pytest.raises(IntrinsicsError, match=r"data.dist\[1\]='x' is not a number"):
        check_intrinsics(*EUROC, 752, 480, [0.1, "x", 0.0, 0.0])
    # a fisheye lens: 175 degrees is refused for a pinhole, accepted when the model says fisheye (4 coefficients)
    fx = 752 / (2 * np.tan(np.radians(87.5)))
    with pytest.raises(IntrinsicsError, match="175.0-degree"):
        check_intrinsics(fx, fx, 376, 240, 752, 480)
    assert check_intrinsics(fx, fx, 376, 240, 752, 480, [0.01, 0.0, 0.0, 0.0], model="fisheye")[4] is not None
    with pytest.raises(IntrinsicsError, match=r"expected \[k1, k2, k3, k4\] \(equidistant fisheye\)"):
        check_intrinsics(fx, fx, 376, 240, 752, 480, EUROC_DIST + [0.0], model="fisheye")


def test_check_matrix_names_the_file() -> None:
    K = KITTI_06.copy()
    K[0, 2] = 1601.9
    with pytest.raises(IntrinsicsError, match=r"^cx=1601.9 in seq06/calib.txt is outside the 1226-px-wide image"):
        check_matrix(K, 1226, 370, source="seq06/calib.txt")
    with pytest.raises(IntrinsicsError, match="3x3"):
        check_matrix(np.eye(4), 1226, 370)


def test_off_centre_principal_point_is_a_warning(caplog: pytest.LogCaptureFixture) -> None:
    """A principal point more than a quarter of the side from the centre is warned about with its offset (frames
    downscaled by 2 with the full-resolution intrinsics: KITTI 06's (601.9, 183.1) on a 613x185 frame), not refused;
    real calibrations (EuRoC, KITTI, TUM: within 3 % of the centre) give no warning."""
    with caplog.at_level("WARNING", logger="dfvo.data"):
        check_intrinsics(*EUROC, 752, 480)
        check_matrix(KITTI_06, 1226, 370, source="calib.txt")
        check_intrinsics(517.3, 516.5, 318.6, 255.3, 640, 480)
    assert not caplog.records
    with caplog.at_level("WARNING", logger="dfvo.data"):
        out = check_matrix(KITTI_06, 613, 185, source="calib.txt")
    assert out[:4] == (707.0912, 707.0912, 601.8873, 183.1104)
    (record,) = caplog.records
    dx, dy = 601.8873 - 306.0, 183.1104 - 92.0  # from the centre ((w-1)/2, (h-1)/2)
    assert record.getMessage().startswith(f"cx=601.887, cy=183.11 in calib.txt: the principal point is {dx:+.0f} px, "
                                          f"{dy:+.0f} px from the centre of the 613x185 image ({100 * dx / 613:.0f} % "
                                          f"of the width, {100 * dy / 185:.0f} % of the height")
    caplog.clear()
    with caplog.at_level("WARNING", logger="dfvo.data"):  # only the vertical offset beyond a quarter of the height
        check_intrinsics(500.0, 500.0, 320.0, 400.0, 640, 480)
    assert len(caplog.records) == 1 and "+0 px, +160 px" in caplog.records[0].getMessage()
