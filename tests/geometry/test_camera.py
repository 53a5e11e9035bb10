"""Camera model: projection round trips, intrinsics under resize/crop against resampled images, flow resizing."""

import torch
import torch.nn.functional as F

from dfvo.geometry.camera import (
    backproject_points,
    crop_intrinsics,
    intrinsics_matrix,
    project_points,
    resize_flow,
    resize_intrinsics,
    rigid_flow,
)
from dfvo.geometry.se3 import pose_from_axis_angle


def test_backproject_project_round_trip():
    K = intrinsics_matrix(718.856, 718.856, 607.1928, 185.2157)
    pix = torch.tensor([[[10.0, 20.0], [600.5, 180.25], [1200.0, 370.0]]])
    depth = torch.tensor([[3.0, 17.5, 80.0]])
    pts = backproject_points(pix, depth, K)
    back, z = project_points(pts, K)
    assert torch.allclose(back, pix, atol=1e-4)
    assert torch.allclose(z, depth)


def test_resize_intrinsics_matches_resampled_image():
    """A bright dot rendered at the projection of a 3-D point stays at the projection after resizing."""
    H, W = 370, 1226
    K = intrinsics_matrix(718.856, 718.856, 607.1928, 185.2157)
    point = torch.tensor([[[2.0, -0.5, 10.0]]])
    (u, v), _ = project_points(point, K)[0][0, 0], None
    # a smooth blob centred on the projection; its intensity centroid is its centre
    vv, uu = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64),
                            indexing="ij")
    blob = torch.exp(-((uu - u) ** 2 + (vv - v) ** 2) / (2 * 6.0**2))[None, None]
    dst = (192, 640)
    small = F.interpolate(blob, size=dst, mode="bilinear", align_corners=False)[0, 0]
    sv, su = torch.meshgrid(torch.arange(dst[0], dtype=torch.float64), torch.arange(dst[1], dtype=torch.float64),
                            indexing="ij")
    cu = (small * su).sum() / small.sum()
    cv = (small * sv).sum() / small.sum()
    K2 = resize_intrinsics(K, (H, W), dst)
    (u2, v2) = project_points(point, K2)[0][0, 0]
    assert abs(float(u2) - float(cu)) < 0.02 and abs(float(v2) - float(cv)) < 0.02


def test_crop_intrinsics_shifts_principal_point():
    K = intrinsics_matrix(500.0, 500.0, 320.0, 96.0)
    point = torch.tensor([[[1.0, 0.3, 7.0]]])
    pix, _ = project_points(point, K)
    pix_c, _ = project_points(point, crop_intrinsics(K, top=20, left=33))
    assert torch.allclose(pix_c, pix - torch.tensor([33.0, 20.0]), atol=1e-5)


def test_rigid_flow_matches_point_motion():
    K = intrinsics_matrix(300.0, 300.0, 31.5, 23.5)
    depth = torch.full((1, 1, 48, 64), 5.0)
    T = pose_from_axis_angle(torch.tensor([[0.0, 0.02, 0.0]]), torch.tensor([[0.1, 0.0, -0.5]]))
    flow = rigid_flow(depth, T, K)
    # hand check for pixel (u=10, v=7)
    p = backproject_points(torch.tensor([[[10.0, 7.0]]]), torch.tensor([[5.0]]), K)
    q = p @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3]
    uv, _ = project_points(q, K)
    assert torch.allclose(flow[0, :, 7, 10], uv[0, 0] - torch.tensor([10.0, 7.0]), atol=1e-4)


def test_resize_flow_is_the_flow_of_the_resized_camera():
    """A rigid flow resized to twice the size (vectors rescaled) is the rigid flow of the same motion seen by the
    resized camera (intrinsics from resize_intrinsics), up to the bilinear interpolation of a smooth field."""
    K = intrinsics_matrix(300.0, 300.0, 31.5, 23.5)
    T = pose_from_axis_angle(torch.tensor([[0.0, 0.02, 0.0]]), torch.tensor([[0.1, 0.0, -0.5]]))
    small = rigid_flow(torch.full((1, 1, 48, 64), 5.0), T, K)
    big = rigid_flow(torch.full((1, 1, 96, 128), 5.0), T, resize_intrinsics(K, (48, 64), (96, 128)))
    up = resize_flow(small, (96, 128))
    assert up.shape == big.shape and float(big.abs().max()) > 5.0  # pixels, so the rescaling matters
    assert float((up - big)[..., 2:-2, 2:-2].abs().max()) < 0.01
    assert resize_flow(small, (48, 64)) is small
