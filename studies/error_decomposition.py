"""Where does a trajectory's frame-to-frame error come from: translation length (scale), or direction and rotation?

DF-VO computes each relative pose's rotation and translation direction from the flow (epipolar geometry) and only
the translation length from the depth network. Replacing every predicted relative translation's length by the true
one removes the scale error and leaves what the flow and the geometry did; the per-frame ratio of predicted to true
lengths is the scale error itself. Prints one JSON object:

    - ``as_run``: RPE (m, deg) and ATE (m) of the prediction (``--align``, 6-DoF by default);
    - ``true_lengths``: the same with every relative translation rescaled to the true length;
    - ``length_ratio``: mean, median and standard deviation of |t_pred| / |t_true| over frames, and its lag-1
      autocorrelation (near 0: the scale errors of consecutive frames are independent);
    - ``direction_error_deg``: median, mean and max angle between predicted and true translation directions.

    python studies/error_decomposition.py --gt ../shared/data/kitti_odom/poses/06.txt --pred OUT/06.txt

Any trajectory format that ``python -m dfvo.evaluate`` reads (KITTI 12/13, TUM, EuRoC; ``--format auto``); the two
files are paired as there (timestamps, frame indices, or line by line; a prefix is accepted) and must pair up on
consecutive frames.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from dfvo.eval.error_decomposition import scale_free
from dfvo.eval.odometry_metrics import evaluate_trajectory
from dfvo.io.association import associate_trajectories
from dfvo.io.trajectory import read_trajectory


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--gt", required=True, help="trajectory file of the ground truth")
    p.add_argument("--pred", required=True, help="trajectory file of the prediction")
    p.add_argument("--align", default="6dof", choices=["6dof", "7dof", "scale", "none"])
    p.add_argument("--format", default="auto", choices=["auto", "kitti", "tum", "euroc"])
    p.add_argument("--max-time-diff", type=float, default=0.01, help="timestamp association tolerance (s)")
    args = p.parse_args()
    try:
        assoc = associate_trajectories(read_trajectory(args.gt, args.format), read_trajectory(args.pred, args.format),
                                       args.max_time_diff, allow_prefix=True)
    except (ValueError, FileNotFoundError) as err:
        raise SystemExit(f"error: {err}") from None
    rows = np.flatnonzero(assoc.valid)
    if np.any(np.diff(rows) > 1):
        raise SystemExit(f"{args.pred}: the predicted frames are not consecutive ({assoc.describe()})")
    gt, pred = assoc.gt[rows], assoc.pred[rows]
    true_lengths, _, angle, ratio = scale_free(gt, pred)

    def summary(traj: np.ndarray) -> dict[str, float]:
        m = evaluate_trajectory(gt, traj, align=args.align)
        return {"rpe_m": round(m["rpe_m"], 4), "rpe_deg": round(m["rpe_deg"], 4), "ate_m": round(m["ate_m"], 4)}

    print(json.dumps({
        "gt": args.gt, "pred": args.pred, "align": args.align, "frames": len(gt), "pairing": assoc.describe(),
        "as_run": summary(pred), "true_lengths": summary(true_lengths),
        "length_ratio": {"mean": round(float(ratio.mean()), 4), "median": round(float(np.median(ratio)), 4),
                         "std": round(float(ratio.std()), 4),
                         "lag1_autocorrelation": (round(float(np.corrcoef(ratio[:-1], ratio[1:])[0, 1]), 4)
                                                  if len(ratio) > 2 else None)},
        "direction_error_deg": {"median": round(float(np.median(angle)), 3), "mean": round(float(angle.mean()), 3),
                                "max": round(float(angle.max()), 3)},
    }))


if __name__ == "__main__":
    main()
