"""Image files to tensors, and the errors every real-data loader raises.

Convention:
    - ``read_image`` returns a (3,H,W) float32 tensor in [0,1], RGB. Grayscale files are replicated to three
      channels, alpha is dropped, palette images are expanded. 8-bit files are divided by 255, 16-bit files by 65535
      (by 4095 when no value exceeds it: 12-bit data, :func:`sixteen_bit_to_unit`). ``decode_image`` does the same
      for a file held in memory (a ROS ``CompressedImage``).
    - Image folders are listed in natural order (``frame2`` before ``frame10``), PNG and JPEG only; hidden files
      (names starting with ``.``, such as macOS's ``._000001.png``) are skipped with one warning.
"""

from __future__ import annotations

import io
import logging
import re
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image, UnidentifiedImageError

IMAGE_SUFFIXES: tuple[str, ...] = (".png", ".jpg", ".jpeg")

log = logging.getLogger("dfvo.data")


class DatasetError(ValueError):
    """A dataset on disk is not what the loader expected (the message names the path and the expectation)."""


class DatasetNotFoundError(DatasetError, FileNotFoundError):
    """A file or folder a dataset needs does not exist."""


def require_dir(path: str | Path, what: str) -> Path:
    """Return ``path`` as a Path, raising :class:`DatasetNotFoundError` naming ``what`` when it is no folder."""
    path = Path(path)
    if not path.is_dir():
        raise DatasetNotFoundError(f"{what}: folder {path} does not exist (or is not a folder)")
    return path


def require_file(path: str | Path, what: str) -> Path:
    """Return ``path`` as a Path, raising :class:`DatasetNotFoundError` naming ``what`` when it is no file."""
    path = Path(path)
    if not path.is_file():
        raise DatasetNotFoundError(f"{what}: file {path} does not exist")
    return path


def _natural_key(path: Path) -> list[int | str]:
    return [int(tok) if tok.isdigit() else tok.lower() for tok in re.split(r"(\d+)", path.name)]


def list_images(folder: str | Path, what: str = "image folder") -> list[Path]:
    """All PNG/JPEG files directly inside ``folder``, in natural order; hidden files (``._000001.png``) are skipped
    and reported in one warning. The set is checked before it is trusted: one file per frame name (``000001.png``
    beside ``000001.jpg`` is one frame exported twice) and every link pointing at a file.

    Raises:
        DatasetNotFoundError: ``folder`` does not exist.
        DatasetError: ``folder`` holds no PNG/JPEG file, a frame name twice (two extensions), or a broken link.
    """
    folder = require_dir(folder, what)
    named = [p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES]
    broken = sorted((p.name for p in named if not p.name.startswith(".") and p.is_symlink() and not p.exists()),
                    key=lambda n: _natural_key(Path(n)))
    if broken:
        raise DatasetError(f"{what}: {folder} holds {len(broken)} broken link{'s' if len(broken) > 1 else ''} "
                           f"({', '.join(broken[:3])}{', ...' if len(broken) > 3 else ''}): every frame file must be "
                           "readable (a skipped one would shift every later pose to the wrong frame); fix or remove")
    images = [p for p in named if p.is_file()]
    files = [p for p in images if not p.name.startswith(".")]
    hidden = sorted((p.name for p in images if p.name.startswith(".")), key=lambda n: _natural_key(Path(n)))
    if hidden:
        log.warning("%s: skipped %d hidden file%s in %s (%s%s: names starting with '.', such as the '._' files "
                    "macOS writes beside copied frames, are not frames)", what, len(hidden),
                    "s" if len(hidden) > 1 else "", folder, ", ".join(hidden[:3]), ", ..." if len(hidden) > 3 else "")
    if not files:
        raise DatasetError(f"{what}: folder {folder} contains no images (expected files ending in "
                           f"{', '.join(IMAGE_SUFFIXES)})")
    stems: dict[str, list[str]] = {}
    for p in files:
        stems.setdefault(p.stem, []).append(p.name)
    twice = sorted((names for names in stems.values() if len(names) > 1), key=lambda n: _natural_key(Path(n[0])))
    if twice:
        example = ", ".join(sorted(twice[0]))
        raise DatasetError(f"{what}: {folder} holds {len(twice)} frame name{'s' if len(twice) > 1 else ''} with more "
                           f"than one file (e.g. {example}): one file per frame expected; keep one naming family "
                           "(one extension)")
    return sorted(files, key=_natural_key)


def image_size(path: str | Path) -> tuple[int, int]:
    """(height, width) of an image file, read from its header only."""
    path = require_file(path, "image")
    try:
        with Image.open(path) as im:
            return im.height, im.width
    except (UnidentifiedImageError, OSError) as err:
        raise DatasetError(f"cannot read image {path}: expected a PNG or JPEG file ({err})") from err


def _to_array(im: Image.Image, source: str | Path = "") -> np.ndarray:
    """Pillow image to an (H,W) or (H,W,3) float32 array in [0,1]; ``source`` names it in the notes of
    :func:`_note_once` (16-bit files holding 12-bit data, EXIF orientations)."""
    mode = im.mode
    if mode in ("I;16", "I;16B", "I;16L", "I;16N", "I"):  # "I": 32-bit container some Pillow versions use
        return sixteen_bit_to_unit(np.asarray(im, dtype=np.int32 if mode == "I" else np.uint16), source)
    if mode == "F":
        return np.asarray(im, dtype=np.float32)
    if mode == "1":
        im = im.convert("L")
    elif mode not in ("L", "RGB"):
        im = im.convert("RGB")  # RGBA, LA, P, CMYK, YCbCr ...
    return np.asarray(im, dtype=np.uint8) * np.float32(1.0 / 255.0)


TWELVE_BIT_MAX = 4095
EXIF_ORIENTATION = 0x0112
EXIF_TURNS = {2: "mirrored", 3: "rotated 180 degrees", 4: "flipped", 5: "transposed", 6: "rotated 90 degrees",
              7: "transversed", 8: "rotated 270 degrees"}
_NOTED: set[tuple[str, str]] = set()


def sixteen_bit_to_unit(raw: np.ndarray, source: str | Path = "") -> np.ndarray:
    """16-bit pixel values (any integer array) to float32 in [0,1]: divided by 65535, or by 4095 when none exceeds
    it (12-bit sensor data stored in 16 bits, which 65535 leaves nearly black; noted once per folder of
    ``source``). The one home of the rule for files (:func:`read_image`), arrays (:func:`array_to_image`) and
    bag messages."""
    peak = int(raw.max()) if raw.size else 0
    full = 65535.0
    if 0 < peak <= TWELVE_BIT_MAX:
        full = float(TWELVE_BIT_MAX)
        _note_once(source, "12bit", "16-bit image with values up to %d: read as 12-bit data (divided by 4095, not "
                   "65535, which left it nearly black)", peak)
    return raw.astype(np.float32) * np.float32(1.0 / full)


def _note_once(source: str | Path, kind: str, message: str, *args: object) -> None:
    """Log ``message`` once per folder of ``source`` and ``kind`` (a sequence's frames share their cause)."""
    key = (str(Path(source).parent) if source else "", kind)
    if key in _NOTED:
        return
    _NOTED.add(key)
    log.warning("%s: " + message + " (noted once for its folder)", source or "image", *args)


def _check_orientation(im: Image.Image, source: str | Path) -> None:
    """Name an EXIF orientation other than 1: viewers show such a frame rotated or mirrored, the frames are read as
    stored (as videos are), so the intrinsics must be the stored pixels' and every frame must be stored alike."""
    try:
        orientation = int(im.getexif().get(EXIF_ORIENTATION, 1))
    except (OSError, ValueError, TypeError, SyntaxError):
        return
    if orientation != 1:
        _note_once(source, f"exif{orientation}", "EXIF orientation %d (%s in viewers): frames are read as stored, not "
                   "turned; give the intrinsics of the stored pixels, and store every frame the same way up",
                   orientation, EXIF_TURNS.get(orientation, "turned"))


def _decode(file: str | Path | io.BytesIO, source: str | Path, what: str) -> np.ndarray:
    """An image file (a path, or its bytes) decoded now (so truncated files fail here) by :func:`_to_array`, its EXIF
    orientation checked; ``source`` names it in the notes, ``what`` in the error.

    Raises:
        DatasetError: not a complete PNG or JPEG file.
    """
    try:
        with Image.open(file) as im:
            im.load()
            arr = _to_array(im, source)
            _check_orientation(im, source)
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as err:
        raise DatasetError(f"cannot {what}: expected a complete PNG or JPEG file ({err})") from err
    return arr


def _to_chw(arr: np.ndarray, size: tuple[int, int] | None) -> torch.Tensor:
    """(H,W) or (H,W,3) float32 array to a contiguous (3,H',W') tensor (gray replicated), resized when asked.

    Resizing is bilinear, ``align_corners=False``, no antialias, run on the channels-last view of the decoded
    array (several times faster on CPU than on a channels-first copy, and numerically identical).
    """
    if size is not None and tuple(arr.shape[:2]) != tuple(size):
        hwc = torch.from_numpy(arr if arr.ndim == 3 else arr[..., None])
        out = F.interpolate(hwc.permute(2, 0, 1).unsqueeze(0), size=size, mode="bilinear", align_corners=False,
                            antialias=False)[0]
        return out.expand(3, -1, -1).contiguous() if out.shape[0] == 1 else out.contiguous()
    if arr.ndim == 2:
        out = np.empty((3, *arr.shape), dtype=np.float32)
        out[0] = arr
        out[1] = arr
        out[2] = arr
        return torch.from_numpy(out)
    return torch.from_numpy(np.ascontiguousarray(arr.transpose(2, 0, 1)))


def read_image(path: str | Path, *, size: tuple[int, int] | None = None,
               expected_size: tuple[int, int] | None = None) -> torch.Tensor:
    """Read a PNG or JPEG file (8 or 16 bit, gray or colour) as an RGB float tensor.

    Args:
        path: image file.
        size: optional (height, width) to resize to (bilinear, ``align_corners=False``, no antialias; use
            :func:`dfvo.data.transforms.resize_with_intrinsics` semantics for ``K``).
        expected_size: optional (height, width) the file must have (checked before resizing).

    Returns:
        (3,H,W) float32 in [0,1] (or (3,*size)); gray images have three equal channels.

    Raises:
        DatasetNotFoundError: the file does not exist.
        DatasetError: the file is not a decodable image, is truncated, or is not ``expected_size``.
    """
    path = require_file(path, "image")
    arr = _decode(path, path, f"read image {path}")
    if expected_size is not None and tuple(arr.shape[:2]) != tuple(expected_size):
        raise DatasetError(f"image {path} is {arr.shape[0]}x{arr.shape[1]}, expected "
                           f"{expected_size[0]}x{expected_size[1]} (the size of the first frame)")
    return _to_chw(arr, size)


def decode_image(data: bytes, what: str, *, size: tuple[int, int] | None = None) -> torch.Tensor:
    """A PNG or JPEG file held in memory (a ROS ``CompressedImage``) as :func:`read_image` reads the same file.

    Raises:
        DatasetError: not a complete PNG or JPEG (the message names ``what``).
    """
    return _to_chw(_decode(io.BytesIO(data), what, f"decode {what}"), size)


def array_to_image(arr: np.ndarray, *, size: tuple[int, int] | None = None) -> torch.Tensor:
    """An image held in memory as :func:`read_image` would give it from a file: (H,W) or (H,W,3) uint8 (RGB) or
    uint16, or float in [0,1], to a (3,H,W) float32 tensor in [0,1] (gray replicated), resized to ``size`` the
    same way (the same numbers as reading the same pixels from a PNG).

    Raises:
        ValueError: another shape or dtype (one line saying what was expected).
    """
    a = np.asarray(arr)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] != 3):
        raise ValueError(f"image array of shape {a.shape}; expected (H,W) or (H,W,3) (RGB)")
    if a.dtype == np.uint8:
        a = a * np.float32(1.0 / 255.0)
    elif a.dtype == np.uint16:
        a = sixteen_bit_to_unit(a)
    elif np.issubdtype(a.dtype, np.floating):
        a = np.ascontiguousarray(a, dtype=np.float32)  # views such as frame[..., ::-1] have negative strides
        finite = a[np.isfinite(a)]  # NaN or infinite pixels are the caller's to flag (a dropped buffer)
        peak = float(finite.max()) if finite.size else 0.0
        if peak > 1.5:
            raise ValueError(f"float image array with values up to {peak:g}; expected [0,1] (divide by 255, or pass "
                             "the uint8 array itself)")
    else:
        raise ValueError(f"image array of dtype {a.dtype}; expected uint8, uint16 or float in [0,1]")
    return _to_chw(a, size)

