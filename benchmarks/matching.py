"""Benchmark of flow consistency, correspondence selection and PnP (prints JSON).

Usage: ``OMP_NUM_THREADS=1 python benchmarks/matching.py [--threads 1] [--repeats 5]``

Measures, at 640x192: forward-backward inconsistency and selection time per frame for B=1 and B=8
(every method), and PnP time per frame with 2000 correspondences, 100 iterations x 5 repeats, for B=1
and B=8, with its rotation/translation errors next to OpenCV's solvePnPRansac + solvePnPRefineLM (when
OpenCV is installed) on the same inputs (sigma = 0.5 px pixel noise, 30% outliers).
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import torch

from dfvo.geometry.pnp import solve_pnp_ransac
from dfvo.geometry.se3 import pose_from_axis_angle, rotation_error_deg
from dfvo.matching.consistency import forward_backward_inconsistency
from dfvo.matching.selection import select_correspondences

H, W = 192, 640


def _time(fn, repeats: int) -> float:
    fn()  # warm-up
    start = time.perf_counter()
    for _ in range(repeats):
        fn()
    return (time.perf_counter() - start) / repeats


def _smooth_flows(B: int, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """A forward flow from a small affine motion plus a little noise, and its approximate inverse."""
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    s = 1.0 + 0.02 * torch.rand(B, 1, 1, generator=g)
    fwd = torch.stack([(s - 1) * (u - W / 2) + 1.5, (s - 1) * (v - H / 2)], 1)
    bwd = -fwd / s.unsqueeze(1) + 0.05 * torch.randn(B, 2, H, W, generator=g)
    return fwd, bwd


def _pnp_problem(B: int, N: int, g: torch.Generator):
    K = torch.tensor([[718.856, 0.0, 319.5], [0.0, 718.856, 95.5], [0.0, 0.0, 1.0]], dtype=torch.float64)
    K = K.expand(B, 3, 3).clone()
    u = torch.rand(B, N, generator=g, dtype=torch.float64) * (W - 1)
    v = torch.rand(B, N, generator=g, dtype=torch.float64) * (H - 1)
    z = 3.0 + torch.rand(B, N, generator=g, dtype=torch.float64) * 45.0
    X = torch.stack([(u - 319.5) / 718.856 * z, (v - 95.5) / 718.856 * z, z], -1)
    T = pose_from_axis_angle(torch.randn(B, 3, generator=g, dtype=torch.float64) * 0.03,
                             torch.randn(B, 3, generator=g, dtype=torch.float64) * 0.1
                             + torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64))
    p = (X @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3]) @ K.transpose(1, 2)
    px = p[..., :2] / p[..., 2:3] + 0.5 * torch.randn(B, N, 2, generator=g, dtype=torch.float64)
    out = torch.rand(B, N, generator=g, dtype=torch.float64) < 0.3
    px = torch.where(out[..., None], px + (torch.rand(B, N, 2, generator=g, dtype=torch.float64) - 0.5) * 80, px)
    return X, px, K, T


def _errors(T_est: torch.Tensor, T: torch.Tensor) -> dict:
    rot = rotation_error_deg(T_est[:, :3, :3].double(), T[:, :3, :3])
    trans = (T_est[:, :3, 3].double() - T[:, :3, 3]).norm(dim=-1)
    return {"rot_err_deg_mean": rot.mean().item(), "trans_err_m_mean": trans.mean().item()}


def _opencv(X, px, K, T) -> dict | None:
    try:
        import cv2
    except ImportError:
        return None
    import numpy as np

    poses, start = [], time.perf_counter()
    for b in range(X.shape[0]):
        Xb, pb, Kb = X[b].numpy(), px[b].numpy(), K[b].numpy()
        ok, rvec, tvec, inl = cv2.solvePnPRansac(Xb, pb, Kb, None, iterationsCount=500, reprojectionError=1.0,
                                                 confidence=0.999, flags=cv2.SOLVEPNP_EPNP)
        if ok and inl is not None:
            rvec, tvec = cv2.solvePnPRefineLM(Xb[inl[:, 0]], pb[inl[:, 0]], Kb, None, rvec, tvec)
        Tb = np.eye(4)
        Tb[:3, :3], Tb[:3, 3] = cv2.Rodrigues(rvec)[0], tvec[:, 0]
        poses.append(torch.from_numpy(Tb))
    ms = (time.perf_counter() - start) / X.shape[0] * 1000
    return {"ms_per_frame": ms, **_errors(torch.stack(poses), T)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    g = torch.Generator().manual_seed(0)
    out: dict = {"machine": f"{platform.machine()} {platform.processor() or ''}".strip(),
                 "torch_threads": args.threads, "resolution": [W, H], "selection": {}, "consistency": {}, "pnp": {}}
    for B in (1, 8):
        fwd, bwd = _smooth_flows(B, g)
        out["consistency"][f"B{B}_ms_per_frame"] = _time(lambda f=fwd, b=bwd: forward_backward_inconsistency(f, b),
                                                         args.repeats) / B * 1000
        incon = forward_backward_inconsistency(fwd, bwd)
        for method in ("local_best_k", "best_n", "uniform"):
            sec = _time(lambda m=method, f=fwd, c=incon: select_correspondences(f, c, method=m, num=2000), args.repeats)
            out["selection"][f"{method}_B{B}_ms_per_frame"] = sec / B * 1000
    for B in (1, 8):
        X, px, K, T = _pnp_problem(B, 2000, g)
        Xf, pf, Kf = X.float(), px.float(), K.float()
        mask = torch.ones(B, 2000, dtype=torch.bool)
        result = {}

        def run(Xf=Xf, pf=pf, mask=mask, Kf=Kf, result=result):
            result["r"] = solve_pnp_ransac(Xf, pf, mask, Kf, threshold_px=1.0, iterations=100, repeats=5,
                                           generators=[torch.Generator().manual_seed(1 + b) for b in range(len(Xf))])

        sec = _time(run, max(1, args.repeats // 2))
        entry = {"ms_per_frame": sec / B * 1000, **_errors(result["r"].T_cur_prev, T),
                 "success": int(result["r"].success.sum())}
        if B == 8:
            entry["opencv"] = _opencv(X, px, K, T)
        out["pnp"][f"B{B}_N2000_100x5"] = entry
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
