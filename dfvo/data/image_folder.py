"""Any folder of PNG/JPEG frames plus pinhole intrinsics: the "run it on my own video" path.

Convention:
    - Frames are read in natural filename order (``frame2`` before ``frame10``).
    - ``fx, fy, cx, cy`` are in pixels of the files as stored, pixel centres at integer coordinates.
    - ``dist`` is OpenCV's radial-tangential model ``[k1, k2, p1, p2]`` or ``[k1, k2, p1, p2, k3]``. Frames are
      undistorted at native resolution with kornia (the same model as ``cv2.undistort`` with the new camera
      matrix equal to ``K``), so the undistorted frame keeps the intrinsics ``K``; pixels whose source falls
      outside the frame become 0. Then the frame is resized to the working size and ``K`` follows exactly.
    - Samples: ``image`` (3,H,W) in [0,1], ``K`` (3,3) at the working resolution, ``index``; no pose.
"""

from __future__ import annotations

from pathlib import Path

import torch
from kornia.geometry.calibration import distort_points
from kornia.geometry.transform import remap
from torch.utils.data import Dataset

from dfvo.data.image_io import image_size, list_images, read_image
from dfvo.data.transforms import check_working_size, resize_image, resize_with_intrinsics
from dfvo.geometry.camera import intrinsics_matrix, pixel_grid


class Undistorter:
    """Precomputed undistortion of frames of one size with radial-tangential distortion (kornia remap).

    Args:
        K: (3,3) intrinsics of the distorted frames (kept by the undistorted frames).
        dist: [k1, k2, p1, p2] or [k1, k2, p1, p2, k3].
        height: frame rows; width: frame columns.
    """

    def __init__(self, K: torch.Tensor, dist: list[float], height: int, width: int) -> None:
        if len(dist) not in (4, 5):
            raise ValueError(f"dist must be [k1, k2, p1, p2] or [k1, k2, p1, p2, k3], got {len(dist)} values")
        coeffs = torch.zeros(5, dtype=torch.float64)
        coeffs[: len(dist)] = torch.as_tensor(dist, dtype=torch.float64)
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


class ImageFolder(Dataset):
    """Frames of a folder with known intrinsics (and optional lens distortion), no ground truth.

    Args:
        path: folder of PNG/JPEG files (all the same size).
        fx, fy, cx, cy: intrinsics in pixels of the stored files.
        dist: optional [k1, k2, p1, p2(, k3)] radial-tangential distortion; frames are undistorted.
        height: working height; width: working width (both or neither; None keeps the native size).

    Raises:
        DatasetNotFoundError: the folder does not exist.
        DatasetError: no images in it; a frame whose size differs from the first; unreadable frames (on access).
        ValueError: non-positive focal lengths, a distortion list of the wrong length.
    """

    def __init__(self, path: str | Path, fx: float, fy: float, cx: float, cy: float, dist: list[float] | None = None,
                 height: int | None = None, width: int | None = None) -> None:
        self.path = Path(path)
        self.files = list_images(self.path, "image folder")
        if fx <= 0 or fy <= 0:
            raise ValueError(f"ImageFolder({self.path}): fx and fy must be positive, got fx={fx}, fy={fy}")
        self.native_size = image_size(self.files[0])
        working = check_working_size(height, width, f"ImageFolder({self.path})")
        self.image_size: tuple[int, int] = working if working is not None else self.native_size
        K_native = intrinsics_matrix(fx, fy, cx, cy)[0]
        self.undistort = Undistorter(K_native, list(dist), *self.native_size) if dist else None
        _, self.intrinsics = resize_with_intrinsics(torch.zeros(1, *self.native_size), K_native, *self.image_size)

    def __len__(self) -> int:
        return len(self.files)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        path = self.files[index]
        if self.undistort is None:
            image = read_image(path, size=self.image_size, expected_size=self.native_size)
        else:
            image = resize_image(self.undistort(read_image(path, expected_size=self.native_size)), *self.image_size)
        return {"image": image, "K": self.intrinsics.clone(), "index": torch.tensor(index % len(self))}
