"""Resize and crop images together with their intrinsics, so 3-D points keep projecting onto the same content.

Convention:
    - Images are (C,H,W) or (B,C,H,W) float; intrinsics (3,3) or (B,3,3) in pixels of the image they describe.
    - Resizing is bilinear with ``align_corners=False`` and no antialiasing (the KITTI/monodepth2 practice);
      the intrinsics follow :func:`dfvo.geometry.camera.resize_intrinsics`, exact for that resize
      (``cx' = (cx + 0.5) * W'/W - 0.5``).
    - Cropping keeps rows ``top .. top+height-1`` and columns ``left .. left+width-1``; the principal point
      shifts by ``(-left, -top)``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from dfvo.geometry.camera import crop_intrinsics, resize_intrinsics


def _check(image: torch.Tensor, K: torch.Tensor) -> None:
    if image.ndim not in (3, 4):
        raise ValueError(f"image must be (C,H,W) or (B,C,H,W), got shape {tuple(image.shape)}")
    if K.shape[-2:] != (3, 3) or K.ndim != image.ndim - 1:
        raise ValueError(f"K must be (3,3) for a (C,H,W) image or (B,3,3) for (B,C,H,W); got K {tuple(K.shape)} "
                         f"with image {tuple(image.shape)}")


def resize_image(image: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Bilinear resize (``align_corners=False``, no antialias) of a (C,H,W) or (B,C,H,W) image."""
    if image.shape[-2:] == (height, width):
        return image
    batched = image if image.ndim == 4 else image.unsqueeze(0)
    out = F.interpolate(batched, size=(height, width), mode="bilinear", align_corners=False, antialias=False)
    return out if image.ndim == 4 else out.squeeze(0)


def resize_with_intrinsics(image: torch.Tensor, K: torch.Tensor, height: int,
                           width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Resize an image to (height, width) and return it with its updated intrinsics.

    Args:
        image: (C,H,W) or (B,C,H,W).
        K: (3,3) or (B,3,3) intrinsics of ``image``.
        height: output rows.
        width: output columns.

    Returns:
        The resized image (C,height,width) / (B,C,height,width) and its intrinsics (same shape as ``K``).
    """
    _check(image, K)
    if height <= 0 or width <= 0:
        raise ValueError(f"resize target must be positive, got height={height}, width={width}")
    src_hw = (int(image.shape[-2]), int(image.shape[-1]))
    return resize_image(image, height, width), resize_intrinsics(K, src_hw, (height, width))


def crop_with_intrinsics(image: torch.Tensor, K: torch.Tensor, top: int, left: int, height: int,
                         width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Crop ``image[..., top:top+height, left:left+width]`` and shift the principal point accordingly.

    Args:
        image: (C,H,W) or (B,C,H,W).
        K: (3,3) or (B,3,3) intrinsics of ``image``.
        top: first kept row; left: first kept column; height, width: size of the crop.

    Returns:
        The cropped image and its intrinsics.
    """
    _check(image, K)
    H, W = image.shape[-2:]
    if top < 0 or left < 0 or height <= 0 or width <= 0 or top + height > H or left + width > W:
        raise ValueError(f"crop rows {top}..{top + height} / cols {left}..{left + width} do not fit an image of "
                         f"{H}x{W}")
    return image[..., top:top + height, left:left + width], crop_intrinsics(K, top, left)


def check_working_size(height: int | None, width: int | None, what: str) -> tuple[int, int] | None:
    """Validate an optional (height, width) setting: both or neither, positive."""
    if height is None and width is None:
        return None
    if height is None or width is None or height <= 0 or width <= 0:
        raise ValueError(f"{what}: height and width must both be positive integers or both None, "
                         f"got height={height}, width={width}")
    return int(height), int(width)
