"""``viewer=rerun``: infer.py writes OUT/run.rrd as frames are tracked; read back with Rerun's own reader, it holds
every entity, one camera pose per frame equal to SEQ.txt, and the diagnostics of frames.csv."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
pytest.importorskip("rerun", reason="the optional Rerun SDK (pip install 'dfvo[viewer]') is not installed")


def _run(*args: str, cwd: Path = REPO) -> subprocess.CompletedProcess:
    env = dict(os.environ, OMP_NUM_THREADS="1")
    return subprocess.run([sys.executable, "infer.py", *args], cwd=cwd, capture_output=True, text=True, env=env,
                          timeout=600)


def _check_recording(out: Path, pose_file: Path, frames: int) -> None:
    from dfvo.io.trajectory import read_kitti_poses
    from dfvo.viewer import ENTITIES, read_rrd

    rec = read_rrd(out / "run.rrd")
    rows = list(csv.DictReader((out / "frames.csv").open()))
    expected = set(ENTITIES) - {"world", "diagnostics"}  # parents of logged entities, nothing logged at them
    if not any(r["tracker"] == "E" for r in rows):
        expected.discard("world/points")  # triangulated points come from the E-tracker's inliers
    assert expected <= rec.entities, expected - rec.entities
    poses = rec.poses()
    assert sorted(poses) == list(range(frames)) and rec.frames("world/camera", "pose_3x4") == list(range(frames))
    np.testing.assert_allclose(np.stack([poses[k] for k in range(frames)]), read_kitti_poses(pose_file), atol=1e-8)
    for key in ("num_correspondences", "num_inliers", "scale", "gric_e"):
        logged = rec.scalars(key)
        for row in rows:
            if row[key] != "":
                assert logged[int(row["frame"])] == pytest.approx(float(row[key]), rel=1e-5), (key, row["frame"])
    codes = rec.scalars("tracker_code")
    names = {"init": 0.0, "E": 1.0, "PnP": 2.0, "constant_motion": 3.0}
    assert [codes[int(r["frame"])] for r in rows] == [names[r["tracker"]] for r in rows]


def test_synthetic_default_writes_a_readable_recording(tmp_path: Path) -> None:
    n = 6
    proc = _run("viewer=rerun", f"out_dir={tmp_path}", f"data.num_frames={n}", "img_res.height=96",
                "img_res.width=320", "progress=false", "num_threads=1")
    assert proc.returncode == 0, proc.stderr[-2000:]
    _check_recording(tmp_path, tmp_path / "synthetic_drive_s0.txt", n)


@pytest.mark.slow  # the fast cover of the recording: test_synthetic_default_writes_a_readable_recording
def test_kitti06_writes_a_readable_recording(kitti_odom_root: Path, tmp_path: Path) -> None:
    n = 5
    proc = _run("viewer=rerun", "data=kitti_odom", f"data.root={kitti_odom_root}", "seq=06", f"data.end={n}",
                f"out_dir={tmp_path}", "progress=false", "num_threads=1")
    assert proc.returncode == 0, proc.stderr[-2000:]
    _check_recording(tmp_path, tmp_path / "06.txt", n)
