"""Classical baseline flow source: OpenCV's DIS optical flow (Kroeger et al. 2016), ``flow=dis``.

The baseline that says what the learning buys: the same interface as the network source, dense forward and
backward flow from OpenCV's Dense Inverse Search on 8-bit grayscale images. OpenCV is an optional extra
(``pip install "dfvo[classical]"``); without it, constructing :class:`DISFlow` fails with one line naming it.

Convention:
    Images (B,3,H,W) float in [0,1] (RGB), converted to 8-bit grayscale with the ITU-R BT.601 weights
    (0.299, 0.587, 0.114), as OpenCV's ``cvtColor`` does. Flow (B,2,H,W) float32 in pixels of the input,
    ``flow_i->j(x)`` = position in j of pixel x of i minus x; forward = prev→cur on prev's pixels, backward =
    cur→prev on cur's pixels. Outputs are on the input's device; DIS itself runs on the CPU.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from kornia.core.check import KORNIA_CHECK, KORNIA_CHECK_SHAPE

from dfvo.sources.config import DisPreset, FlowSourceConfig
from dfvo.validation import choice, choices

__all__ = ["DISFlow", "PRESETS", "MISSING_OPENCV"]

PRESETS = tuple(choices(DisPreset))
MISSING_OPENCV = ('flow=dis needs OpenCV: pip install "dfvo[classical]" (or pip install -e ".[classical]" from a '
                  'checkout)')


def _import_cv2() -> Any:
    try:
        import cv2
    except ImportError:
        raise ImportError(MISSING_OPENCV) from None
    if not hasattr(cv2, "DISOpticalFlow_create"):
        raise ImportError(f"{MISSING_OPENCV}; the installed cv2 ({getattr(cv2, '__version__', '?')}) has no "
                          "DISOpticalFlow_create")
    return cv2


def _to_gray_uint8(images: torch.Tensor) -> np.ndarray:
    """(B,3,H,W) float [0,1] → (B,H,W) uint8 grayscale (BT.601 luma, rounded)."""
    w = torch.tensor([0.299, 0.587, 0.114], dtype=torch.float32).view(1, 3, 1, 1)
    gray = (images.detach().float().cpu().clamp(0, 1) * w).sum(1) * 255.0
    return gray.round().to(torch.uint8).numpy()


class DISFlow:
    """Forward and backward flow from OpenCV's DIS optical flow (one frame pair at a time).

    Args:
        preset: ``"ultrafast"``, ``"fast"`` or ``"medium"`` (OpenCV's ``DISOPTICAL_FLOW_PRESET_*``).
        device: kept for interface parity (outputs follow the input images' device).

    Raises:
        ImportError: OpenCV is not installed (one line naming the ``classical`` extra).
        ValueError: unknown preset.
    """

    name = "dis"

    def __init__(self, preset: DisPreset | str = FlowSourceConfig.preset, device: str = "cpu") -> None:
        preset = choice(DisPreset, preset, "flow.preset")
        cv2 = _import_cv2()
        code = getattr(cv2, f"DISOPTICAL_FLOW_PRESET_{preset.upper()}")
        self.preset = preset
        self.device = torch.device(device)
        self._dis = cv2.DISOpticalFlow_create(code)

    def _calc(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return self._dis.calc(a, b, None)  # (H,W,2) float32: (u, v)

    def __call__(self, images_prev: torch.Tensor, images_cur: torch.Tensor,
                 indices: list[int] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``(flow_fwd, flow_bwd)``, each (B,2,H,W) float32, for images (B,3,H,W) prev and cur (``indices``
        unused)."""
        KORNIA_CHECK_SHAPE(images_prev, ["B", "3", "H", "W"])
        KORNIA_CHECK(images_prev.shape == images_cur.shape,
                     f"flow=dis: images_prev {tuple(images_prev.shape)} and images_cur {tuple(images_cur.shape)} "
                     "differ in shape")
        prev, cur = _to_gray_uint8(images_prev), _to_gray_uint8(images_cur)
        fwd = np.stack([self._calc(p, c) for p, c in zip(prev, cur)])
        bwd = np.stack([self._calc(c, p) for p, c in zip(prev, cur)])
        to = images_prev.device
        return (torch.from_numpy(fwd).permute(0, 3, 1, 2).contiguous().to(to),
                torch.from_numpy(bwd).permute(0, 3, 1, 2).contiguous().to(to))
