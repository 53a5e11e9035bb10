"""NEES of the per-frame step covariance of an ``infer.py`` run against ground truth; prints JSON.

    python studies/covariance_nees.py OUT [OUT ...] [--gt GT.txt ...] [--inflation K] [--drop-correlation]

``OUT`` is a run's folder (``frames.csv``, the trajectory ``SEQ.txt`` in KITTI format, ``summary.json``); the ground
truth defaults to ``ROOT/poses/SEQ.txt`` of a KITTI odometry run (``--gt`` gives it per run otherwise). For every
frame tracked by E or PnP: the error of the step ``T_prev_cur`` against the true step (rotation vector and
translation, :func:`dfvo.tracking.covariance.step_error`) and its NEES under the frame's covariance (6 degrees of
freedom; 3 for the rotation and the translation blocks alone). A calibrated covariance has a mean NEES of 6 (band:
chi-square 95 % of 6 N over N frames). ``calibrated_inflation`` is the factor on the covariance that would make this
run's mean NEES 6; ``--inflation K`` reports the NEES of the covariances multiplied by K (to check a factor calibrated
on one sequence on another). ``inflation_in_run`` is ``tracker.covariance.inflation`` of the run (already applied).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from pathlib import Path

import numpy as np
import torch

from dfvo.geometry.pose_covariance import covariance_from_row, nees, step_error
from dfvo.tracking.covariance import uncorrelated


def chi2_quantile(p: float, dof: int) -> float:
    """Wilson-Hilferty approximation of the chi-square quantile (within 0.1 % for dof >= 30)."""
    lo, hi = -10.0, 10.0
    for _ in range(200):  # the standard normal quantile by bisection on erf
        mid = 0.5 * (lo + hi)
        if 0.5 * (1 + math.erf(mid / math.sqrt(2))) < p:
            lo = mid
        else:
            hi = mid
    z, a = 0.5 * (lo + hi), 2.0 / (9.0 * dof)
    return dof * (1.0 - a + z * math.sqrt(a)) ** 3


def read_kitti_poses(path: Path) -> np.ndarray:
    rows = np.loadtxt(path, ndmin=2)
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    T[:, :3, :4] = rows[:, :12].reshape(-1, 3, 4)
    return T


def read_run(out: Path) -> tuple[dict, np.ndarray, list[dict]]:
    """An ``infer.py`` run's ``summary.json``, its poses (N,4,4) (the pose file where the summary says, else the file
    of that name in ``out``: a moved run) and its ``frames.csv`` rows."""
    summary = json.loads((out / "summary.json").read_text())
    pose_file = Path(summary["pose_file"])
    pred = read_kitti_poses(pose_file if pose_file.is_file() else out / pose_file.name)
    return summary, pred, list(csv.DictReader((out / "frames.csv").open()))


def evaluate(out: Path, gt_path: Path | None, inflation: float, drop_correlation: bool = False) -> dict:
    summary, pred, rows = read_run(out)
    if gt_path is None:
        gt_path = Path(summary.get("data_root", "")) / "poses" / f"{summary['sequence']}.txt"
    gt = read_kitti_poses(gt_path)[: len(pred)]
    per: dict[str, list[tuple[float, float, float]]] = {}
    errors = []
    for k in range(1, len(pred)):
        C = covariance_from_row(rows[k])
        tracker = rows[k]["tracker"]
        if C is None:
            continue
        C = C * inflation
        if drop_correlation and tracker in ("E", "PnP"):  # what tracker.covariance.correlated=false writes
            C = uncorrelated(C)
        e = step_error(torch.from_numpy(np.linalg.inv(pred[k - 1]) @ pred[k]),
                       torch.from_numpy(np.linalg.inv(gt[k - 1]) @ gt[k]))
        per.setdefault(tracker, []).append((nees(e, C), nees(e[:3], C[:3, :3]), nees(e[3:], C[3:, 3:])))
        errors.append((tracker, e.numpy(), C.diagonal().sqrt().numpy()))
    measured = [v for t in ("E", "PnP") for v in per.get(t, [])]
    n = len(measured)
    arr = np.asarray(measured) if measured else np.zeros((0, 3))
    out_json = {
        "run": str(out), "sequence": summary["sequence"], "frames": n, "inflation_applied_here": inflation,
        "mean_nees_6dof": float(arr[:, 0].mean()) if n else None,
        "median_nees_6dof": float(np.median(arr[:, 0])) if n else None,
        "mean_nees_rotation_3dof": float(arr[:, 1].mean()) if n else None,
        "mean_nees_translation_3dof": float(arr[:, 2].mean()) if n else None,
        "band_95_mean_6dof": [chi2_quantile(0.025, 6 * n) / n, chi2_quantile(0.975, 6 * n) / n] if n else None,
        "calibrated_inflation": float(arr[:, 0].mean() / 6.0) if n else None,
        "by_tracker": {t: {"frames": len(v), "mean_nees_6dof": float(np.mean([x[0] for x in v])),
                           "mean_nees_rotation": float(np.mean([x[1] for x in v])),
                           "mean_nees_translation": float(np.mean([x[2] for x in v]))} for t, v in per.items()},
    }
    if errors:
        e = np.stack([x[1] for x in errors if x[0] in ("E", "PnP")])
        s = np.stack([x[2] for x in errors if x[0] in ("E", "PnP")])
        out_json["rms_error"] = dict(zip(("rx", "ry", "rz", "tx", "ty", "tz"), np.sqrt((e ** 2).mean(0)).tolist(),
                                         strict=True))
        out_json["rms_predicted_std"] = dict(zip(("rx", "ry", "rz", "tx", "ty", "tz"),
                                                 np.sqrt((s ** 2).mean(0)).tolist(), strict=True))
    return out_json


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--gt", nargs="*", type=Path, default=None, help="ground-truth KITTI pose files, one per run")
    parser.add_argument("--inflation", type=float, default=1.0)
    parser.add_argument("--drop-correlation", action="store_true",
                        help="zero the rotation-translation cross block of E and PnP frames (the default since "
                             "tracker.covariance.correlated=false: to read runs written before it as it would)")
    args = parser.parse_args(argv)
    gts = args.gt or [None] * len(args.runs)
    if len(gts) != len(args.runs):
        sys.exit("covariance_nees.py: give one --gt file per run (or none: KITTI's ROOT/poses/SEQ.txt)")
    results = [evaluate(r, g, args.inflation, args.drop_correlation) for r, g in zip(args.runs, gts, strict=True)]
    print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
