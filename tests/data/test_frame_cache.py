"""dfvo.data.frame_cache: decoded frames memory-mapped from disk, keyed by the files and the size (issue 37)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from dfvo.data.frame_cache import DecodedFrames
from dfvo.data.image_io import DatasetError, read_image


def _images(folder: Path, n: int) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    paths = []
    for i in range(n):
        p = folder / f"{i:06d}.png"
        Image.fromarray(rng.integers(0, 256, (30, 40, 3), dtype=np.uint8)).save(p)
        paths.append(p)
    return paths


def test_cached_frames_are_the_decoded_frames_in_half_precision(tmp_path: Path) -> None:
    """Each cached frame is read_image's (resized) frame to fp16 rounding; a second reader maps the same file (not
    rewritten); a changed image gets a new key, so a stale cache is never read; a cut file is refused in one line."""
    paths = _images(tmp_path / "img", 3)
    calls = []

    def load(p: Path) -> torch.Tensor:
        calls.append(p)
        return read_image(p, size=(16, 24))

    cache = DecodedFrames(paths, (16, 24), load, tmp_path / "cache", "cam")
    assert len(cache) == 3 and len(calls) == 3 and cache.path.name.startswith("cam_16x24_")
    for i, p in enumerate(paths):
        torch.testing.assert_close(cache[i], read_image(p, size=(16, 24)), rtol=0, atol=2.5e-4)
        assert cache[i].dtype == torch.float32 and cache[i].shape == (3, 16, 24)
    written = cache.path.stat().st_mtime_ns
    again = DecodedFrames(paths, (16, 24), load, tmp_path / "cache", "cam")
    assert len(calls) == 3 and again.path == cache.path and again.path.stat().st_mtime_ns == written
    Image.fromarray(np.zeros((30, 40, 3), dtype=np.uint8)).save(paths[1])
    os.utime(paths[1], ns=(written + 10**9, written + 10**9))
    changed = DecodedFrames(paths, (16, 24), load, tmp_path / "cache", "cam")
    assert changed.path != cache.path and float(changed[1].abs().max()) == 0.0
    changed.path.write_bytes(changed.path.read_bytes()[:200])
    with pytest.raises(DatasetError, match=f"frame cache {changed.path}.*delete it"):
        DecodedFrames(paths, (16, 24), load, tmp_path / "cache", "cam")


def test_kitti_raw_snippets_read_through_the_cache(kitti_raw_root: Path, tmp_path: Path) -> None:
    """KittiRawSnippets with cache_dir gives the frames of the uncached dataset (fp16 rounding), from files in it."""
    from dfvo.data.kitti_raw import KittiRawSnippets

    plain = KittiRawSnippets(kitti_raw_root.parent, 32, 96, stereo=True, temporal=True)
    cached = KittiRawSnippets(kitti_raw_root.parent, 32, 96, stereo=True, temporal=True, cache_dir=tmp_path)
    assert sorted(p.name.split("_32x96")[0] for p in tmp_path.glob("*.npy")) == [
        "2011_09_26_drive_0001_sync_image_02", "2011_09_26_drive_0001_sync_image_03"]
    for i in (0, len(plain) - 1):
        a, b = plain[i], cached[i]
        for key in ("image", "image_prev", "image_next", "image_right"):
            torch.testing.assert_close(b[key], a[key], rtol=0, atol=2.5e-4)

