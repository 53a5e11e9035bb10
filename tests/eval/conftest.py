"""Fixtures of the evaluation tests: the real KITTI 00 trajectories of ../shared (skip with a reason when absent)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

KITTI00_EVO = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "trajectories" / "kitti00_evo"


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
