"""Ground-truth stretches of constant rotation rate (interpolated poses) and a run's RPE inside and outside; JSON.

    python studies/gt_constant_rate.py --gt ../shared/data/kitti_odom/poses_full/*.txt
    python studies/gt_constant_rate.py --run OUT --gt ../shared/data/kitti_odom/poses/06.txt

For every ``--gt`` file (KITTI pose format): its segments (:func:`dfvo.eval.ground_truth_checks.constant_rate_segments`:
first pair, pairs, the constant rotation rate) and the median second difference of its pairs' rotations elsewhere
(how much a measured rotation changes from frame to frame). With ``--run OUT`` (an ``infer.py`` output folder; one
``--gt``, the ground truth of the frames it tracked): the run's RPE (m, deg; the pairs of
:func:`dfvo.eval.odometry_metrics.relative_pose_errors`) over all pairs, the pairs inside the segments and those
outside.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from dfvo.eval import constant_rate_segments, pairs_in_segments, read_kitti_poses, relative_pose_errors
from dfvo.eval.ground_truth_checks import pair_rotations_deg, rotation_changes_deg


def describe(poses: np.ndarray, threshold: float, min_pairs: int) -> dict:
    """The segments of one ground truth and the typical frame-to-frame change of its rotation elsewhere."""
    segments = constant_rate_segments(poses, threshold, min_pairs)
    rates = pair_rotations_deg(poses)
    change = rotation_changes_deg(rates)
    in_segment = pairs_in_segments(segments, len(rates))
    inside = in_segment[1:len(change) + 1]  # change k is around pair k + 1
    return {"frames": len(poses),
            "segments": [{"first_pair": a, "pairs": n, "frames": [a, a + n],
                          "rate_deg": [round(float(v), 4) for v in rates[a]]} for a, n in segments],
            "pairs_in_segments": int(in_segment.sum()),
            "median_rotation_change_deg_elsewhere": round(float(np.median(change[~inside])), 4)}


def run_errors(run: Path, gt: np.ndarray, segments: list[tuple[int, int]]) -> dict:
    """RPE of the run's trajectory over all pairs, inside the segments and outside."""
    summary = json.loads((run / "summary.json").read_text())
    pred = read_kitti_poses(run / Path(summary["pose_file"]).name)
    n = min(len(pred), len(gt))
    pairs, t_err, r_err = relative_pose_errors(gt[:n], pred[:n])
    inside = pairs_in_segments(segments, n - 1)[pairs]

    def stats(mask: np.ndarray) -> dict:
        if not mask.any():
            return {"pairs": 0, "rpe_m": None, "rpe_deg": None}
        return {"pairs": int(mask.sum()), "rpe_m": round(float(t_err[mask].mean()), 5),
                "rpe_deg": round(float(r_err[mask].mean()), 5)}

    return {"run": str(run), "all": stats(np.ones_like(inside)), "inside_segments": stats(inside),
            "outside_segments": stats(~inside)}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--gt", nargs="+", required=True, help="KITTI pose files")
    p.add_argument("--run", nargs="*", default=[], help="infer.py output folders (with one --gt)")
    p.add_argument("--threshold-deg", type=float, default=0.01)
    p.add_argument("--min-pairs", type=int, default=8)
    args = p.parse_args(argv)
    if args.run and len(args.gt) != 1:
        p.error("--run needs exactly one --gt (the ground truth of the run's frames)")
    out: dict = {"threshold_deg": args.threshold_deg, "min_pairs": args.min_pairs, "ground_truth": {}}
    for path in args.gt:
        poses = read_kitti_poses(path)
        out["ground_truth"][path] = describe(poses, args.threshold_deg, args.min_pairs)
    if args.run:
        gt = read_kitti_poses(args.gt[0])
        segments = constant_rate_segments(gt, args.threshold_deg, args.min_pairs)
        out["runs"] = [run_errors(Path(r), gt, segments) for r in args.run]
    json.dump(out, sys.stdout, indent=1)
    print()


if __name__ == "__main__":
    main()
