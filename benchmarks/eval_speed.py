"""Time ``evaluate_trajectory`` on all 11 full-length KITTI GT sequences (perturbed copies); prints JSON."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from dfvo.eval import evaluate_trajectory, read_kitti_poses


def main() -> None:
    default = Path(__file__).resolve().parents[2] / "shared/data/kitti_odom/poses_full"
    root = Path(sys.argv[1]) if len(sys.argv) > 1 else default
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
                      "wall_s": round(wall, 4)}))


if __name__ == "__main__":
    main()
