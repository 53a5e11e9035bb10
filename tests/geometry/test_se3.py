"""SE(3) helpers: closed-form inverse against the general matrix inverse, any batch shape and dtype."""

import pytest
import torch

from dfvo.geometry.se3 import direction_error_deg, pose_from_axis_angle, rotation_error_deg, se3_inverse


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("batch", [(), (5,), (2, 3)])
def test_se3_inverse_matches_matrix_inverse(dtype, batch):
    g = torch.Generator().manual_seed(0)
    n = int(torch.tensor(batch).prod()) if batch else 1
    T = pose_from_axis_angle(torch.randn(n, 3, generator=g, dtype=torch.float64),
                             10 * torch.randn(n, 3, generator=g, dtype=torch.float64)).reshape(*batch, 4, 4).to(dtype)
    inv = se3_inverse(T)
    assert inv.shape == T.shape and inv.dtype == dtype
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    assert torch.allclose(inv, torch.linalg.inv(T), atol=tol * 10)
    eye = torch.eye(4, dtype=dtype).expand_as(T)
    assert torch.allclose(T @ inv, eye, atol=tol * 10) and torch.allclose(inv @ T, eye, atol=tol * 10)
    assert torch.equal(inv[..., 3, :], eye[..., 3, :])  # exact last row


def test_se3_inverse_of_relative_motion_and_bad_shape():
    # T_prev_cur = inv(T_w_prev) @ T_w_cur and T_cur_prev = inv(T_prev_cur)
    T_w_prev = pose_from_axis_angle(torch.tensor([[0.1, 0.2, 0.3]]).double(), torch.tensor([[1.0, 2.0, 3.0]]).double())
    T_w_cur = pose_from_axis_angle(torch.tensor([[0.1, 0.25, 0.3]]).double(), torch.tensor([[1.0, 2.0, 4.0]]).double())
    T_prev_cur = se3_inverse(T_w_prev) @ T_w_cur
    assert torch.allclose(se3_inverse(T_prev_cur), se3_inverse(T_w_cur) @ T_w_prev, atol=1e-12)
    with pytest.raises(Exception, match="se3_inverse"):
        se3_inverse(torch.zeros(3, 4))


def test_angle_errors():
    R = pose_from_axis_angle(torch.tensor([[0.0, 0.0, 0.1]]).double(), torch.zeros(1, 3).double())[:, :3, :3]
    assert torch.allclose(rotation_error_deg(R, torch.eye(3, dtype=torch.float64)[None]),
                          torch.tensor([0.1 * 180 / torch.pi], dtype=torch.float64))
    a, b = torch.tensor([1.0, 0.0, 0.0]), torch.tensor([2.0, 2.0, 0.0])
    assert abs(float(direction_error_deg(a, b)) - 45.0) < 1e-4
