"""Fixtures of the inference tests: frame folders made from the synthetic world (``infer.py`` as a user runs it is
``infer_cli`` of tests/conftest.py)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

REPO = Path(__file__).resolve().parents[2]


def write_frames(folder: Path, images: Sequence[torch.Tensor]) -> Path:
    """(3,H,W) float [0,1] images as 8-bit PNGs ``000000.png, ...`` in ``folder`` (created)."""
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    for k, img in enumerate(images):
        arr = (img.clamp(0, 1).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
        Image.fromarray(arr).save(folder / f"{k:06d}.png")
    return folder


def intrinsics_overrides(K: torch.Tensor | np.ndarray) -> list[str]:
    """``data.fx= data.fy= data.cx= data.cy=`` of a (3,3) matrix."""
    K = np.asarray(K, dtype=np.float64)
    return [f"data.fx={K[0, 0]:.9g}", f"data.fy={K[1, 1]:.9g}", f"data.cx={K[0, 2]:.9g}", f"data.cy={K[1, 2]:.9g}"]


def read_kitti(path: Path) -> np.ndarray:
    """(N,4,4) poses of a KITTI pose file, asserting 12 numbers on every line."""
    rows = [line.split() for line in path.read_text().splitlines()]
    assert rows and all(len(r) == 12 for r in rows), f"{path}: every line must hold 12 numbers"
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    T[:, :3, :4] = np.asarray(rows, dtype=np.float64).reshape(-1, 3, 4)
    return T


@pytest.fixture(scope="session")
def frames_io() -> SimpleNamespace:
    """Helpers as attributes: ``write_frames``, ``intrinsics_overrides``, ``read_kitti``."""
    return SimpleNamespace(write_frames=write_frames, intrinsics_overrides=intrinsics_overrides, read_kitti=read_kitti)
