"""Can a per-frame model of the step's error calibrate the covariance on every road? Issue 40's test, one road left out.

For every E or PnP frame of the panel's runs (``studies/length_panel.py``'s case folders under ``PANEL/CONFIG``) the
step's error against the case's ground truth is split into rotation (3), direction (2) and length (1) blocks
(:func:`covariance_blocks.blocks`' split), each block's NEES ``z_b`` under the written covariance. The model scales each
block's covariance by ``exp(beta_b . x)``, ``x`` the frame's own measurements (``--features``: the tracker, log inlier
count, log parallax, the spread of the scale's sources, their number, whether the camera height or the CNN alone gave
the length, the cheirality fraction), fitted by the Gaussian likelihood of the blocks (convex in ``beta``; Newton's
method), each road weighted equally. Printed (JSON): per case the mean and median 6-DoF NEES as run, with the model
fitted on all roads, and fitted without the case's road (KITTI 06 at steps 1-3, KITTI 07 with its video, raw 0005,
each synthetic world, ``handheld_markers``). Issue 40's band: mean in [3, 12], median in [3, 9].

    python studies/covariance_model_fit.py RUNS/panel_s7/default [--features pnp log_inliers log_parallax]
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
import length_panel  # noqa: E402
from covariance_blocks import _basis, source_spread  # noqa: E402
from covariance_nees import read_run  # noqa: E402

from dfvo.geometry.pose_covariance import covariance_from_row, step_error  # noqa: E402

ROADS = {"kitti06": ("kitti06", "kitti06_step2", "kitti06_step3"),
         "kitti07": ("kitti07", "kitti07_step2", "kitti07_video"), "raw0005": ("kitti_raw_0005",),
         "drive": ("synthetic_drive",), "city": ("synthetic_city",),
         "straight": ("synthetic_straight",), "highway": ("synthetic_highway",), "handheld": ("handheld_markers",)}
DOF = np.array([3.0, 2.0, 1.0])


def _number(value: str | None, default: float) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return default


FEATURES = {
    "pnp": lambda r: float(r["tracker"] == "PnP"),
    "log_inliers": lambda r: math.log(max(_number(r["num_inliers"], 10.0), 10.0)),
    "log_parallax": lambda r: math.log(max(_number(r["parallax_px"], 0.01), 0.01)),
    "source_spread": lambda r: source_spread(r) or 0.0,
    "sources": lambda r: float(len(r["scale_source"].split("|")[0].split("+"))) if r.get("scale_source") else 0.0,
    "height": lambda r: float("height" in (r.get("scale_source") or "").split("|")[0]),
    "cnn_only": lambda r: float((r.get("scale_source") or "").split("|")[0] == "cnn"),
    "cheirality": lambda r: _number(r["cheirality_fraction"], 1.0),
}


def case_blocks(folder: Path, overrides: list[str], features: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """(F, 1 + len(features)) features (a constant first) and (F, 3) block NEES of a run's E and PnP frames."""
    _, pred, rows = read_run(folder)
    if folder.name.startswith("synthetic"):  # the run's own length (the panel's --synthetic-frames)
        overrides = [o for o in overrides if not o.startswith("data.num_frames")] + [f"data.num_frames={len(pred)}"]
    gt = length_panel.ground_truth(overrides)
    x, z = [], []
    for k in range(1, len(pred)):
        row, C = rows[k], covariance_from_row(rows[k])
        if row["tracker"] not in ("E", "PnP") or C is None:
            continue
        C, T = C.numpy(), np.linalg.inv(pred[k - 1]) @ pred[k]
        e = step_error(torch.from_numpy(T), torch.from_numpy(np.linalg.inv(gt[k - 1]) @ gt[k])).numpy()
        s = float(np.linalg.norm(T[:3, 3]))
        u, B = T[:3, 3] / s, _basis(T[:3, 3] / s)
        e_dir, C_dir = B @ e[3:] / s, B @ C[3:, 3:] @ B.T / s ** 2
        z.append([e[:3] @ np.linalg.solve(C[:3, :3], e[:3]), e_dir @ np.linalg.solve(C_dir, e_dir),
                  (u @ e[3:] / s) ** 2 / (u @ C[3:, 3:] @ u / s ** 2)])
        x.append([1.0] + [FEATURES[f](row) for f in features])
    return np.asarray(x), np.asarray(z)


def fit(x: np.ndarray, z: np.ndarray, weight: np.ndarray, iterations: int = 50) -> np.ndarray:
    """(3, P) ``beta`` of each block: minimises ``sum w (z exp(-x.beta) + dof x.beta)`` (Newton, damped)."""
    betas = np.zeros((3, x.shape[1]))
    for b in range(3):
        beta = np.zeros(x.shape[1])
        for _ in range(iterations):
            r = weight * z[:, b] * np.exp(-np.clip(x @ beta, -30, 30))
            grad = x.T @ (weight * DOF[b] - r)
            hess = (x * r[:, None]).T @ x + 1e-9 * np.eye(x.shape[1])
            step = np.linalg.solve(hess, grad)
            beta -= step / max(1.0, float(np.abs(step).max()))  # at most 1 in log scale a step
            if float(np.abs(step).max()) < 1e-8:
                break
        betas[b] = beta
    return betas


def nees6(x: np.ndarray, z: np.ndarray, betas: np.ndarray) -> dict[str, float]:
    n = sum(z[:, b] * np.exp(-np.clip(x @ betas[b], -30, 30)) for b in range(3))
    return {"mean": round(float(n.mean()), 2), "median": round(float(np.median(n)), 2)}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("panel", type=Path, help="one configuration's folder of a panel (case folders inside)")
    p.add_argument("--kitti-root", default=str(Path(__file__).resolve().parents[2] / "shared/data/kitti_odom"))
    p.add_argument("--video", default=None, help="the panel's --video (KITTI 07 as H.264), for its case")
    p.add_argument("--features", nargs="*", default=list(FEATURES), choices=list(FEATURES))
    p.add_argument("--exclude", nargs="*", default=[], choices=list(ROADS),
                   help="roads left out of every fit (still reported), e.g. those whose steps fail outright")
    a = p.parse_args(argv)
    cases = length_panel.cases(argparse.Namespace(kitti_root=a.kitti_root, synthetic_frames=60, video=a.video))
    data = {c: case_blocks(a.panel / c, cases[c], a.features) for c in cases
            if (a.panel / c / "summary.json").is_file()}
    road_of = {c: road for road, names in ROADS.items() for c in names}

    def fitted(names: list[str]) -> np.ndarray:
        x = np.concatenate([data[c][0] for c in names])
        z = np.concatenate([data[c][1] for c in names])
        per_road = {road_of[c]: sum(len(data[n][1]) for n in names if road_of[n] == road_of[c]) for c in names}
        w = np.concatenate([np.full(len(data[c][1]), 1.0 / per_road[road_of[c]]) for c in names])
        return fit(x, z, w)

    names = [c for c in data if c in road_of]
    fit_names = [c for c in names if road_of[c] not in a.exclude]
    everywhere = fitted(fit_names)
    out = {"panel": str(a.panel), "features": ["constant", *a.features], "excluded_from_fits": a.exclude,
           "beta_rotation_direction_length": everywhere.round(4).tolist(), "cases": {}}
    for c in names:
        ones = np.zeros_like(everywhere)
        loo = fitted([n for n in fit_names if road_of[n] != road_of[c]])
        out["cases"][c] = {"frames": len(data[c][1]), "as_run": nees6(*data[c], ones),
                           "fitted_on_all": nees6(*data[c], everywhere), "leave_road_out": nees6(*data[c], loo)}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
