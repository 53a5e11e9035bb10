"""The working size of a sequence: keep the frames' aspect ratio, from a target width or a scale factor.

Convention:
    - Sizes are ``(height, width)`` in pixels. Both sides are rounded to the nearest multiple of ``multiple``
      (default 32, at least one multiple): the ResNet depth encoder downsamples five times and refuses other
      sizes (``dfvo.models.resnet``), and the flow network resizes its input to multiples of 32 internally
      (``dfvo.models.flow_net.MULTIPLE``), so a multiple of 32 is the size both networks see unchanged.
      ``multiple=8`` keeps the aspect closer for sources without a network (``flow=oracle``, ``flow=dis``).
    - Rounding the two sides separately leaves a small aspect change; the intrinsics follow each axis exactly
      (:func:`dfvo.geometry.camera.resize_intrinsics`), so geometry stays exact and only the pixels are a little
      non-square. :func:`aspect_change` reports it (relative change of width/height).
"""

from __future__ import annotations

import math

import torch

from dfvo.geometry.camera import resize_intrinsics

__all__ = ["working_size", "working_intrinsics", "aspect_change", "TRAINING_ASPECT"]

TRAINING_ASPECT = 640 / 192  # width/height the shipped networks were trained at (KITTI 640x192)


def _round_to(value: float, multiple: int) -> int:
    return max(multiple, int(math.floor(value / multiple + 0.5)) * multiple)  # halves round up


def working_size(native_hw: tuple[int, int], *, width: int | None = None, scale: float | None = None,
                 multiple: int = 32) -> tuple[int, int]:
    """Working ``(height, width)`` that keeps the aspect ratio of ``native_hw``.

    Args:
        native_hw: (height, width) of the stored frames.
        width: target width in pixels (rounded to ``multiple``); the height follows the aspect ratio.
        scale: or a scale factor applied to both sides (0.5 halves the frames).
        multiple: both sides are rounded to the nearest multiple of this (>= 1; 32 for the networks).

    Returns:
        (height, width), both positive multiples of ``multiple``.

    Raises:
        ValueError: neither or both of ``width`` and ``scale`` given, non-positive values.

    Example:
        EuRoC 752x480 at ``width=640``: ``480 * 640 / 752 = 408.5`` -> (416, 640), aspect 1.538 vs 1.567 (-1.8 %).
    """
    h0, w0 = int(native_hw[0]), int(native_hw[1])
    if h0 <= 0 or w0 <= 0:
        raise ValueError(f"native size must be positive, got {native_hw}")
    if int(multiple) < 1:
        raise ValueError(f"multiple must be >= 1, got {multiple}")
    if (width is None) == (scale is None):
        raise ValueError(f"give either a target width or a scale factor, got width={width}, scale={scale}")
    if width is not None:
        if width <= 0:
            raise ValueError(f"target width must be positive, got {width}")
        w = _round_to(float(width), multiple)
        return _round_to(h0 * w / w0, multiple), w
    if scale <= 0:
        raise ValueError(f"scale factor must be positive, got {scale}")
    return _round_to(h0 * scale, multiple), _round_to(w0 * scale, multiple)


def working_intrinsics(K: torch.Tensor, native_hw: tuple[int, int], working_hw: tuple[int, int]) -> torch.Tensor:
    """Intrinsics (3,3) or (B,3,3) of the frames resized from ``native_hw`` to ``working_hw`` (exact per axis)."""
    return resize_intrinsics(K, tuple(native_hw), tuple(working_hw))


def aspect_change(native_hw: tuple[int, int], working_hw: tuple[int, int]) -> float:
    """Relative change of the aspect ratio width/height from ``native_hw`` to ``working_hw`` (0 = kept)."""
    return (working_hw[1] / working_hw[0]) / (native_hw[1] / native_hw[0]) - 1.0
