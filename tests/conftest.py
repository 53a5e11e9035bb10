"""Shared test fixtures: the location of ../shared data (tests that need it skip when it is absent), the KITTI 00
trajectories of evo's tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
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


KITTI00_EVO = SHARED_DATA / "trajectories" / "kitti00_evo"


@pytest.fixture(scope="session")
def kitti00() -> dict[str, Path]:
    """``{"gt", "times", "orb", "sptam"}``: KITTI 00 ground truth (4541 poses), its timestamps, and the ORB-SLAM
    and S-PTAM estimates, as published with evo's tests."""
    files = {"gt": "KITTI_00_gt.txt", "times": "KITTI_00_gt_times.txt", "orb": "KITTI_00_ORB.txt",
             "sptam": "KITTI_00_SPTAM.txt"}
    out = {k: KITTI00_EVO / v for k, v in files.items()}
    missing = [p for p in out.values() if not p.is_file()]
    if missing:
        pytest.skip(f"needs {missing[0]} (the project's ../shared data folder); not present on this machine")
    return out


@pytest.fixture(scope="session")
def kitti00_times(kitti00) -> np.ndarray:
    return np.loadtxt(kitti00["times"])
