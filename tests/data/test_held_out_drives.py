"""Training on a KITTI raw root leaves the held-out test drives out (the Eigen split's 28 and drive 0005), says so,
and trains on one only when it is named, with a warning (issue 38)."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from dfvo.data.held_out import EIGEN_TEST_DRIVES, HELD_OUT_DRIVES
from dfvo.data.image_io import DatasetError
from dfvo.data.kitti_raw import KittiRawSnippets


def _root(tmp_path: Path, kitti_raw_root: Path, names: list[str]) -> Path:
    """A KITTI raw root whose drives are links to the shared drive 0001 under other names."""
    date = tmp_path / "2011_09_26"
    date.mkdir(parents=True)
    for f in kitti_raw_root.glob("calib_*.txt"):
        (date / f.name).symlink_to(f)
    drive = next(kitti_raw_root.glob("*_drive_*_sync"))
    for name in names:
        (date / name).symlink_to(drive, target_is_directory=True)
    return tmp_path


def test_held_out_drives_are_left_out_unless_named(tmp_path: Path, kitti_raw_root: Path,
                                                     caplog: pytest.LogCaptureFixture) -> None:
    assert len(EIGEN_TEST_DRIVES) == 28 and "2011_09_26_drive_0005_sync" in HELD_OUT_DRIVES
    root = _root(tmp_path, kitti_raw_root, ["2011_09_26_drive_0001_sync", "2011_09_26_drive_0005_sync",
                                             "2011_09_26_drive_0002_sync"])
    with caplog.at_level(logging.INFO, logger="dfvo.data"):
        ds = KittiRawSnippets(root, 32, 96, stereo=False, temporal=True, held_out=HELD_OUT_DRIVES)
    assert [d.dir.name for d in ds.drives] == ["2011_09_26_drive_0001_sync"]
    assert "2 held-out test drive(s) left out" in caplog.text and "drive_0005_sync" in caplog.text
    everything = KittiRawSnippets(root, 32, 96, stereo=False, temporal=True)  # inference: nothing held out
    assert len(everything.drives) == 3
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="dfvo.data"):
        named = KittiRawSnippets(root, 32, 96, drives=["0005"], stereo=False, temporal=True, held_out=HELD_OUT_DRIVES)
    assert [d.dir.name for d in named.drives] == ["2011_09_26_drive_0005_sync"]
    assert "is a held-out test drive" in caplog.text
    only = _root(tmp_path / "only", kitti_raw_root, ["2011_09_26_drive_0005_sync"])
    with pytest.raises(DatasetError, match="holds only held-out test drives"):
        KittiRawSnippets(only, 32, 96, stereo=False, temporal=True, held_out=HELD_OUT_DRIVES)
