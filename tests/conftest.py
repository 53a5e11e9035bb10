"""Shared test fixtures: the location of ../shared data (tests that need it skip when it is absent)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"

torch.set_num_threads(2)


def _require(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"needs {path} (the project's ../shared data folder); not present on this machine")
    return path


@pytest.fixture
def kitti_odom_root() -> Path:
    """``../shared/data/kitti_odom`` (sequence 06, frames 0-50, grayscale stereo, poses)."""
    return _require(SHARED_DATA / "kitti_odom" / "sequences" / "06").parents[1]


@pytest.fixture
def kitti_raw_root() -> Path:
    """``../shared/data/kitti_raw`` (drive 2011_09_26_0001, colour stereo JPEG, no oxts)."""
    return _require(SHARED_DATA / "kitti_raw" / "2011_09_26")


@pytest.fixture
def kitti_poses_full() -> Path:
    """``../shared/data/kitti_odom/poses_full`` (official GT poses 00-10)."""
    return _require(SHARED_DATA / "kitti_odom" / "poses_full")
