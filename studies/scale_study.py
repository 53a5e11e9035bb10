"""Tracker-only sweeps of the scale settings on cached flow and depth (what ``infer.py`` computes, computed once).

``infer.py``'s cost is the networks; the tracker is a few seconds per sequence. This script runs ``infer.py`` once
with the given overrides and keeps what its tracker was given (the refined flows, the depths, the intrinsics and the
images) in a cache file, then runs :class:`dfvo.tracking.VisualOdometry` with each requested
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
07 with the defaults: RPE 0.011162 m from both; with ``tracker.window.enabled=true`` 0.011052 m from both). The cache
holds the inputs of the code that built it: delete it after a change to the networks, the flow, its refinement or
the data settings (a cache of an older version of this script is refused). Measured tables and the ablation
commands: docs/scale.md.
"""

from __future__ import annotations

import argparse
import json
import math
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


def build_cache(overrides: list[str], path: Path) -> dict:
    """Run ``infer.py`` once with ``overrides`` (outputs in a temporary folder) and keep what its tracker was given:
    the refined flows, the depths of each pair's two frames, the intrinsics and the images of every frame (the
    photometric road scale reads them), plus the ground truth; saved to ``path``. Replaying them through
    :meth:`VisualOdometry.run` gives ``infer.py``'s poses exactly (batched == streaming)."""
    import tempfile

    from dfvo.inference.frames import build_sequence
    from dfvo.inference.pipeline import run_inference
    from dfvo.sources import build_depth_source
    from dfvo.tracking import VisualOdometry

    batches: list[tuple[tuple, dict]] = []
    original = VisualOdometry._batch

    def recording(self, *args, **kwargs):  # the one entry of step() and run(): record what the tracker is given
        batches.append((args, kwargs))
        return original(self, *args, **kwargs)

    icfg = compose(overrides)
    threads = torch.get_num_threads()
    VisualOdometry._batch = recording
    try:
        with tempfile.TemporaryDirectory() as out:
            run_inference(compose([*overrides, f"out_dir={out}", "progress=false"]))
    finally:
        VisualOdometry._batch = original
        torch.set_num_threads(threads)
    if not batches:
        raise SystemExit(f"scale_study: infer.py {' '.join(overrides)} tracked no frame; nothing to cache")
    names = ("flow_fwd", "flow_bwd", "depth", "K", "depth_next", "images")
    calls = [dict(zip(names, args, strict=False)) | kwargs for args, kwargs in batches]

    def cat(key: str, drop_first: bool = False) -> torch.Tensor | None:
        parts = [c.get(key) for c in calls]
        if any(x is None for x in parts):
            return None
        return torch.cat([x[1:] if drop_first and k else x for k, x in enumerate(parts)])

    seq = build_sequence(icfg.data, icfg.seq, icfg.img_res)
    depth, images = cat("depth"), cat("images", drop_first=True)
    depth_next = cat("depth_next")
    if depth_next is None:  # a one-view run: the later frames' depths are the next pairs'; the last one is computed
        last = build_depth_source(icfg.depth, seq.world, "cpu")(images[-1:], [len(images) - 1])
        depth_next = torch.cat([depth[1:], last.to(depth.dtype)])
    data = {"name": seq.name, "flow_fwd": cat("flow_fwd"), "flow_bwd": cat("flow_bwd"), "depth": depth,
            "depth_next": depth_next, "K": cat("K"), "images": images,
            "poses": None if seq.poses is None else torch.from_numpy(np.asarray(seq.poses)), "overrides": overrides}
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

    icfg = compose(base + setting)
    tcfg = icfg.tracker
    vo = VisualOdometry(tcfg, icfg.flow.refine.pyramid)
    t0 = time.perf_counter()
    res = vo.run(data["flow_fwd"], data["flow_bwd"], data["depth"], data["K"], batch_size=4,
                 depths_next=data["depth_next"], images=data["images"])
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
    cache = args.cache
    data = torch.load(cache, weights_only=False) if cache.exists() else build_cache(args.overrides, cache)
    if "images" not in data:
        raise SystemExit(f"--cache {args.cache}: written by an older scale_study.py (no images); delete it to rebuild")
    base = list(data["overrides"])
    for s in args.setting or ["default="]:
        name, _, ov = s.partition("=")
        r = evaluate(data, [o for o in ov.split(",") if o], base)
        print(json.dumps({"name": name, **r}), flush=True)


if __name__ == "__main__":
    main()
