"""Warp a source view into the target view by the target's depth and the relative pose.

Convention:
    ``T_source_target`` (B,4,4) maps points of the target camera into the source camera (for the stereo
    partner of a left target: ``T_right_left``). Pixel centres as in :mod:`dfvo.geometry.camera`;
    sampling with ``grid_sample(align_corners=True)`` at ``2u/(W-1) - 1``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from kornia.core.check import KORNIA_CHECK_SHAPE

from dfvo.geometry.camera import backproject_points, pixel_grid, project_points, transform_points
from dfvo.matching.flow_warp import normalise_pixels


@dataclass
class Reprojection:
    """Result of :func:`reproject`.

    Attributes:
        warped: (B,C,H,W) source sampled at the projection of each target pixel.
        valid: (B,1,H,W) bool, the projection lies in front of the source camera and inside its image.
        depth_in_source: (B,1,H,W) z of each target pixel's 3-D point in the source camera.
        grid: (B,H,W,2) normalised sampling grid (reuse it to sample other maps of the source view).
    """

    warped: torch.Tensor
    valid: torch.Tensor
    depth_in_source: torch.Tensor
    grid: torch.Tensor


@dataclass
class SourceRays:
    """The target's pixel rays seen from the source camera, which do not depend on the depth: a target pixel at depth
    ``d`` is the source-camera point ``d * ray + t`` (:func:`source_rays`; one per view pair, reused at every scale).

    Attributes:
        rays: (B,H*W,3) ``R K^-1 [u, v, 1]`` of every target pixel (row-major), ``R`` the rotation of
            ``T_source_target``.
        t: (B,1,3) its translation.
    """

    rays: torch.Tensor
    t: torch.Tensor


def source_rays(T_source_target: torch.Tensor, K: torch.Tensor, height: int, width: int) -> SourceRays:
    """:class:`SourceRays` of a (height, width) target view for ``T_source_target`` (B,4,4) and ``K`` (B,3,3)."""
    KORNIA_CHECK_SHAPE(T_source_target, ["B", "4", "4"])
    KORNIA_CHECK_SHAPE(K, ["B", "3", "3"])
    B = K.shape[0]
    grid = pixel_grid(height, width, K.device, K.dtype).reshape(1, height * width, 2).expand(B, -1, -1)
    unit = backproject_points(grid, torch.ones(B, height * width, device=K.device, dtype=K.dtype), K)  # z = 1
    T = T_source_target.to(K.dtype)
    return SourceRays(rays=unit @ T[:, :3, :3].transpose(1, 2), t=T[:, None, :3, 3])


def reproject(source: torch.Tensor, depth_target: torch.Tensor, T_source_target: torch.Tensor,
              K: torch.Tensor, rays: SourceRays | None = None) -> Reprojection:
    """Inverse-warp ``source`` into the target view.

    Args:
        source: (B,C,H,W) source image (or any map of the source view).
        depth_target: (B,1,H,W) depth of the target view.
        T_source_target: (B,4,4) target camera -> source camera.
        K: (B,3,3) intrinsics of both views at this resolution.
        rays: :func:`source_rays` of ``T_source_target`` and ``K`` when several depths are warped with the same pose
            (the scales of a training step): the back-projection and rotation are then done once (the same points to
            float rounding).

    Returns:
        :class:`Reprojection`.
    """
    KORNIA_CHECK_SHAPE(source, ["B", "C", "H", "W"])
    KORNIA_CHECK_SHAPE(depth_target, ["B", "1", "H", "W"])
    KORNIA_CHECK_SHAPE(T_source_target, ["B", "4", "4"])
    KORNIA_CHECK_SHAPE(K, ["B", "3", "3"])
    B, _, H, W = depth_target.shape
    if source.shape[-2:] != (H, W):
        raise ValueError(f"reproject: source {tuple(source.shape)} and depth {tuple(depth_target.shape)} differ")
    if rays is None:
        grid = pixel_grid(H, W, depth_target.device, depth_target.dtype).reshape(1, H * W, 2).expand(B, -1, -1)
        points = transform_points(T_source_target.to(depth_target.dtype),
                                  backproject_points(grid, depth_target.reshape(B, H * W), K))
    else:
        if tuple(rays.rays.shape) != (B, H * W, 3):
            raise ValueError(f"reproject: rays {tuple(rays.rays.shape)} do not fit depth {tuple(depth_target.shape)} "
                             f"(expected ({B}, {H * W}, 3): source_rays of the same pose batch and size)")
        points = torch.addcmul(rays.t, rays.rays, depth_target.reshape(B, H * W, 1))
    pix, z = project_points(points, K)
    u, v = pix[..., 0], pix[..., 1]
    tol = 1e-3  # pixels: border pixels reprojected onto themselves stay inside despite rounding
    valid = ((z > 1e-3) & (u >= -tol) & (u <= W - 1 + tol) & (v >= -tol) & (v <= H - 1 + tol)
             & torch.isfinite(u) & torch.isfinite(v))
    norm = normalise_pixels(pix, H, W)
    norm = torch.where(valid[..., None], norm, torch.full_like(norm, 2.0)).reshape(B, H, W, 2)
    warped = F.grid_sample(source, norm, mode="bilinear", padding_mode="border", align_corners=True)
    return Reprojection(warped, valid.reshape(B, 1, H, W), z.reshape(B, 1, H, W), norm)
