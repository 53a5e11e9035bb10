"""Working size from a target width or a scale factor: aspect kept, multiples of 32, intrinsics exact."""

from __future__ import annotations

import pytest
import torch

from dfvo.data.transforms import resize_with_intrinsics
from dfvo.data.working_size import aspect_change, working_intrinsics, working_size
from dfvo.geometry.camera import intrinsics_matrix, project_points


@pytest.mark.parametrize("native, kwargs, expected", [
    ((480, 752), {"width": 640}, (416, 640)),  # EuRoC: 480*640/752 = 408.5 -> 416 (not KITTI's 192)
    ((376, 1241), {"width": 640}, (192, 640)),  # KITTI: the paper's 640x192
    ((480, 752), {"scale": 0.5}, (256, 384)),  # 240 -> 256, 376 -> 384
    ((480, 640), {"width": 600}, (448, 608)),  # TUM: a width off the grid is rounded too
    ((1080, 1920), {"width": 640}, (352, 640)),  # phone video 16:9: 360 -> 352
    ((480, 752), {"width": 640, "multiple": 8}, (408, 640)),
    ((40, 60), {"scale": 0.1}, (32, 32)),  # never below one multiple
])
def test_sizes(native: tuple[int, int], kwargs: dict, expected: tuple[int, int]) -> None:
    h, w = working_size(native, **kwargs)
    assert (h, w) == expected
    m = kwargs.get("multiple", 32)
    assert h % m == 0 and w % m == 0
    if native[0] >= 2 * m:  # the aspect is kept to within half a multiple of rounding
        assert abs(aspect_change(native, (h, w))) <= (m / 2) / h + (m / 2) / w + 1e-12


def test_aspect_change_values() -> None:
    assert aspect_change((480, 752), (416, 640)) == pytest.approx((640 / 416) / (752 / 480) - 1)
    assert aspect_change((480, 752), (416, 640)) == pytest.approx(-0.0180, abs=1e-4)
    assert aspect_change((376, 1241), (192, 640)) == pytest.approx(0.00990, abs=1e-4)


def test_intrinsics_follow_the_resize() -> None:
    native = (480, 752)
    K = intrinsics_matrix(458.654, 457.296, 367.215, 248.375, dtype=torch.float64)
    hw = working_size(native, width=640)
    K_w = working_intrinsics(K, native, hw)
    _, K_ref = resize_with_intrinsics(torch.zeros(1, *native), K[0], *hw)
    assert torch.allclose(K_w[0], K_ref)
    # a 3-D point lands where the resize moves its native projection: u' = (u + 0.5) * W'/W - 0.5
    point = torch.tensor([[[0.4, -0.3, 2.5]]], dtype=torch.float64)
    uv, _ = project_points(point, K)
    uv_w, _ = project_points(point, K_w)
    assert float(uv_w[0, 0, 0]) == pytest.approx((float(uv[0, 0, 0]) + 0.5) * hw[1] / native[1] - 0.5, abs=1e-9)
    assert float(uv_w[0, 0, 1]) == pytest.approx((float(uv[0, 0, 1]) + 0.5) * hw[0] / native[0] - 0.5, abs=1e-9)


def test_errors() -> None:
    with pytest.raises(ValueError, match="either a target width or a scale factor"):
        working_size((480, 752))
    with pytest.raises(ValueError, match="either a target width or a scale factor"):
        working_size((480, 752), width=640, scale=0.5)
    with pytest.raises(ValueError, match="scale factor must be positive"):
        working_size((480, 752), scale=0)
    with pytest.raises(ValueError, match="target width must be positive"):
        working_size((480, 752), width=-1)
