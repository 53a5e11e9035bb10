"""``python -m dfvo.evaluate task=depth``: single-view depth on the KITTI Eigen split (or any KITTI raw frames).

For every frame of the split (:func:`dfvo.data.kitti_eigen.read_split`; without one, every velodyne scan under
``gt_dir``) the ground truth is the velodyne scan projected into the rectified colour camera
(:func:`dfvo.data.kitti_eigen.project_velodyne`); the prediction comes from the depth network
(:class:`dfvo.sources.networks.NetworkDepth`, run on the native image and resized back by it) or from files in
``pred_dir``, and is resized (bilinear) to the ground truth's size. Pixels inside the crop (Garg by default) with
ground truth in ``(min_depth, max_depth)`` are scored; with ``median_scaling`` each prediction is first multiplied by
``median(gt) / median(pred)``; predictions are clamped to ``[min_depth, max_depth]``
(:func:`dfvo.eval.depth_metrics.compute_depth_metrics`). The seven Eigen metrics are averaged over frames.

Prediction files (``source=pred``): ``pred_dir/DATE/DATE_drive_XXXX_sync/FFFFFFFFFF.npy`` (float depth in metres,
``(H,W)`` or ``(1,H,W)``, any size) or ``.png`` (KITTI depth format: uint16 metres * 256, 0 = none), or
``pred_dir/NNNNNN.npy`` by line index of the split, or ``pred_dir`` = one ``.npy`` file of ``(N,H,W)`` depths in
split order.

Settings: :class:`dfvo.source_eval.config.DepthEvalConfig` (the ``depth:`` node of the command).
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

from dfvo.data.image_io import DatasetError, read_image
from dfvo.data.kitti_eigen import (
    EigenFrame,
    crop_mask,
    frame_size,
    list_velodyne_frames,
    project_velodyne,
    read_split,
    read_velodyne,
    velodyne_projection,
)
from dfvo.eval.depth_metrics import DEPTH_METRIC_NAMES, compute_depth_metrics
from dfvo.source_eval.config import DepthEvalConfig, task_settings
from dfvo.sources import find_checkpoint
from dfvo.sources.networks import NetworkDepth

__all__ = ["evaluate_depth_task", "depth_settings", "format_depth_table"]



def depth_settings(cfg: Any) -> DepthEvalConfig:
    """The ``depth:`` node of ``cfg`` as a :class:`DepthEvalConfig` (missing keys: its defaults; unknown: an error)."""
    return task_settings(DepthEvalConfig, cfg, "depth")


class _Predictions:
    """Reads predictions from ``pred_dir`` (see the module docstring)."""

    def __init__(self, pred_dir: Path) -> None:
        self.dir = pred_dir
        self.stack = None
        if pred_dir.is_file():
            if pred_dir.suffix != ".npy":
                raise ValueError(f"pred_dir={pred_dir}: a single prediction file must be an (N,H,W) .npy array")
            self.stack = np.load(pred_dir, mmap_mode="r")
            if self.stack.ndim != 3:
                raise ValueError(f"pred_dir={pred_dir}: expected an (N,H,W) array of depths, got {self.stack.shape}")
        elif not pred_dir.is_dir():
            raise FileNotFoundError(f"depth.source=pred: pred_dir={pred_dir} does not exist")

    def __call__(self, index: int, frame: EigenFrame) -> torch.Tensor:
        if self.stack is not None:
            if index >= len(self.stack):
                raise ValueError(f"pred_dir={self.dir}: holds {len(self.stack)} depth maps, the split has more lines")
            arr = np.asarray(self.stack[index], dtype=np.float32)
        else:
            base = self.dir / frame.drive / f"{frame.frame:010d}"
            candidates = [base.with_suffix(".npy"), base.with_suffix(".png"), self.dir / f"{index:06d}.npy"]
            path = next((c for c in candidates if c.is_file()), None)
            if path is None:
                raise FileNotFoundError(f"pred_dir: no prediction for {frame.drive} {frame.frame:010d} (looked for "
                                        f"{candidates[0]}, {candidates[1].name}, {candidates[2]})")
            if path.suffix == ".png":
                with Image.open(path) as im:
                    arr = np.asarray(im, dtype=np.float32) / 256.0
            else:
                arr = np.load(path).astype(np.float32)
        arr = np.squeeze(arr)
        if arr.ndim != 2:
            raise ValueError(f"pred_dir: prediction for {frame.drive} {frame.frame:010d} has shape {arr.shape}; "
                             "expected (H,W) depth")
        return torch.from_numpy(np.array(arr, dtype=np.float32))[None, None]


def _network(s: DepthEvalConfig) -> Any:
    net = s.network
    return NetworkDepth(find_checkpoint(net.checkpoint, "depth.network.checkpoint"), float(net.depth_scale),
                        float(net.min_depth), float(net.max_depth), device=str(s.device), input_size=net.input_size,
                        flip_average=bool(net.flip_average))


def evaluate_depth_task(cfg: Any) -> dict[str, Any]:
    """Evaluate depth predictions on KITTI raw frames against projected velodyne scans.

    Args:
        cfg: the command's config: ``gt_dir`` (KITTI raw root holding ``DATE/`` folders), optional ``pred_dir``,
            and the ``depth`` node (:class:`DepthEvalConfig`; missing keys take its defaults).

    Returns:
        ``{"task", "gt_dir", "pred_dir", "source", "split", "crop", "median_scaling", "depth_range",
        "num_frames", "skipped" (frames without ground truth in range), "metrics": {abs_rel, sq_rel, rmse,
        rmse_log, a1, a2, a3}, "scale": {"median", "std"} (median-scaling factors; 1 without), "per_frame",
        "source_seconds_per_frame"}``.
    """
    s = depth_settings(cfg)
    gt_dir = cfg.get("gt_dir")
    if not gt_dir:
        raise ValueError("task=depth needs gt_dir=PATH (a KITTI raw root with DATE/DATE_drive_XXXX_sync/"
                         "velodyne_points/data/*.bin and the DATE/calib_*.txt files)")
    root = Path(gt_dir)
    pred_dir = Path(cfg["pred_dir"]) if cfg.get("pred_dir") else None
    kind = str(s.source)
    kind = ("pred" if pred_dir else "network") if kind == "auto" else kind
    if kind == "pred" and pred_dir is None:
        raise ValueError("depth.source=pred needs pred_dir=PATH")
    frames = read_split(s.split) if s.split else list_velodyne_frames(root)
    if s.max_frames:
        frames = frames[: int(s.max_frames)]
    predict = _Predictions(pred_dir) if kind == "pred" else _network(s)
    projections: dict[tuple[str, int], tuple[np.ndarray, tuple[int, int] | None]] = {}
    per_frame, seconds, skipped = [], 0.0, []
    for i, frame in enumerate(frames):
        key = (str(frame.calib_dir(root)), frame.camera)
        if key not in projections:
            projections[key] = velodyne_projection(frame.calib_dir(root), frame.camera)
        P, calib_size = projections[key]
        size = frame_size(root, frame, calib_size)
        gt = project_velodyne(read_velodyne(frame.velodyne(root)), P, size, int(s.gt_pixel_offset))
        t0 = time.perf_counter()
        if kind == "pred":
            pred = predict(i, frame)
        else:
            pred = predict(read_image(frame.image(root))[None].to(str(s.device))).cpu()
        seconds += time.perf_counter() - t0
        if not torch.isfinite(pred).all() or bool((pred <= 0).any()):
            raise ValueError(f"depth prediction for {frame.drive} {frame.frame:010d} holds non-positive or "
                             "non-finite values; expected depth in metres > 0")
        if tuple(pred.shape[-2:]) != size:
            pred = F.interpolate(pred.float(), size=size, mode="bilinear", align_corners=False)
        name = f"{frame.drive} {frame.frame:010d} {'l' if frame.camera == 2 else 'r'}"
        try:
            m = compute_depth_metrics(pred.float(), gt[None], float(s.min_depth), float(s.max_depth),
                                      bool(s.median_scaling), crop_mask(size, str(s.crop))[None])
        except ValueError:
            skipped.append(name)
            continue
        valid = (gt > float(s.min_depth)) & (gt < float(s.max_depth)) & crop_mask(size, str(s.crop))
        per_frame.append({"frame": name, **{k: m[k] for k in DEPTH_METRIC_NAMES}, "scale": m["scale"],
                          "num_points": int(valid.sum())})
    if not per_frame:
        raise DatasetError(f"task=depth: no frame has ground truth inside ({s.min_depth}, {s.max_depth}) m in the "
                           f"{s.crop} crop ({len(frames)} frames under {root})")
    metrics = {k: sum(f[k] for f in per_frame) / len(per_frame) for k in DEPTH_METRIC_NAMES}
    scales = np.array([f["scale"] for f in per_frame])
    return {"task": "depth", "gt_dir": str(root), "pred_dir": str(pred_dir) if pred_dir else None, "source": kind,
            "split": str(s.split) if s.split else None, "crop": str(s.crop), "median_scaling": bool(s.median_scaling),
            "depth_range": [float(s.min_depth), float(s.max_depth)], "num_frames": len(per_frame),
            "skipped": skipped, "metrics": metrics,
            "scale": {"median": float(np.median(scales)), "std": float(np.std(scales / np.median(scales)))},
            "per_frame": per_frame, "source_seconds_per_frame": seconds / max(len(frames), 1)}


def format_depth_table(result: dict[str, Any]) -> str:
    """The seven Eigen metrics of :func:`evaluate_depth_task` as a two-line table (monodepth's layout)."""
    m = result["metrics"]
    head = "".join(f"{k:>10}" for k in DEPTH_METRIC_NAMES)
    row = "".join(f"{m[k]:10.4f}" if m[k] is not None and math.isfinite(m[k]) else f"{'-':>10}"
                  for k in DEPTH_METRIC_NAMES)
    scale = result["scale"]
    note = (f"median scaling: ratio median {scale['median']:.3f}, std {scale['std']:.3f}"
            if result["median_scaling"] else "no median scaling (metric depth)")
    return (f"depth: {result['source']} on {result['num_frames']} frames ({result['crop']} crop, "
            f"{result['depth_range'][0]:g}-{result['depth_range'][1]:g} m, {note})\n{head}\n{row}")
