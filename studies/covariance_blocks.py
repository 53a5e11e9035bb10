"""Where a run's step covariance is right or wrong: its NEES split into rotation (3), direction (2) and length (1)
blocks, how the errors compare with the predicted standard deviations, their lag-1 autocorrelation, and whether
the spread of the scale's sources predicts the length's error. Prints JSON.

For every frame tracked by E or PnP of an ``infer.py`` run (``frames.csv``, the pose file, ``summary.json``) against
its ground truth: the step's error (:func:`dfvo.geometry.pose_covariance.step_error`), the rotation block of the
written covariance, and its translation block split in the step's own axes: along the translation (the length,
relative: ``u^T C u / s^2``) and across it (the direction, in radians). ``extra_length_log_std`` adds a length
variance to every E frame (what ``tracker.covariance`` would add) to see its effect. A calibrated block has a mean
NEES equal to its dimension; white noise in the ground-truth poses shows as a lag-1 autocorrelation near -0.5 of the
step errors (each pose's error enters two steps with opposite signs).

    python studies/covariance_blocks.py OUT --gt GT.txt [--extra-length-log-std 0.04]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from covariance_nees import read_kitti_poses, read_run  # noqa: E402

from dfvo.geometry.pose_covariance import covariance_from_row, step_error  # noqa: E402


def _basis(u: np.ndarray) -> np.ndarray:
    """(2,3) orthonormal basis across the unit vector ``u``."""
    h = np.zeros(3)
    h[int(np.argmin(np.abs(u)))] = 1.0
    b1 = np.cross(u, h)
    b1 /= np.linalg.norm(b1)
    return np.stack([b1, np.cross(u, b1)])


def source_spread(row: dict) -> float | None:
    """RMS of log(observation / fused length) over the scale sources a frame used (the CNN scale divided by its
    estimated bias); None with fewer than two."""
    if not row.get("scale"):
        return None
    s = float(row["scale"])
    values = {"homography": row.get("scale_homography"), "temporal": row.get("scale_temporal"),
              "height": row.get("scale_height"),
              "cnn": (float(row["scale_cnn"]) / float(row["cnn_bias"] or 1.0)) if row.get("scale_cnn") else None}
    used = (row.get("scale_source") or "").split("|")[0].split("+")
    logs = [math.log(float(values[n]) / s) for n in used if values.get(n) and float(values[n]) > 0]
    return float(np.sqrt(np.mean(np.square(logs)))) if len(logs) >= 2 else None


def blocks(run: Path, gt_path: Path, extra_length_log_std: float = 0.0) -> dict:
    _, pred, rows = read_run(run)
    gt = read_kitti_poses(gt_path)[: len(pred)]
    nees, ratio, err, spread = [], [], [], []
    for k in range(1, len(pred)):
        row = rows[k]
        C = covariance_from_row(row)
        if row["tracker"] not in ("E", "PnP") or C is None:
            continue
        C = C.numpy()
        T = np.linalg.inv(pred[k - 1]) @ pred[k]
        e = step_error(torch.from_numpy(T), torch.from_numpy(np.linalg.inv(gt[k - 1]) @ gt[k])).numpy()
        s = float(np.linalg.norm(T[:3, 3]))
        u = T[:3, 3] / s
        B = _basis(u)
        e_rot, e_dir, e_len = e[:3], B @ e[3:] / s, float(u @ e[3:]) / s
        C_rot, C_dir = C[:3, :3], B @ C[3:, 3:] @ B.T / s ** 2
        v_len = float(u @ C[3:, 3:] @ u) / s ** 2 + (extra_length_log_std ** 2 if row["tracker"] == "E" else 0.0)
        nees.append((float(e_rot @ np.linalg.solve(C_rot, e_rot)), float(e_dir @ np.linalg.solve(C_dir, e_dir)),
                     e_len ** 2 / v_len))
        ratio.append((np.linalg.norm(e_rot) / math.sqrt(np.trace(C_rot)),
                      np.linalg.norm(e_dir) / math.sqrt(np.trace(C_dir)), abs(e_len) / math.sqrt(v_len)))
        err.append(np.concatenate([e_rot, e_dir * s, [e_len * s]]))
        spread.append((source_spread(row), abs(e_len)))
    if not nees:
        return {"run": str(run), "frames": 0}
    n, r, x = np.array(nees), np.array(ratio), np.array(err)

    def lag1(v: np.ndarray) -> float:
        v = v - v.mean()
        return float((v[1:] * v[:-1]).sum() / max((v * v).sum(), 1e-300))

    pairs = np.array([(a, b) for a, b in spread if a is not None])
    names = ("rotation", "direction", "length")
    return {
        "run": str(run), "frames": len(n), "extra_length_log_std": extra_length_log_std,
        "nees_6dof": {"mean": float(n.sum(1).mean()), "median": float(np.median(n.sum(1)))},
        "nees_blocks_mean": dict(zip(names, n.mean(0).tolist(), strict=True)),
        "median_error_over_predicted_std": dict(zip(names, np.median(r, 0).tolist(), strict=True)),
        "rms_error_m": {"across": float(np.sqrt((x[:, 3:5] ** 2).sum(1).mean())),
                        "along": float(np.sqrt((x[:, 5] ** 2).mean()))},
        "lag1_autocorrelation": {"rx": lag1(x[:, 0]), "ry": lag1(x[:, 1]), "rz": lag1(x[:, 2]),
                                 "across_1": lag1(x[:, 3]), "across_2": lag1(x[:, 4]), "length": lag1(x[:, 5])},
        "corr_source_spread_vs_length_error": (float(np.corrcoef(pairs[:, 0], pairs[:, 1])[0, 1])
                                               if len(pairs) > 2 else None),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", type=Path)
    p.add_argument("--gt", nargs="+", type=Path, required=True, help="ground-truth KITTI pose files, one per run")
    p.add_argument("--extra-length-log-std", type=float, default=0.0)
    a = p.parse_args()
    if len(a.gt) != len(a.runs):
        sys.exit("covariance_blocks.py: give one --gt file per run")
    print(json.dumps([blocks(r, g, a.extra_length_log_std) for r, g in zip(a.runs, a.gt, strict=True)], indent=1))


if __name__ == "__main__":
    main()
