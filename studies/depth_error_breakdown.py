"""Where a depth network's error against real LiDAR lies (issue 38): drive 2011_09_26_0005's 16 held-out scans.

Every LiDAR pixel that ``python -m dfvo.evaluate task=depth`` scores (the Eigen crop, 1e-3..80 m, the same
projection and bilinear resize) is pooled over the 16 frames and split by

- distance (LiDAR depth 0-10, 10-20, 20-40, 40-80 m),
- what the pixel shows, by a proxy: ``edge`` when the LiDAR depths within 7 pixels of it span more than 25 % of its
  own depth (an object's outline, where a low-resolution prediction resized up blends the two sides), else
  ``interior``; and the image's lower third (mostly road) against the rest,

with each group's share of the pixels, its abs rel (metric; the pooled mean, not the per-frame mean of the Eigen
table) and median prediction / LiDAR ratio, and its share of the summed absolute relative error: what a recipe
would have to fix to move the headline number. ``--input-size HxW`` runs the network at another size than its
training size (its metadata), e.g. to see how much of the error is resolution.

    python studies/depth_error_breakdown.py --weights dfvo/checkpoints/depth.safetensors \
        campaign/depth_scene_shadow/weights.safetensors
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from dfvo.data.image_io import read_image
from dfvo.data.kitti_eigen import crop_mask, frame_size, project_velodyne, read_split, read_velodyne
from dfvo.io.checkpoint import find_checkpoint
from dfvo.source_eval.depth import velodyne_projection
from dfvo.sources.networks import NetworkDepth

REPO = Path(__file__).resolve().parent.parent
ROOT = REPO.parent / "shared" / "data" / "kitti_raw_test"
SPLIT = REPO / "dfvo" / "eval" / "splits" / "kitti_raw_0005_lidar.txt"
BINS = ((0.0, 10.0), (10.0, 20.0), (20.0, 40.0), (40.0, 80.0))


def lidar_pairs(weights: str, input_size: tuple[int, int] | None) -> dict[str, np.ndarray]:
    """Pooled LiDAR depth, prediction, edge flag and image row fraction of every scored pixel of the 16 scans."""
    net = NetworkDepth(find_checkpoint(weights, "--weights"), input_size=input_size)
    out: dict[str, list[np.ndarray]] = {"gt": [], "pred": [], "edge": [], "row": []}
    for frame in read_split(SPLIT):
        P, calib_size = velodyne_projection(frame.calib_dir(ROOT), frame.camera)
        size = frame_size(ROOT, frame, calib_size)
        gt = project_velodyne(read_velodyne(frame.velodyne(ROOT)), P, size, 0)[0]  # (H, W)
        with torch.no_grad():
            pred = net(read_image(frame.image(ROOT))[None])
        pred = F.interpolate(pred.float(), size=size, mode="bilinear", align_corners=False)[0, 0]
        valid = (gt > 1e-3) & (gt < 80.0) & crop_mask(size, "garg")[0]
        # the spread of the LiDAR depths around each pixel (7-pixel radius), from the sparse scan
        filled = torch.where(gt > 0, gt, torch.nan)[None, None]
        hi = F.max_pool2d(torch.nan_to_num(filled, nan=0.0), 15, 1, 7)[0, 0]
        lo = -F.max_pool2d(torch.nan_to_num(-filled, nan=-1e4), 15, 1, 7)[0, 0]
        edge = (hi - lo) > 0.25 * gt
        rows = torch.arange(size[0], dtype=torch.float32)[:, None].expand(size) / size[0]
        out["gt"].append(gt[valid].numpy())
        out["pred"].append(pred.clamp(1e-3, 80.0)[valid].numpy())
        out["edge"].append(edge[valid].numpy())
        out["row"].append(rows[valid].numpy())
    return {k: np.concatenate(v) for k, v in out.items()}


def breakdown(pairs: dict[str, np.ndarray]) -> dict:
    gt, pred = pairs["gt"], pairs["pred"]
    rel = np.abs(pred - gt) / gt
    total = rel.sum()
    groups = {f"{a:.0f}-{b:.0f} m": (gt >= a) & (gt < b) for a, b in BINS}
    groups["edge"] = pairs["edge"]
    groups["interior"] = ~pairs["edge"]
    groups["lower third"] = pairs["row"] >= 2 / 3
    groups["upper two thirds"] = pairs["row"] < 2 / 3
    out = {"pixels": int(gt.size), "abs_rel_pooled": round(float(rel.mean()), 4),
           "median_pred_over_gt": round(float(np.median(pred / gt)), 4), "groups": {}}
    for name, m in groups.items():
        if not m.any():
            continue
        out["groups"][name] = {"share_of_pixels": round(float(m.mean()), 3), "abs_rel": round(float(rel[m].mean()), 4),
                               "median_pred_over_gt": round(float(np.median(pred[m] / gt[m])), 3),
                               "share_of_error": round(float(rel[m].sum() / total), 3)}
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--weights", nargs="+", required=True)
    p.add_argument("--input-size", default=None, help="HxW the network runs at (default: its training size)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", default=None, help="write the JSON here too")
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    size = tuple(int(v) for v in a.input_size.lower().split("x")) if a.input_size else None
    result = {w: breakdown(lidar_pairs(w, size)) for w in a.weights}
    text = json.dumps({"input_size": a.input_size, "networks": result}, indent=1)
    print(text)
    if a.out:
        Path(a.out).write_text(text + "\n")


if __name__ == "__main__":
    main()
