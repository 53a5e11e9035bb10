"""Tracker benchmark: per-frame time and accuracy of the batched E-tracker (5 RANSAC repeats with the local
optimisation of E, GRIC, simple scale) on 2000 noisy correspondences with outliers, side by side with the same
E-RANSAC without its local optimisation (``dfvo_without_lo``: time and accuracy of ``refine=False``) and with
OpenCV (findEssentialMat + recoverPose, same threshold, same inputs), plus the whole odometry loop on the
synthetic world with oracle flow and depth.

Usage: python benchmarks/tracker.py [--frames 16] [--batch 8] [--noise 0.5] [--outliers 0.3] [--threshold 1.0]
Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time

import torch

from dfvo.geometry.camera import project_points, transform_points
from dfvo.geometry.gric import gric_essential, gric_homography
from dfvo.geometry.se3 import direction_error_deg, pose_from_axis_angle, rotation_error_deg
from dfvo.geometry.two_view import decompose_essential, find_essential_ransac, find_homography_ransac
from dfvo.tracking import TrackerConfig, VisualOdometry
from dfvo.tracking.scale import simple_scale, triangulated_depth


def make_frames(B: int, N: int, noise: float, outliers: float, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    K = torch.tensor([[718.856, 0.0, 607.19], [0.0, 718.856, 185.21], [0.0, 0.0, 1.0]], dtype=torch.float64)
    K = K.repeat(B, 1, 1)
    z = torch.rand(B, N, generator=g, dtype=torch.float64) * 45 + 4
    X = torch.stack([(torch.rand(B, N, generator=g, dtype=torch.float64) - 0.5) * 1.6 * z,
                     (torch.rand(B, N, generator=g, dtype=torch.float64) - 0.5) * 0.5 * z, z], -1)
    aa = (torch.rand(B, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([0.01, 0.06, 0.01]).double()
    t = torch.cat([(torch.rand(B, 2, generator=g, dtype=torch.float64) - 0.5) * 0.1,
                   -(0.5 + torch.rand(B, 1, generator=g, dtype=torch.float64))], -1)
    T = pose_from_axis_angle(aa, t)
    pi, _ = project_points(X, K)
    pj, _ = project_points(transform_points(T, X), K)
    pj = pj + noise * torch.randn(pj.shape, generator=g, dtype=torch.float64)
    bad = torch.rand(B, N, generator=g) < outliers
    pj = torch.where(bad[..., None], pj + (torch.rand(B, N, 2, generator=g, dtype=torch.float64) - 0.5) * 60, pj)
    return pi, pj, K, T, X[..., 2]


def ours(pi, pj, K, z_true, cfg: TrackerConfig, threshold: float, refine: bool = True):
    B, N = pi.shape[:2]
    mask = torch.ones(B, N, dtype=torch.bool)
    gens = [torch.Generator().manual_seed(b) for b in range(B)]
    t0 = time.perf_counter()
    e = find_essential_ransac(pi, pj, mask, K, threshold_px=threshold, iterations=cfg.essential.iterations,
                              repeats=cfg.essential.repeats, generators=gens, refine=refine)
    t1 = time.perf_counter()
    R, t, front = decompose_essential(e.model, K, pi, pj, mask)
    t2 = time.perf_counter()
    ms = cfg.model_selection
    h = find_homography_ransac(pi, pj, mask, threshold_px=ms.h_threshold_px, iterations=ms.h_iterations,
                               generators=gens)
    g_e, g_h = gric_essential(e.model, K, pi, pj, mask), gric_homography(h.model, pi, pj, mask)
    t3 = time.perf_counter()
    z_tri, ok = triangulated_depth(R, t, K, pi, pj)
    s, _, _ = simple_scale(z_true, z_tri, mask & ok, generators=gens)
    t4 = time.perf_counter()
    times = {"essential_ransac": t1 - t0, "decompose_cheirality": t2 - t1, "homography_gric": t3 - t2,
             "scale": t4 - t3}
    return R, t, s, (g_e > g_h), {k: 1000 * v / B for k, v in times.items()}


def opencv(pi, pj, K, threshold: float):
    import cv2
    import numpy as np

    Rs, ts, total = [], [], 0.0
    for b in range(pi.shape[0]):
        a, c, k = pi[b].numpy(), pj[b].numpy(), K[b].numpy()
        t0 = time.perf_counter()
        E, m = cv2.findEssentialMat(a, c, k, method=cv2.RANSAC, prob=0.99, threshold=threshold)
        _, R, t, _ = cv2.recoverPose(E[:3], a, c, k, mask=m)
        total += time.perf_counter() - t0
        Rs.append(torch.from_numpy(R))
        ts.append(torch.from_numpy(np.ascontiguousarray(t[:, 0])))
    return torch.stack(Rs), torch.stack(ts), 1000 * total / pi.shape[0]


def summary(values: torch.Tensor) -> dict[str, float]:
    v = values.tolist()
    return {"mean": statistics.fmean(v), "median": statistics.median(v), "max": max(v)}


def odometry(frames: int, batch: int) -> dict:
    from dfvo.synthetic import SyntheticWorld

    w = SyntheticWorld(seed=0, num_frames=frames, scenario="straight")
    rendered = [w.render(i) for i in range(len(w) - 1)]
    ff = torch.stack([r["flow_fwd"] for r in rendered])
    fb = torch.stack([r["flow_bwd"] for r in rendered])
    d = torch.stack([r["depth"] for r in rendered])
    d_next = torch.stack([w.render(i + 1, right=False, flow=False)["depth"] for i in range(len(w) - 1)])
    out = {}
    for bs in (1, batch):
        vo = VisualOdometry(TrackerConfig())
        t0 = time.perf_counter()
        res = vo.run(ff, fb, d, w.intrinsics(), batch_size=bs, depths_next=d_next)
        ms = 1000 * (time.perf_counter() - t0) / len(res)
        P = w.poses()
        err = torch.stack([(r.T_prev_cur[:3, 3] - (torch.linalg.inv(P[k]) @ P[k + 1])[:3, 3]).norm()
                           for k, r in enumerate(res)])
        out[f"batch_{bs}"] = {"ms_per_frame": ms, "rpe_m_max": float(err.max()),
                              "trackers": sorted({r.diagnostics.tracker.value for r in res}),
                              "selection_ms_per_frame": 1000 * statistics.fmean(
                                  r.diagnostics.time_selection for r in res)}
    out["resolution"] = [w.height, w.width]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=16, help="frame pairs for the correspondence benchmark")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--points", type=int, default=2000)
    ap.add_argument("--noise", type=float, default=0.5, help="pixel noise std")
    ap.add_argument("--outliers", type=float, default=0.3)
    ap.add_argument("--threshold", type=float, default=1.0, help="RANSAC threshold in pixels for both pipelines")
    ap.add_argument("--threads", type=int, default=int(os.environ.get("OMP_NUM_THREADS", "1")),
                    help="torch threads (1 is fastest on the shared 2-core box)")
    ap.add_argument("--odometry-frames", type=int, default=17)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    cfg = TrackerConfig()
    pi, pj, K, T, z = make_frames(args.frames, args.points, args.noise, args.outliers)
    ours(pi[:2], pj[:2], K[:2], z[:2], cfg, args.threshold)  # warm-up
    without_lo = {"essential_ransac_ms_per_frame": 0.0}
    Rn, tn = [], []
    for s in range(0, args.frames, args.batch):
        sl = slice(s, s + args.batch)
        R, t, _, _, st = ours(pi[sl], pj[sl], K[sl], z[sl], cfg, args.threshold, refine=False)
        Rn.append(R), tn.append(t)
        without_lo["essential_ransac_ms_per_frame"] += st["essential_ransac"] * R.shape[0] / args.frames
    without_lo["rot_err_deg"] = summary(rotation_error_deg(torch.cat(Rn), T[:, :3, :3]))
    without_lo["trans_dir_err_deg"] = summary(direction_error_deg(torch.cat(tn), T[:, :3, 3]))
    Rs, ts, ss, pnp, stages = [], [], [], [], []
    t0 = time.perf_counter()
    for s in range(0, args.frames, args.batch):
        sl = slice(s, s + args.batch)
        R, t, sc, p, st = ours(pi[sl], pj[sl], K[sl], z[sl], cfg, args.threshold)
        Rs.append(R), ts.append(t), ss.append(sc), pnp.append(p), stages.append(st)
    ms = 1000 * (time.perf_counter() - t0) / args.frames
    R, t, sc = torch.cat(Rs), torch.cat(ts), torch.cat(ss)
    result = {
        "machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
                    "torch_threads": torch.get_num_threads(), "torch": torch.__version__},
        "setup": {"frames": args.frames, "batch": args.batch, "points": args.points, "noise_px": args.noise,
                  "outliers": args.outliers, "threshold_px": args.threshold, "ransac_repeats": cfg.essential.repeats,
                  "e_iterations_per_repeat": cfg.essential.iterations, "scale": "simple", "model_selection": "gric"},
        "dfvo": {"ms_per_frame": ms,
                 "stage_ms_per_frame": {k: statistics.fmean(st[k] for st in stages) for k in stages[0]},
                 "rot_err_deg": summary(rotation_error_deg(R, T[:, :3, :3])),
                 "trans_dir_err_deg": summary(direction_error_deg(t, T[:, :3, 3])),
                 "scale_rel_err": summary((sc / T[:, :3, 3].norm(dim=-1) - 1).abs()),
                 "gric_prefers_pnp": int(torch.cat(pnp).sum())},
        "dfvo_without_lo": without_lo,
    }
    try:
        Rc, tc, ms_cv = opencv(pi, pj, K, args.threshold)
        result["opencv"] = {"ms_per_frame": ms_cv, "rot_err_deg": summary(rotation_error_deg(Rc, T[:, :3, :3])),
                            "trans_dir_err_deg": summary(direction_error_deg(tc, T[:, :3, 3])),
                            "note": "findEssentialMat(RANSAC, prob 0.99) + recoverPose; no GRIC, no scale"}
    except ImportError:
        result["opencv"] = None
    if args.odometry_frames > 1:
        result["odometry_synthetic_oracle"] = odometry(args.odometry_frames, args.batch)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
