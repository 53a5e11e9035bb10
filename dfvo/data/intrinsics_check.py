"""Plausibility checks of camera intrinsics, shared by every reader (folder, EuRoC, TUM RGB-D, video, KITTI).

A wrong number in the intrinsics does not crash visual odometry: it makes every frame fall back to PnP or
drift without a word. These checks turn the common mistakes (a principal point from another resolution, a
focal length in millimetres or normalised units, fx and cx swapped, a distortion list of the wrong length)
into one line that names the setting, its value and what was expected.

Convention:
    - ``fx, fy, cx, cy`` are in pixels of an image ``width`` x ``height``; pixel centres at integer
      coordinates, so the image spans ``-0.5 .. width - 0.5`` and the check asks ``0 < cx < width``.
    - ``model="pinhole"``: OpenCV radial-tangential distortion ``[k1, k2, p1, p2(, k3(, k4, k5, k6))]``
      (4, 5 or 8 coefficients). ``model="fisheye"``: equidistant (Kannala-Brandt) ``[k1, k2, k3, k4]``; the
      upper limit of the field of view is lifted (fisheye lenses see 180 degrees and more).
    - The horizontal field of view of the pinhole part is ``2 atan(width / (2 fx))``; the plausible range is
      10..170 degrees (a 10-degree lens is a long telephoto; beyond 170 degrees the pinhole focal length is
      under 5 % of the width, the signature of focal lengths in millimetres or normalised units).
    - ``fx / fy`` must lie in 0.5..2 (square pixels give 1; anamorphic video stays well inside).
    - A principal point farther than a quarter of the width (height) from the image centre ``((w-1)/2, (h-1)/2)``
      is logged as a warning, not refused: real lenses sit within a few percent of the centre, but crops exist. It
      is the signature of intrinsics from another resolution (frames downscaled by 2 with full-resolution
      intrinsics put the principal point at the right and bottom edges).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from typing import Any

__all__ = ["IntrinsicsError", "RADTAN_COUNTS", "FISHEYE_COUNTS", "check_intrinsics", "check_matrix",
           "horizontal_fov_deg", "principal_point_offset"]

RADTAN_COUNTS: tuple[int, ...] = (4, 5, 8)
FISHEYE_COUNTS: tuple[int, ...] = (4,)
HFOV_RANGE_DEG: tuple[float, float] = (10.0, 170.0)
FX_FY_RATIO_RANGE: tuple[float, float] = (0.5, 2.0)
PRINCIPAL_POINT_WARN_OFFSET = 0.25  # fraction of the side beyond which an off-centre principal point is warned about

log = logging.getLogger("dfvo.data")


class IntrinsicsError(ValueError):
    """Intrinsics that cannot describe the frames (the message names the setting, its value and the expectation)."""


def horizontal_fov_deg(fx: float, width: int) -> float:
    """Horizontal field of view in degrees of a pinhole camera with focal length ``fx`` (pixels) and ``width``."""
    return math.degrees(2.0 * math.atan(width / (2.0 * fx)))


def _number(value: Any, name: str, where: str) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise IntrinsicsError(f"{name}={value!r}{where} is not a number (expected pixels)") from None
    if not math.isfinite(out):
        raise IntrinsicsError(f"{name}={value!r}{where} is not finite (expected pixels)")
    return out


def check_intrinsics(fx: Any, fy: Any, cx: Any, cy: Any, width: int, height: int, dist: Any = None, *,
                     model: str = "pinhole", names: Sequence[str] = ("data.fx", "data.fy", "data.cx", "data.cy"),
                     dist_name: str = "data.dist", source: str | None = None
                     ) -> tuple[float, float, float, float, list[float] | None]:
    """Check pinhole intrinsics (and distortion) against the image they describe; return them as floats.

    Args:
        fx, fy, cx, cy: focal lengths and principal point in pixels of the ``width`` x ``height`` image.
        width, height: size of the image the intrinsics are for (the stored frames, before any resize).
        dist: None, or the distortion coefficients (see module docstring for the counts per ``model``).
        model: ``"pinhole"`` (radial-tangential distortion) or ``"fisheye"`` (equidistant).
        names: how the four values are called where the user set them (config keys, or YAML fields).
        dist_name: how the distortion list is called.
        source: optional file or folder the values came from, quoted in the message.

    Returns:
        ``(fx, fy, cx, cy, dist)`` as floats (``dist`` a list of floats, or None).

    Raises:
        IntrinsicsError: a value is not a finite number, a focal length is not positive, the principal point lies
            outside the image, the field of view or ``fx/fy`` is implausible, the distortion count is wrong.
    """
    if model not in ("pinhole", "fisheye"):
        raise IntrinsicsError(f"camera model {model!r}; expected 'pinhole' (radial-tangential) or 'fisheye'")
    where = f" in {source}" if source else ""
    n_fx, n_fy, n_cx, n_cy = names
    fx, fy, cx, cy = (_number(v, n, where) for v, n in zip((fx, fy, cx, cy), names))
    width, height = int(width), int(height)
    for value, name in ((fx, n_fx), (fy, n_fy)):
        if value <= 0:
            raise IntrinsicsError(f"{name}={value:g}{where} must be positive (a focal length in pixels)")
    for value, name, size, what, short in ((cx, n_cx, width, "wide", "cx"), (cy, n_cy, height, "high", "cy")):
        if not 0.0 < value < size:
            raise IntrinsicsError(f"{name}={value:g}{where} is outside the {size}-px-{what} image "
                                  f"(expected 0 < {short} < {size}; intrinsics are in pixels of the stored frames)")
    ratio = fx / fy
    lo, hi = FX_FY_RATIO_RANGE
    if not lo <= ratio <= hi:
        raise IntrinsicsError(f"{n_fx}={fx:g} and {n_fy}={fy:g}{where}: fx/fy = {ratio:.3g}, expected {lo:g}..{hi:g} "
                              "(nearly square pixels; are the values swapped or from different resolutions?)")
    fov = horizontal_fov_deg(fx, width)
    lo, hi = HFOV_RANGE_DEG
    if fov < lo or (fov > hi and model == "pinhole"):
        raise IntrinsicsError(f"{n_fx}={fx:g}{where} gives a {fov:.1f}-degree horizontal field of view on the "
                              f"{width}-px-wide image; expected {lo:g}..{hi:g} degrees (focal length in pixels, "
                              "not millimetres or normalised units)")
    _warn_off_centre(cx, cy, width, height, n_cx, n_cy, where)
    return fx, fy, cx, cy, _check_dist(dist, model, dist_name, where)


def principal_point_offset(cx: float, cy: float, width: int, height: int) -> tuple[float, float]:
    """Offset in pixels of ``(cx, cy)`` from the centre ``((width-1)/2, (height-1)/2)`` of the image."""
    return cx - (width - 1) / 2.0, cy - (height - 1) / 2.0


def _warn_off_centre(cx: float, cy: float, width: int, height: int, n_cx: str, n_cy: str, where: str) -> None:
    dx, dy = principal_point_offset(cx, cy, width, height)
    if abs(dx) <= PRINCIPAL_POINT_WARN_OFFSET * width and abs(dy) <= PRINCIPAL_POINT_WARN_OFFSET * height:
        return
    log.warning("%s=%g, %s=%g%s: the principal point is %+.0f px, %+.0f px from the centre of the %dx%d image "
                "(%.0f %% of the width, %.0f %% of the height; lenses are within a few %%): are the intrinsics from "
                "another resolution (frames resized or cropped after calibration)? Intrinsics are in pixels of the "
                "stored frames", n_cx, cx, n_cy, cy, where, dx, dy, width, height, 100 * abs(dx) / width,
                100 * abs(dy) / height)


def _check_dist(dist: Any, model: str, name: str, where: str) -> list[float] | None:
    if dist is None:
        return None
    if isinstance(dist, str | bytes) or not hasattr(dist, "__len__"):
        raise IntrinsicsError(f"{name}={dist!r}{where} must be a list of numbers, e.g. [k1, k2, p1, p2]")
    values = [_number(v, f"{name}[{i}]", where) for i, v in enumerate(dist)]
    counts = RADTAN_COUNTS if model == "pinhole" else FISHEYE_COUNTS
    if len(values) not in counts:
        expected = ("[k1, k2, p1, p2], [k1, k2, p1, p2, k3] or [k1, k2, p1, p2, k3, k4, k5, k6] (OpenCV "
                    "radial-tangential)" if model == "pinhole" else "[k1, k2, k3, k4] (equidistant fisheye)")
        raise IntrinsicsError(f"{name}{where} has {len(values)} coefficients; expected {expected}")
    return values


def check_matrix(K: Any, width: int, height: int, *, source: str | None = None, dist: Any = None,
                 model: str = "pinhole") -> tuple[float, float, float, float, list[float] | None]:
    """:func:`check_intrinsics` on a (3,3) matrix (numpy or torch), naming the entries ``fx fy cx cy``.

    Intended for readers whose intrinsics come from a file (KITTI ``calib.txt``: pass ``source=path``).
    The skew ``K[0,1]`` is not checked.
    """
    rows = [[float(v) for v in row] for row in (K.tolist() if hasattr(K, "tolist") else K)]
    if len(rows) != 3 or any(len(r) != 3 for r in rows):
        raise IntrinsicsError(f"intrinsics{' in ' + source if source else ''} must be a 3x3 matrix")
    return check_intrinsics(rows[0][0], rows[1][1], rows[0][2], rows[1][2], width, height, dist, model=model,
                            names=("fx", "fy", "cx", "cy"), dist_name="dist", source=source)
