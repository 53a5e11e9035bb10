"""Time the odometry evaluation; prints one JSON object.

- ``wall_s``: ``evaluate_trajectory`` (7-DoF) on all 11 full-length KITTI GT sequences (perturbed copies);
- ``io_s``: reading the 4541-pose KITTI 00 ground truth in each format (KITTI 12 / 13 numbers, TUM, EuRoC CSV),
  the nearest-timestamp association of two TUM files of it, and ``evaluate_sequences`` on that pair.

    python benchmarks/eval_speed.py [POSES_FULL_DIR] [KITTI00_EVO_DIR]
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from dfvo.eval import associate_trajectories, evaluate_sequences, evaluate_trajectory, read_kitti_poses
from dfvo.io.trajectory import read_trajectory, write_euroc_poses, write_kitti_poses, write_tum_poses

SHARED = Path(__file__).resolve().parents[2] / "shared/data"


def _timed(fn, repeat: int = 3) -> float:
    best = float("inf")
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return round(best, 4)


def io_timings(root: Path) -> dict:
    gt = read_kitti_poses(root / "KITTI_00_gt.txt")
    times = np.loadtxt(root / "KITTI_00_gt_times.txt")
    with tempfile.TemporaryDirectory() as tmp:
        files = {"kitti12": write_kitti_poses(Path(tmp) / "a.txt", gt),
                 "kitti13": write_kitti_poses(Path(tmp) / "b.txt", gt, frame_ids=np.arange(len(gt))),
                 "tum": write_tum_poses(Path(tmp) / "c.txt", gt, times),
                 "euroc": write_euroc_poses(Path(tmp) / "d.csv", gt, times)}
        out = {f"read_{k}": _timed(lambda p=p: read_trajectory(p)) for k, p in files.items()}
        tum = read_trajectory(files["tum"])
        out["associate_timestamps"] = _timed(lambda: associate_trajectories(tum, tum))
        out["evaluate_sequences_tum_pair"] = _timed(lambda: evaluate_sequences(files["tum"], files["tum"]))
    return {"poses": int(len(gt)), **out}


def main() -> None:
    root = Path(sys.argv[1]) if len(sys.argv) > 1 else SHARED / "kitti_odom/poses_full"
    evo_root = Path(sys.argv[2]) if len(sys.argv) > 2 else SHARED / "trajectories/kitti00_evo"
    rng = np.random.default_rng(0)
    gts = [read_kitti_poses(root / f"{s:02d}.txt") for s in range(11)]
    preds = []
    for gt in gts:
        pred = gt.copy()
        pred[:, :3, 3] = pred[:, :3, 3] * 0.5 + rng.normal(0, 0.5, size=(len(gt), 3))
        preds.append(pred)
    start = time.perf_counter()
    for gt, pred in zip(gts, preds, strict=True):
        evaluate_trajectory(gt, pred, "7dof")
    wall = time.perf_counter() - start
    print(json.dumps({"sequences": 11, "frames": int(sum(len(g) for g in gts)), "align": "7dof",
                      "wall_s": round(wall, 4),
                      "io_s": io_timings(evo_root) if (evo_root / "KITTI_00_gt.txt").is_file() else None}))


if __name__ == "__main__":
    main()
