"""Accuracy of a trained depth checkpoint (and of its untrained initialisation); prints JSON.

    python studies/depth_eval.py runs/depth_stereo_cpu/checkpoints/last.ckpt [--kitti-odom ../shared/data/kitti_odom]
        [--eigen-root KITTI_RAW --eigen-split eigen_test_files.txt]

- Synthetic: Eigen metrics (abs rel, δ<1.25; raw = metric, and median-scaled) on the validation worlds of the run's
  config (true depth, sky and > 80 m excluded), for the checkpoint and for the same seed's untrained network.
- KITTI odometry 06 (held out: never trained on): median relative depth error against stereo geometry, i.e.
  OpenCV semi-global matching on the rectified pair (a test-only dependency) turned into depth ``fx * b / d``,
  on the lower 70% of the image, 1-50 m, pixels whose disparity passes SGBM's uniqueness check. This reference
  is itself approximate (SGBM errors), so read it as a sanity check of the metric scale, not a benchmark.
- KITTI Eigen split (``--eigen-root``, a KITTI raw root with velodyne scans; optional ``--eigen-split`` file): the
  seven Eigen metrics of the checkpoint's depth network against projected LiDAR (:mod:`dfvo.source_eval.depth`, Garg
  crop, 1e-3..80 m), metric and median-scaled.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable

import lightning as L
import numpy as np
import torch
import torch.nn.functional as F
from omegaconf import OmegaConf

from dfvo.eval.depth_metrics import compute_depth_metrics
from dfvo.synthetic import SyntheticSequenceDataset
from dfvo.training.depth_module import DepthPoseModule


def synthetic_metrics(module: DepthPoseModule, data: SyntheticSequenceDataset) -> dict[str, float]:
    preds, gts = [], []
    with torch.no_grad():
        for i in range(len(data)):
            s = data[i]
            preds.append(module(s["image"][None]))
            gts.append(s["depth"][None])
    pred, gt = torch.cat(preds), torch.cat(gts)
    raw = compute_depth_metrics(pred, gt, max_depth=80.0, median_scaling=False)
    med = compute_depth_metrics(pred, gt, max_depth=80.0, median_scaling=True)
    return {"abs_rel": float(raw["abs_rel"]), "a1": float(raw["a1"]), "abs_rel_med": float(med["abs_rel"]),
            "a1_med": float(med["a1"])}


def kitti_stereo_median_error(predict: Callable[[torch.Tensor], torch.Tensor], root: str,
                              frames: list[int]) -> dict[str, float]:
    """Median relative error and median scale SGBM / prediction of ``predict`` (a full-resolution (1,3,H,W) image ->
    depth (1,1,h,w) in metres) on KITTI odometry 06 ``frames`` against OpenCV SGBM stereo depth (lower 70 % of the
    image, 1-50 m)."""
    import cv2

    from dfvo.data.kitti_odometry import KittiOdometry
    full = KittiOdometry(root, "06", stereo=True)
    errs, ratios = [], []
    for k in frames:
        s = full[k]
        left = (s["image"].mean(0).numpy() * 255).astype(np.uint8)
        right = (s["image_right"].mean(0).numpy() * 255).astype(np.uint8)
        sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=128, blockSize=5, P1=8 * 25, P2=32 * 25,
                                     uniquenessRatio=15, speckleWindowSize=100, speckleRange=2, disp12MaxDiff=1)
        disp = sgbm.compute(left, right).astype(np.float32) / 16.0
        fx, b = float(s["K"][0, 0]), float(-s["T_right_left"][0, 3])
        ref = torch.from_numpy(np.where(disp > 0, fx * b / np.maximum(disp, 1e-6), 0.0)).float()
        with torch.no_grad():
            pred = F.interpolate(predict(s["image"][None]).float(), size=ref.shape, mode="bilinear",
                                 align_corners=False)[0, 0]
        H = ref.shape[0]
        mask = (ref > 1.0) & (ref < 50.0)
        mask[: int(0.3 * H)] = False
        errs.append(((pred[mask] - ref[mask]).abs() / ref[mask]).median())
        ratios.append((ref[mask] / pred[mask]).median())
    return {"kitti06_median_rel_error": float(torch.stack(errs).mean()),
            "kitti06_median_scale_ratio_ref_over_pred": float(torch.stack(ratios).mean()), "kitti06_frames": frames}


def _at_size(module: DepthPoseModule, height: int, width: int) -> Callable[[torch.Tensor], torch.Tensor]:
    return lambda img: module(F.interpolate(img, size=(height, width), mode="bilinear", align_corners=False))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("checkpoint")
    p.add_argument("--kitti-odom", default=None, help="KITTI odometry root holding sequences/06 (optional)")
    p.add_argument("--eigen-root", default=None, help="KITTI raw root with velodyne_points (optional)")
    p.add_argument("--eigen-split", default=None, help="split file (default: every velodyne scan under the root)")
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    ckpt = torch.load(a.checkpoint, map_location="cpu", weights_only=False)
    cfg = OmegaConf.create(ckpt["hyper_parameters"]["cfg"])
    L.seed_everything(int(cfg.get("seed", 0)), verbose=False)
    init = DepthPoseModule(cfg).eval()  # same seed as the run: its initial weights
    trained = DepthPoseModule(cfg).eval()
    trained.load_state_dict(ckpt["state_dict"])
    d = cfg.data
    val = SyntheticSequenceDataset(list(d.val_seeds), int(d.val_num_frames), int(d.height), int(d.width))
    out = {"checkpoint": a.checkpoint, "global_step": int(ckpt["global_step"]), "epoch": int(ckpt["epoch"]),
           "resolution": f"{d.width}x{d.height}", "synthetic_val_seeds": list(d.val_seeds),
           "synthetic_before": synthetic_metrics(init, val), "synthetic_after": synthetic_metrics(trained, val)}
    if a.kitti_odom:
        out["kitti_before"] = kitti_stereo_median_error(_at_size(init, int(d.height), int(d.width)), a.kitti_odom,
                                                        [0, 25, 50])
        out["kitti_after"] = kitti_stereo_median_error(_at_size(trained, int(d.height), int(d.width)), a.kitti_odom,
                                                       [0, 25, 50])
    if a.eigen_root:
        from dfvo.source_eval.depth import evaluate_depth_task
        for key, median in (("eigen_metric", False), ("eigen_median_scaled", True)):
            res = evaluate_depth_task(OmegaConf.create({
                "gt_dir": a.eigen_root, "depth": {
                    "source": "network", "split": a.eigen_split, "median_scaling": median,
                    "network": {"checkpoint": a.checkpoint, "min_depth": float(cfg.model.get("min_depth", 0.1)),
                                "max_depth": float(cfg.model.get("max_depth", 100.0)),
                                "input_size": [int(d.height), int(d.width)]}}}))
            out[key] = {**res["metrics"], "num_frames": res["num_frames"], "scale_median": res["scale"]["median"]}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
