"""KITTI raw drives that training leaves out: the test drives of published depth results and of this project's checks.

Plain names, no I/O (the training configs import this while composing, before torch is loaded).
"""

from __future__ import annotations

__all__ = ["EIGEN_TEST_DRIVES", "HELD_OUT_DRIVES"]

# The 28 drives of the Eigen split's test files (697 frames; monodepth2's splits/eigen/test_files.txt), which
# published depth results are measured on, and drive 0005, which this project holds out for its own LiDAR and
# odometry checks (../shared/data/kitti_raw_test). Training on KITTI raw leaves them out by default
# (``data.held_out_drives``).
EIGEN_TEST_DRIVES = tuple(f"2011_09_26_drive_{n:04d}_sync" for n in (
    2, 9, 13, 20, 23, 27, 29, 36, 46, 48, 52, 56, 59, 64, 84, 86, 93, 96, 101, 106, 117)) + (
    "2011_09_28_drive_0002_sync", "2011_09_29_drive_0071_sync", "2011_09_30_drive_0016_sync",
    "2011_09_30_drive_0018_sync", "2011_09_30_drive_0027_sync", "2011_10_03_drive_0027_sync",
    "2011_10_03_drive_0047_sync")
HELD_OUT_DRIVES = (*EIGEN_TEST_DRIVES, "2011_09_26_drive_0005_sync")
