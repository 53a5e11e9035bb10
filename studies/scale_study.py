"""Tracker-only sweeps of the scale settings on cached flow and depth (what ``infer.py`` computes, computed once).

``infer.py``'s cost is the networks; the tracker is a few seconds per sequence. This script composes ``infer.py``'s
own configuration (the same Hydra overrides), computes the sources' flow (refined as ``infer.py`` refines it) and
depth of every frame once into a cache file, then runs :class:`dfvo.tracking.VisualOdometry` with each requested
tracker setting on the cached tensors and prints one JSON object per setting:

    - ``rpe_m``, ``rpe_deg``, ``ate_m``: ``metrics.json``'s numbers (6-DoF alignment); ``rpe_m_true_lengths``: the
      RPE with every relative translation rescaled to its true length (what a perfect scale would give);
    - ``length_ratio``: mean / std / min / max of |t_pred| / |t_true| per frame (frames moving > 0.1 m);
    - ``max_translation_error_m``: the largest |t_pred - t_true| of one frame's relative translation (and its frame);
    - ``trackers``: frames per tracker; ``fallback_reasons``: counts;
    - ``sources_log_ratio_on_E_frames``: per scale source (``scale_cnn``, ``scale_height``, ``scale_temporal``,
      ``scale``): frames where it exists, and the mean / std of log(source / true length) over them (the measured
      spreads the fusion's variances come from);
    - ``temporal_relative_log_error``: the three-frame relative scale's own error, log(scale_temporal / true) minus
      log(previous length used / previous true length);
    - ``network_road_height_log_ratio``: with ``tracker.road_plane.points=depth``, log(network road height / camera
      height).

    python studies/scale_study.py --cache /tmp/k06.pt -o data=kitti_odom data.root=../shared/data/kitti_odom \
        seq=06 -s default= -s no_height=data.camera_height=null \
    -s paper=tracker.scale.depth_views=1,tracker.scale.temporal=false,tracker.gate.enabled=false,data.camera_height=null

``-o`` takes ``infer.py`` overrides for the data and sources (cached: change them, change ``--cache``); each
``-s NAME=OVERRIDE[,OVERRIDE...]`` is one tracker setting (overrides of ``tracker.*`` or the ``scale=`` group).
The tracker runs batched (``VisualOdometry.run``), identical to ``infer.py``'s streaming of the same tensors (KITTI
06 with the defaults: RPE 0.0377 m from both). The cache holds the flow and depth of the code that built it: delete it
after a change to the networks, the flow or its refinement. Measured tables and the ablation commands: docs/scale.md.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import torch

from dfvo.eval import evaluate_trajectory


def compose(overrides: list[str]):
    """``infer.py``'s typed configuration for ``overrides``."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_module

    from dfvo.inference.config import typed

    with initialize_config_module(config_module="dfvo.conf.infer", version_base="1.3"):
        cfg = hydra_compose(config_name="infer", overrides=overrides)
    return typed(cfg)


def build_cache(overrides: list[str], path: Path, batch: int = 4) -> dict:
    """Flow (refined) of every pair and depth of every frame of the sequence ``overrides`` describe, saved to path."""
    from dfvo.inference.frames import build_sequence
    from dfvo.matching.flow_refinement import refine_forward_backward
    from dfvo.sources import NetworkFlow, build_depth_source, build_flow_source, check_sources

    icfg = compose(overrides)
    seq = build_sequence(icfg.data, icfg.seq, icfg.img_res)
    check_sources(icfg.flow, icfg.depth, seq.world)
    flow_src = build_flow_source(icfg.flow, seq.world, "cpu")
    depth_src = build_depth_source(icfg.depth, seq.world, "cpu")
    refine = icfg.flow.refine if isinstance(flow_src, NetworkFlow) and icfg.flow.refine.iterations > 0 else None
    fwds, bwds, depths = [], [], []
    prev = seq.image(0)[None]
    depths.append(depth_src(prev, [0]))
    for first in range(0, seq.length - 1, batch):
        idx = list(range(first, min(first + batch, seq.length - 1)))
        imgs = torch.cat([prev] + [seq.image(i + 1)[None] for i in idx])
        prev = imgs[-1:]
        with torch.no_grad():
            f, b = flow_src(imgs[:-1], imgs[1:], idx)
            if refine is not None:
                f, b = refine_forward_backward(imgs[:-1], imgs[1:], f, b, refine)
            depths.append(depth_src(imgs[1:], [i + 1 for i in idx]))
        fwds.append(f)
        bwds.append(b)
        print(f"cached pairs up to {idx[-1] + 1}/{seq.length - 1}", file=sys.stderr, flush=True)
    data = {"name": seq.name, "flow_fwd": torch.cat(fwds), "flow_bwd": torch.cat(bwds), "depth": torch.cat(depths),
            "K": seq.K.clone(), "poses": None if seq.poses is None else torch.from_numpy(np.asarray(seq.poses)),
            "overrides": overrides}
    torch.save(data, path)
    return data


def _stats(x: list[float]) -> dict:
    a = np.asarray(x, np.float64)
    if a.size == 0:
        return {"n": 0}
    return {"n": int(a.size), "mean": float(a.mean()), "std": float(a.std()), "min": float(a.min()),
            "max": float(a.max())}


def evaluate(data: dict, setting: list[str], base: list[str]) -> dict:
    """Run the tracker of ``base + setting`` on the cached tensors; the numbers listed in the module docstring."""
    from dfvo.tracking import VisualOdometry

    tcfg = compose(base + setting).tracker
    vo = VisualOdometry(tcfg)
    t0 = time.perf_counter()
    res = vo.run(data["flow_fwd"], data["flow_bwd"], data["depth"][:-1], data["K"], batch_size=4,
                 depths_next=data["depth"][1:])
    wall = time.perf_counter() - t0
    pred = np.stack([np.eye(4)] + [r.T_w_cur.numpy() for r in res])
    out: dict = {"setting": setting, "tracker_seconds": round(wall, 2)}
    P = data["poses"]
    diags = [r.diagnostics for r in res]
    out["trackers"] = dict(Counter(str(d.tracker) for d in diags))
    out["fallback_reasons"] = dict(Counter(d.fallback_reason for d in diags if d.fallback_reason))
    if P is None:
        return out
    P = P.numpy()
    m = evaluate_trajectory(P, pred, align="6dof")
    out.update({k: m[k] for k in ("rpe_m", "rpe_deg", "ate_m")})
    rel_true = np.linalg.inv(P[:-1]) @ P[1:]
    true_len = np.linalg.norm(rel_true[:, :3, 3], axis=-1)
    pred_t = np.stack([r.T_prev_cur[:3, 3].numpy() for r in res])
    err = np.linalg.norm(pred_t - rel_true[:, :3, 3], axis=-1)
    moving = true_len > 0.1
    ratio = np.linalg.norm(pred_t, axis=-1)[moving] / true_len[moving]
    out["length_ratio"] = _stats(ratio.tolist())
    rel_pred = np.stack([r.T_prev_cur.numpy() for r in res])
    norm = np.linalg.norm(rel_pred[:, :3, 3], axis=-1, keepdims=True)
    rel_pred[:, :3, 3] = np.where(norm > 1e-12, rel_pred[:, :3, 3] / np.maximum(norm, 1e-12) * true_len[:, None], 0.0)
    composed = [np.eye(4)]
    for T in rel_pred:
        composed.append(composed[-1] @ T)
    out["rpe_m_true_lengths"] = evaluate_trajectory(P, np.stack(composed), align="6dof")["rpe_m"]
    out["max_translation_error_m"] = {"value": float(err.max()), "frame": int(err.argmax()) + 1}
    out["frames_translation_error_over_1m"] = int((err > 1.0).sum())
    sources = {}
    for name in ("scale_cnn", "scale_height", "scale_temporal", "scale"):
        logs = [math.log(getattr(d, name, None) / true_len[k]) for k, d in enumerate(diags)
                if getattr(d, name, None) and moving[k] and d.tracker == "E"]
        sources[name] = _stats(logs)
    out["sources_log_ratio_on_E_frames"] = sources
    used_len = np.linalg.norm(pred_t, axis=-1)
    rel_err = [math.log(d.scale_temporal / true_len[k]) - math.log(used_len[k - 1] / true_len[k - 1])
               for k, d in enumerate(diags) if k > 0 and d.scale_temporal and moving[k] and moving[k - 1]]
    out["temporal_relative_log_error"] = _stats(rel_err)
    road = [math.log(d.camera_height_fit / tcfg.scale.camera_height) for d in diags
            if d.camera_height_fit and getattr(tcfg.road_plane, "points", "") == "depth"]
    out["network_road_height_log_ratio"] = _stats(road)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cache", required=True, type=Path, help="cache file (built when absent)")
    p.add_argument("-o", "--overrides", nargs="*", default=[], help="infer.py overrides of the data and sources")
    p.add_argument("-s", "--setting", action="append", default=[], help="NAME=OVERRIDE[,OVERRIDE...]")
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    data = torch.load(args.cache) if args.cache.exists() else build_cache(args.overrides, args.cache)
    base = list(data["overrides"])
    for s in args.setting or ["default="]:
        name, _, ov = s.partition("=")
        r = evaluate(data, [o for o in ov.split(",") if o], base)
        print(json.dumps({"name": name, **r}), flush=True)


if __name__ == "__main__":
    main()
