"""Pinhole camera model: intrinsics and flow fields under resize and crop, pixel grids, back-projection and projection.

Convention:
    - Intrinsics ``K`` are (B,3,3) in pixels of the tensor they describe.
    - Pixel coordinates are continuous with the centre of the top-left pixel at (0, 0); pixel (u, v) is
      column u, row v. This is the convention of ``torch.nn.functional.interpolate(...,
      align_corners=False)``: resizing an image by a factor ``s`` maps a continuous coordinate ``u`` to
      ``(u + 0.5) * s - 0.5``. The intrinsics update below follows that map exactly, so a 3-D point
      projects to the same image content before and after resizing. (The DF-VO reference code scales
      ``cx`` by ``s`` alone, which is off by ``(s - 1) / 2`` pixels.)
    - Points in a camera frame are (B,N,3) or depth-maps (B,1,H,W) in metres; camera looks along +z,
      x right, y down.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from kornia.core.check import KORNIA_CHECK_SHAPE
from kornia.geometry import create_meshgrid
from kornia.geometry.camera import unproject_points


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float, batch_size: int = 1,
                      dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Build intrinsics from focal lengths and principal point.

    Convention:
        ``fx, fy, cx, cy`` in pixels -> (B,3,3) ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in ``dtype``.
    """
    K = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=dtype)
    return K.unsqueeze(0).repeat(batch_size, 1, 1)


def resize_intrinsics(K: torch.Tensor, src_hw: tuple[int, int], dst_hw: tuple[int, int]) -> torch.Tensor:
    """Intrinsics of an image resized from ``src_hw`` to ``dst_hw`` (H, W) with ``align_corners=False``.

    Args:
        K: (B,3,3) or (3,3) intrinsics of the source image.
        src_hw: source (height, width) in pixels.
        dst_hw: destination (height, width) in pixels.

    Returns:
        Intrinsics of the resized image, same shape as ``K``:
        ``fx' = fx*sx``, ``cx' = (cx + 0.5)*sx - 0.5`` (and likewise for y) with ``sx = W'/W``.

    Convention:
        Pixel centres at integer coordinates, ``align_corners=False`` resampling (see the module docstring).
    """
    sy = dst_hw[0] / src_hw[0]
    sx = dst_hw[1] / src_hw[1]
    out = K.clone()
    out[..., 0, 0] = K[..., 0, 0] * sx
    out[..., 0, 1] = K[..., 0, 1] * sx
    out[..., 0, 2] = (K[..., 0, 2] + 0.5) * sx - 0.5
    out[..., 1, 1] = K[..., 1, 1] * sy
    out[..., 1, 2] = (K[..., 1, 2] + 0.5) * sy - 0.5
    return out


def crop_intrinsics(K: torch.Tensor, top: int, left: int) -> torch.Tensor:
    """Intrinsics after cropping an image so that pixel (left, top) becomes (0, 0).

    Args:
        K: (B,3,3) or (3,3) intrinsics.
        top: first kept row of the source image.
        left: first kept column of the source image.

    Convention:
        Returns intrinsics of the same shape with ``cx' = cx - left``, ``cy' = cy - top`` (pixels).
    """
    out = K.clone()
    out[..., 0, 2] = K[..., 0, 2] - left
    out[..., 1, 2] = K[..., 1, 2] - top
    return out


def pixel_grid(height: int, width: int, device: torch.device | None = None,
               dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Pixel coordinates of every pixel centre (kornia's ``create_meshgrid`` in pixel units).

    Convention:
        (H,W,2) with ``[..., 0] = u`` (column) and ``[..., 1] = v`` (row), pixel centres at integers.
    """
    return create_meshgrid(height, width, normalized_coordinates=False, device=device, dtype=dtype)[0]


def resize_flow(flow: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """A flow field resized to ``size`` with its vectors in the new pixel units (the one flow resize of the package).

    Convention:
        (B,2,h,w) in pixels of its own size -> (B,2,H,W) in pixels of ``size = (H, W)``: bilinear
        (``align_corners=False``, the module's pixel convention, under which a displacement scales by exactly
        ``W/w``, ``H/h``); the input itself when the size is unchanged.
    """
    h, w = flow.shape[-2:]
    if (h, w) == tuple(size):
        return flow
    out = F.interpolate(flow, size=size, mode="bilinear", align_corners=False)
    scale = torch.tensor([size[1] / w, size[0] / h], dtype=flow.dtype, device=flow.device).view(1, 2, 1, 1)
    return out * scale


def backproject_points(pixels: torch.Tensor, depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Lift pixels with their depths to 3-D points in the camera frame (kornia's ``unproject_points``).

    Args:
        pixels: (B,N,2) pixel coordinates (u, v).
        depth: (B,N) depth (z) of each pixel.
        K: (B,3,3) intrinsics.

    Returns:
        (B,N,3) points ``depth * K^-1 [u, v, 1]``.

    Convention:
        Camera frame of ``K``'s image: +z forward, x right, y down; zero skew assumed.
    """
    KORNIA_CHECK_SHAPE(pixels, ["B", "N", "2"])
    KORNIA_CHECK_SHAPE(depth, ["B", "N"])
    KORNIA_CHECK_SHAPE(K, ["B", "3", "3"])
    return unproject_points(pixels, depth[..., None], K[:, None])


def project_points(points: torch.Tensor, K: torch.Tensor, eps: float = 1e-8) -> tuple[torch.Tensor, torch.Tensor]:
    """Project camera-frame 3-D points to pixels.

    Args:
        points: (B,N,3) points in the camera frame.
        K: (B,3,3) intrinsics.
        eps: smallest depth magnitude used in the division.

    Returns:
        pixels (B,N,2) and depth (B,N). Points behind the camera still get a (meaningless) pixel; use
        ``depth > 0`` to mask them.

    Convention:
        ``[u, v] = [fx x / z + cx, fy y / z + cy]`` (zero skew), camera frame +z forward.
    """
    KORNIA_CHECK_SHAPE(points, ["B", "N", "3"])
    KORNIA_CHECK_SHAPE(K, ["B", "3", "3"])
    z = points[..., 2]
    z_safe = torch.where(z.abs() < eps, torch.full_like(z, eps), z)
    u = K[:, 0, 0, None] * points[..., 0] / z_safe + K[:, 0, 2, None]
    v = K[:, 1, 1, None] * points[..., 1] / z_safe + K[:, 1, 2, None]
    return torch.stack([u, v], dim=-1), z


def transform_points(T_a_b: torch.Tensor, points_b: torch.Tensor) -> torch.Tensor:
    """Map points from frame b into frame a.

    Convention:
        ``T_a_b`` (B,4,4) maps frame-b points into frame a; ``points_b`` (B,N,3) -> (B,N,3) in frame a.
    """
    KORNIA_CHECK_SHAPE(T_a_b, ["B", "4", "4"])
    KORNIA_CHECK_SHAPE(points_b, ["B", "N", "3"])
    return points_b @ T_a_b[:, :3, :3].transpose(1, 2) + T_a_b[:, None, :3, 3]


def rigid_flow(depth: torch.Tensor, T_cur_prev: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Optical flow of a static scene from the previous image to the current one.

    Args:
        depth: (B,1,H,W) depth of the previous image.
        T_cur_prev: (B,4,4) pose mapping points of the previous camera into the current camera
            (``inv(T_w_cur) @ T_w_prev``).
        K: (B,3,3) intrinsics (shared by both images).

    Returns:
        (B,2,H,W) flow prev→cur in pixels: where each pixel of the previous image lands in the current one,
        minus its position.

    Convention:
        "prev"/"cur" name the flow's source and target: for the backward flow pass the current image's depth
        and ``T_prev_cur``.
    """
    KORNIA_CHECK_SHAPE(depth, ["B", "1", "H", "W"])
    B, _, H, W = depth.shape
    grid = pixel_grid(H, W, depth.device, depth.dtype).reshape(1, H * W, 2).expand(B, -1, -1)
    pts_i = backproject_points(grid, depth.reshape(B, H * W), K)
    pix_j, _ = project_points(transform_points(T_cur_prev, pts_i), K)
    return (pix_j - grid).permute(0, 2, 1).reshape(B, 2, H, W)
