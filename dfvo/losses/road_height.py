"""Camera-height loss: the road pixels of a predicted depth map put on a plane at the rig's known height.

Stereo photometric losses teach metric depth through the baseline alone, whose disparity is a few pixels at road range
(at 320x96 a road point 20 m ahead shifts ~2 px between the KITTI cameras), and a network trained on one drive learns
little about where the road is in metres. A car's camera has a known height ``H`` above the road (KITTI: 1.65 m);
every road pixel's depth then follows from its ray and the road plane's normal: ``z = H / (n . K^-1 [u, v, 1])``.
The loss is the log-depth L1 against that depth, ``|log(n . X) - log H|`` with ``X = z K^-1 [u, v, 1]`` the pixel's
point, averaged over the road pixels. The plane (its normal ``n`` and which pixels lie on it) comes from the network's
own depth (a robust fit, no gradient; :mod:`dfvo.training.depth_module`), so the loss moves the road to the right
height without choosing its tilt, and pixels off the plane (cars, kerbs) are not pulled onto it.

Convention:
    depth (B,1,H,W) metres; K (B,3,3) at depth's size; normal (B,3) unit, pointing down towards the road (``n_y > 0``,
    camera frame x right, y down, z forward); road (B,1,H,W) bool, the pixels on the plane; camera_height (B,) metres,
    ``<= 0`` for a sample without one (it adds nothing).
"""

from __future__ import annotations

import torch
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE
from kornia.geometry import create_meshgrid
from kornia.geometry.conversions import convert_points_to_homogeneous

__all__ = ["road_height_log_l1"]


def road_height_log_l1(depth: torch.Tensor, K: torch.Tensor, normal: torch.Tensor, road: torch.Tensor,
                       camera_height: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean over the road pixels of ``|log(n . X) - log H|``, ``X`` the pixel's point at its predicted depth.

    Args:
        depth: (B,1,H,W) predicted depth, positive (metres).
        K: (B,3,3) intrinsics at depth's resolution.
        normal: (B,3) the road plane's unit normal pointing down (towards the road).
        road: (B,1,H,W) bool, the pixels on the road plane.
        camera_height: (B,) the camera's true height above the road (metres); ``<= 0``: none for that sample.

    Returns:
        ``(loss, count)``: the scalar loss (0 when no pixel counts; it still carries ``depth``'s graph) and the number
        of pixels it averages (a scalar tensor). A pixel counts where ``road`` holds, its sample has a height and its
        ray meets the plane in front of the camera (``n . K^-1 [u, v, 1] > 0``).
    """
    KORNIA_CHECK_SHAPE(depth, ["B", "1", "H", "W"])
    B, _, H, W = depth.shape
    KORNIA_CHECK(K.shape == (B, 3, 3), f"road_height_log_l1: K {tuple(K.shape)}; expected ({B}, 3, 3)")
    KORNIA_CHECK(normal.shape == (B, 3), f"road_height_log_l1: normal {tuple(normal.shape)}; expected ({B}, 3)")
    KORNIA_CHECK(road.shape == depth.shape, f"road_height_log_l1: road {tuple(road.shape)} must have depth's shape "
                                            f"{tuple(depth.shape)}")
    KORNIA_CHECK(camera_height.shape == (B,), f"road_height_log_l1: camera_height {tuple(camera_height.shape)}; "
                                              f"expected ({B},)")
    grid = create_meshgrid(H, W, normalized_coordinates=False, device=depth.device, dtype=depth.dtype)  # (1,H,W,2)
    pix = convert_points_to_homogeneous(grid)  # (1,H,W,3): (u, v, 1)
    rays = torch.einsum("bij,bhwj->bhwi", torch.linalg.inv(K.to(depth.dtype)), pix.expand(B, -1, -1, -1))  # z = 1
    along = (rays * normal.to(depth.dtype)[:, None, None]).sum(-1)[:, None]  # (B,1,H,W): n . ray
    h_true = camera_height.to(depth.dtype)[:, None, None, None]
    mask = road.bool() & (along > 1e-6) & (h_true > 0)
    height = depth.clamp_min(1e-6) * along.clamp_min(1e-6)  # n . X, the pixel's point's distance below the camera
    err = (height.log() - h_true.clamp_min(1e-6).log()).abs()
    count = mask.sum()
    loss = torch.where(mask, err, torch.zeros_like(err)).sum() / count.clamp_min(1)
    return loss, count
