"""Decoded frames on disk: every image of a list decoded and resized once, then memory-mapped by later epochs and runs.

A training step that decodes and resizes its JPEGs again at every epoch spends ~50 ms a depth batch on it (two cores,
KITTI raw at 96x320, four views a sample); a memory-mapped array of the decoded frames costs a copy. One cache file
holds one image list (a drive's camera folder) at one working size: ``LABEL_HxW_KEY.npy``, (N,3,H,W) float16 (the
[0,1] images of :func:`dfvo.data.image_io.read_image`, rounded to half precision: at most 2.4e-4 off, a sixteenth of
the 8-bit files' own step). ``KEY`` hashes the cache format, the size and every file's name, byte size and
modification time, so a changed, added or removed image gets a new file and a stale one is never read. A file whose
header does not match its key's frames (cut by a crash, or written by something else) is refused with one line
naming it. Written to a temporary file and renamed, so a reader never sees half a cache.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch

from dfvo.data.image_io import DatasetError

__all__ = ["CACHE_FORMAT", "cache_key", "DecodedFrames"]

CACHE_FORMAT = 1


def cache_key(paths: Sequence[Path], size: tuple[int, int], channels: int = 3) -> str:
    """16 hex digits identifying the frames of ``paths`` decoded at ``size`` (format, size, channels, names, sizes,
    times)."""
    files = []
    for p in paths:
        st = Path(p).stat()
        files.append([Path(p).name, st.st_size, st.st_mtime_ns])
    text = json.dumps([CACHE_FORMAT, list(size), channels, files])
    return hashlib.sha1(text.encode()).hexdigest()[:16]


class DecodedFrames:
    """The frames of ``paths`` decoded by ``load`` at ``size``, from (or into) a memory-mapped cache file.

    Args:
        paths: the image files, in order. size: (H, W) every decoded frame has.
        load: path -> (C,H,W) float tensor (the decoder the frames would otherwise be read with: images in [0,1],
            or maps derived from the files, e.g. stereo depth hints in metres).
        cache_dir: the cache folder (created when missing). label: the file name's prefix (e.g. the drive and
            camera folder, and what the maps are).
        channels: C. key_paths: the files the maps depend on (default ``paths``; e.g. both images of stereo pairs).

    Raises:
        DatasetError: a cache file that does not hold the frames its name promises.
    """

    def __init__(self, paths: Sequence[Path], size: tuple[int, int], load: Callable[[Path], torch.Tensor],
                 cache_dir: str | Path, label: str, channels: int = 3,
                 key_paths: Sequence[Path] | None = None) -> None:
        self.size = (int(size[0]), int(size[1]))
        shape = (len(paths), channels, *self.size)
        folder = Path(cache_dir)
        key = cache_key(paths if key_paths is None else key_paths, self.size, channels)
        self.path = folder / f"{label}_{self.size[0]}x{self.size[1]}_{key}.npy"
        if not self.path.is_file():
            folder.mkdir(parents=True, exist_ok=True)
            tmp = self.path.with_name(f"{self.path.name}.{os.getpid()}.tmp")
            out = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.float16, shape=shape)
            for i, p in enumerate(paths):
                out[i] = load(p).numpy()
            out.flush()
            del out
            os.replace(tmp, self.path)
        try:
            self.frames = np.load(self.path, mmap_mode="r")
        except (OSError, ValueError) as err:
            raise DatasetError(f"frame cache {self.path}: cannot be read ({err}); delete it (it is written again)"
                               ) from err
        if self.frames.shape != shape or self.frames.dtype != np.float16:
            raise DatasetError(f"frame cache {self.path} holds {self.frames.dtype} {self.frames.shape}, expected "
                               f"float16 {shape}; delete it (it is written again)")

    def __len__(self) -> int:
        return int(self.frames.shape[0])

    def __getitem__(self, i: int) -> torch.Tensor:
        """Frame ``i`` as a (C,H,W) float32 tensor (a copy)."""
        return torch.from_numpy(np.asarray(self.frames[i], dtype=np.float32))
