"""Depth hints: a classical stereo matcher's depth for each left image of a rectified stereo pair (Watson et al.,
"Self-Supervised Monocular Depth Hints", ICCV 2019), computed once and kept in the frame cache.

OpenCV's semi-global block matching (``cv2.StereoSGBM``, the ``classical`` extra) runs on the greyscale pair at its
native resolution; disparity ``d`` (pixels) becomes depth ``fx * baseline / d`` (metres); pixels SGBM rejects
(uniqueness, speckle filter, left-right check) or with ``d < 1`` px are 0, "no hint". The depth map is then brought
to the working size by nearest-neighbour sampling (no blending of depths across edges; 0 stays 0). Training uses a
hint only where it reprojects the stereo partner better than the network's own depth
(:class:`dfvo.training.depth_module.DepthPoseModule`, ``model.w_depth_hints``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

__all__ = ["SGBM_SETTINGS", "sgbm_depth", "hint_depth"]

# Matcher settings (native KITTI resolution, 1242x375): 192 disparities reach ~2 m at fx 721 and a 0.54 m baseline.
SGBM_SETTINGS = {"minDisparity": 0, "numDisparities": 192, "blockSize": 5, "P1": 8 * 25, "P2": 32 * 25,
                 "uniquenessRatio": 10, "speckleWindowSize": 100, "speckleRange": 2, "disp12MaxDiff": 1}


def _cv2():
    try:
        import cv2
    except ImportError as err:  # pragma: no cover - the dev install has it
        raise ImportError("depth hints (data.depth_hints=true) need OpenCV: pip install \"dfvo[classical]\"") from err
    return cv2


def sgbm_depth(left: np.ndarray, right: np.ndarray, fx: float, baseline: float) -> np.ndarray:
    """Depth (H,W) float32 in metres of the left view of a rectified pair of greyscale uint8 images (H,W); 0 where
    the matcher gives no disparity of at least one pixel.

    Args:
        left, right: (H,W) uint8 images of the left and right cameras. fx: focal length in pixels (of these images).
        baseline: distance between the cameras in metres (> 0).
    """
    cv2 = _cv2()
    sgbm = cv2.StereoSGBM_create(**SGBM_SETTINGS)
    disp = sgbm.compute(np.ascontiguousarray(left), np.ascontiguousarray(right)).astype(np.float32) / 16.0
    valid = disp >= 1.0
    return np.where(valid, fx * baseline / np.maximum(disp, 1.0), 0.0).astype(np.float32)


def _grey(path: Path) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(im.convert("L"))


def hint_depth(left_path: Path, right_path: Path, fx_native: float, baseline: float,
               size: tuple[int, int]) -> torch.Tensor:
    """The depth hint (1,H,W) float32 of the left image of a stereo pair of files, at the working ``size`` (H,W)."""
    depth = torch.from_numpy(sgbm_depth(_grey(left_path), _grey(right_path), fx_native, baseline))
    return F.interpolate(depth[None, None], size=size, mode="nearest")[0]
