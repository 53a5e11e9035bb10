"""Any folder of PNG/JPEG frames plus pinhole intrinsics: the "run it on my own video" path.

Convention:
    - Frames are read in natural filename order (``frame2`` before ``frame10``).
    - ``fx, fy, cx, cy`` are in pixels of the files as stored, pixel centres at integer coordinates.
    - ``dist`` is OpenCV's radial-tangential model ``[k1, k2, p1, p2]``, ``[k1, k2, p1, p2, k3]`` or the rational
      ``[k1, k2, p1, p2, k3, k4, k5, k6]`` (all zeros: no undistortion). Frames are
      undistorted at native resolution with kornia (the same model as ``cv2.undistort`` with the new camera
      matrix equal to ``K``), so the undistorted frame keeps the intrinsics ``K``; pixels whose source falls
      outside the frame become 0. Then the frame is resized to the working size and ``K`` follows exactly.
    - The intrinsics are checked against the stored frames (:mod:`dfvo.data.intrinsics_check`): principal point
      inside the image, positive focal lengths, a plausible field of view, the distortion count.
    - Samples: ``image`` (3,H,W) in [0,1], ``K`` (3,3) at the working resolution, ``index``; no pose.
    - :class:`FramePrep` (native frame -> undistorted -> working size, with ``K``) is shared by the EuRoC, TUM
      RGB-D and video readers.
"""

from __future__ import annotations

from pathlib import Path

import torch
from kornia.geometry.calibration import distort_points
from kornia.geometry.transform import remap
from torch.utils.data import Dataset

from dfvo.data.image_io import image_size, list_images, read_image
from dfvo.data.intrinsics_check import check_intrinsics
from dfvo.data.transforms import check_working_size, resize_image, resize_with_intrinsics
from dfvo.geometry.camera import intrinsics_matrix, pixel_grid


class Undistorter:
    """Precomputed undistortion of frames of one size with radial-tangential distortion (kornia remap).

    Args:
        K: (3,3) intrinsics of the distorted frames (kept by the undistorted frames).
        dist: [k1, k2, p1, p2], [k1, k2, p1, p2, k3] or [k1, k2, p1, p2, k3, k4, k5, k6] (OpenCV order).
        height: frame rows; width: frame columns.
    """

    def __init__(self, K: torch.Tensor, dist: list[float], height: int, width: int) -> None:
        if len(dist) not in (4, 5, 8):
            raise ValueError(f"dist must be [k1, k2, p1, p2], [k1, k2, p1, p2, k3] or [k1, k2, p1, p2, k3, k4, k5, "
                             f"k6], got {len(dist)} values")
        coeffs = torch.zeros(8, dtype=torch.float64)
        coeffs[: len(dist)] = torch.as_tensor([float(d) for d in dist], dtype=torch.float64)
        grid = pixel_grid(height, width, dtype=torch.float64).reshape(-1, 2)
        src = distort_points(grid, K.to(torch.float64), coeffs)  # where each undistorted pixel lies in the frame
        self.map_x = src[:, 0].reshape(1, height, width).float()
        self.map_y = src[:, 1].reshape(1, height, width).float()

    def __call__(self, image: torch.Tensor) -> torch.Tensor:
        """Undistort a (3,H,W) frame."""
        if tuple(image.shape[-2:]) != tuple(self.map_x.shape[-2:]):
            raise ValueError(f"frame is {tuple(image.shape[-2:])}, the undistortion maps are for "
                             f"{tuple(self.map_x.shape[-2:])}")
        return remap(image.unsqueeze(0), self.map_x, self.map_y, mode="bilinear", padding_mode="zeros",
                     align_corners=True).squeeze(0)


class FramePrep:
    """Native frames to working frames: optional undistortion at native size, then a resize; ``K`` follows.

    Args:
        K_native: (3,3) intrinsics of the stored frames.
        native_size: (height, width) of the stored frames.
        working_size: (height, width) to resize to (None: native size).
        dist: optional distortion coefficients (4, 5 or 8; all zeros means none).

    Attributes:
        K: (3,3) float32 intrinsics at the working size. image_size: the working (height, width).
    """

    def __init__(self, K_native: torch.Tensor, native_size: tuple[int, int], working_size: tuple[int, int] | None,
                 dist: list[float] | None = None) -> None:
        self.native_size = (int(native_size[0]), int(native_size[1]))
        self.image_size: tuple[int, int] = tuple(working_size) if working_size is not None else self.native_size
        K_native = torch.as_tensor(K_native, dtype=torch.float64)
        has_dist = dist is not None and any(float(d) != 0.0 for d in dist)
        self.undistort = Undistorter(K_native, list(dist), *self.native_size) if has_dist else None
        _, K = resize_with_intrinsics(torch.zeros(1, *self.native_size), K_native, *self.image_size)
        self.K = K.float()

    def __call__(self, image: torch.Tensor) -> torch.Tensor:
        """(3,h,w) native frame -> (3,H,W) working frame."""
        if self.undistort is not None:
            image = self.undistort(image)
        return resize_image(image, *self.image_size)

    def read(self, path: Path) -> torch.Tensor:
        """Read an image file of the native size and prepare it (resizing while decoding when nothing to undistort)."""
        if self.undistort is None:
            return read_image(path, size=self.image_size, expected_size=self.native_size)
        return self(read_image(path, expected_size=self.native_size))


class ImageFolder(Dataset):
    """Frames of a folder with known intrinsics (and optional lens distortion), no ground truth.

    Args:
        path: folder of PNG/JPEG files (all the same size).
        fx, fy, cx, cy: intrinsics in pixels of the stored files.
        dist: optional [k1, k2, p1, p2(, k3(, k4, k5, k6))] radial-tangential distortion; frames are undistorted.
        height: working height; width: working width (both or neither; None keeps the native size).

    Raises:
        DatasetNotFoundError: the folder does not exist.
        DatasetError: no images in it; a frame whose size differs from the first; unreadable frames (on access).
        IntrinsicsError (a ValueError): implausible intrinsics for the stored frames (named ``data.fx`` ...).
        ValueError: bad working size.
    """

    def __init__(self, path: str | Path, fx: float, fy: float, cx: float, cy: float, dist: list[float] | None = None,
                 height: int | None = None, width: int | None = None) -> None:
        self.path = Path(path)
        self.files = list_images(self.path, "image folder")
        self.native_size = image_size(self.files[0])
        fx, fy, cx, cy, dist = check_intrinsics(fx, fy, cx, cy, self.native_size[1], self.native_size[0], dist,
                                                source=f"frames of {self.path}")
        working = check_working_size(height, width, f"ImageFolder({self.path})")
        K_native = intrinsics_matrix(fx, fy, cx, cy, dtype=torch.float64)[0]
        self.prep = FramePrep(K_native, self.native_size, working, dist)
        self.image_size = self.prep.image_size
        self.undistort = self.prep.undistort
        self.intrinsics = self.prep.K

    def __len__(self) -> int:
        return len(self.files)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        image = self.prep.read(self.files[index])
        return {"image": image, "K": self.intrinsics.clone(), "index": torch.tensor(index % len(self))}
