"""Flow refinement schedules on KITTI 06: CPU time per pair against the accuracy of what the selection keeps.

For each schedule ``COARSE:FULL[:METHOD]`` (``flow.refine.coarse_iterations``, ``flow.refine.iterations``,
``flow.refine.method``) the shipped flow network's forward and backward flows of KITTI 06 pairs 0..N-1 (640x192,
computed once) are refined in batches of 4 consecutive pairs (as ``infer.py`` does), the default correspondence
selection runs on them, and the Sampson (epipolar) distance of each selected correspondence under the *true* relative
pose is measured. Prints one JSON line per schedule: median / mean / p90 of that distance in pixels, frames whose
selection failed, the median number of pixels passing the 0.1 px forward-backward test, and the CPU milliseconds of
the refinement per pair (``time.process_time``: the machine may be shared; CPU time follows the work, not the
neighbours). ``--sparse`` adds the cost of one refinement iteration over N per-candidate 11x11 windows against one
dense iteration over both flows of a pair (the case for and against refining only the selection's candidates).

Usage (``docs/speed.md``):
    OMP_NUM_THREADS=1 python benchmarks/refine_schedules.py --root ../shared/data/kitti_odom 3:2 3:1 2:1 0:5:symmetric
    OMP_NUM_THREADS=1 python benchmarks/refine_schedules.py --root ../shared/data/kitti_odom --sparse
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch
import torch.nn.functional as F

from dfvo.data.kitti_odometry import KittiOdometry
from dfvo.eval.epipolar import fundamental_from_pose
from dfvo.geometry.two_view import sampson_sq
from dfvo.matching import flow_refinement as fr
from dfvo.matching.consistency import forward_backward_inconsistency
from dfvo.matching.selection import select_correspondences
from dfvo.sources import find_checkpoint
from dfvo.sources.networks import NetworkFlow


def _schedule(spec: str) -> fr.FlowRefinementConfig:
    parts = spec.split(":")
    if len(parts) not in (2, 3):
        raise SystemExit(f"schedule {spec!r}: expected COARSE:FULL or COARSE:FULL:METHOD")
    extra = {"method": parts[2]} if len(parts) == 3 else {}
    return fr.FlowRefinementConfig(coarse_iterations=int(parts[0]), iterations=int(parts[1]), **extra)


def _evaluate(spec: str, imgs: torch.Tensor, fwd: torch.Tensor, bwd: torch.Tensor, poses: np.ndarray,
              K: np.ndarray) -> dict:
    cfg = _schedule(spec)
    n = fwd.shape[0]
    errors, valid, failed, cpu = [], [], 0, 0.0
    for first in range(0, n, 4):
        ks = list(range(first, min(first + 4, n)))
        start = time.process_time()
        f, b = fr.refine_consecutive(imgs[first:first + len(ks) + 1], fwd[ks], bwd[ks], cfg)
        cpu += time.process_time() - start
        inconsistency = forward_backward_inconsistency(f, b)
        sel = select_correspondences(f, inconsistency)
        for j, k in enumerate(ks):
            valid.append(int((inconsistency[j] < 0.1).sum()))
            if sel.failed[j]:
                failed += 1
                continue
            Fm = torch.from_numpy(fundamental_from_pose(np.linalg.inv(poses[k]) @ poses[k + 1], K))[None, None]
            m = sel.mask[j]
            errors.append(sampson_sq(Fm, sel.pts_i[j][m].double()[None], sel.pts_j[j][m].double()[None])[0, 0].sqrt())
    e = torch.cat(errors) if errors else torch.full((1,), float("nan"))
    return {"schedule": spec, "selected_epipolar_px": {"median": round(float(e.median()), 4),
                                                       "mean": round(float(e.mean()), 4),
                                                       "p90": round(float(e.quantile(0.9)), 4)},
            "selection_failed": failed, "fb_valid_pixels_median": int(np.median(valid)),
            "refine_cpu_ms_per_pair": round(1000.0 * cpu / n, 1)}


def _sparse_cost(imgs: torch.Tensor, fwd: torch.Tensor, bwd: torch.Tensor, repeats: int = 7) -> dict:
    """CPU ms of one inverse-compositional iteration: dense over both flows of a pair vs N per-candidate windows."""
    H, W = imgs.shape[-2:]
    cfg = fr.FlowRefinementConfig(iterations=1, coarse_iterations=0)
    t = fr._templates(fr._grey(imgs[:2]), cfg)
    flow = torch.cat([fwd[:1], bwd[:1]])
    finite = torch.ones_like(flow[:, :1], dtype=torch.bool)
    pair = torch.tensor([0, 1]), torch.tensor([1, 0])
    grid = torch.meshgrid(torch.arange(-5, 6.0), torch.arange(-5, 6.0), indexing="xy")
    offsets = torch.stack(grid, -1).view(1, 121, 2)
    scale = torch.tensor([2 / (W - 1), 2 / (H - 1)])

    def sparse(n: int):
        g = torch.Generator().manual_seed(0)
        pts = torch.stack([torch.randint(5, W - 6, (n,), generator=g),
                           torch.randint(5, H - 6, (n,), generator=g)], -1).float()
        idx = ((pts[:, None, 1] + offsets[..., 1]) * W + pts[:, None, 0] + offsets[..., 0]).long()  # (n,121)
        template, grad = t.grey[0, 0].flatten()[idx], t.grad[0].flatten(1)[:, idx].permute(1, 2, 0)
        a_inv, u = torch.rand(n, 2, 2), torch.zeros(n, 2)

        def iteration() -> torch.Tensor:
            pos = (pts[:, None] + offsets + u[:, None]) * scale - 1
            warped = F.grid_sample(t.grey[1:2], pos[None], align_corners=True, padding_mode="border")[0, 0]
            b = torch.bmm((warped - template)[:, None], grad)[:, 0]
            return u - torch.bmm(a_inv, b[..., None])[..., 0]

        return iteration

    fns = {"dense_pair": lambda: fr._refine_ic(t, *pair, flow, finite, cfg),
           **{f"windows_{n}": sparse(n) for n in (2000, 5000, 10000, 20000)}}
    best = dict.fromkeys(fns, float("inf"))
    for _ in range(repeats):
        for name, fn in fns.items():
            start = time.process_time()
            fn()
            best[name] = min(best[name], time.process_time() - start)
    return {"one_iteration_cpu_ms": {k: round(1000.0 * v, 2) for k, v in best.items()}}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("schedules", nargs="*", default=["3:2", "3:1", "0:5:symmetric"])
    p.add_argument("--root", default="../shared/data/kitti_odom")
    p.add_argument("--seq", default="06")
    p.add_argument("--pairs", type=int, default=50)
    p.add_argument("--checkpoint", default="checkpoints/flow.safetensors")
    p.add_argument("--sparse", action="store_true", help="also the per-candidate vs dense iteration cost")
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    ds = KittiOdometry(args.root, args.seq, height=192, width=640, stereo=False)
    imgs = torch.stack([ds[k]["image"] for k in range(args.pairs + 1)])
    src = NetworkFlow(find_checkpoint(args.checkpoint, "--checkpoint"))
    fwd, bwd = [], []
    for first in range(0, args.pairs, 4):
        ks = list(range(first, min(first + 4, args.pairs)))
        f, b = src(imgs[ks], imgs[[k + 1 for k in ks]])
        fwd.append(f)
        bwd.append(b)
    fwd, bwd = torch.cat(fwd), torch.cat(bwd)
    K = ds.intrinsics.double().numpy()
    for spec in args.schedules:
        print(json.dumps(_evaluate(spec, imgs, fwd, bwd, ds.poses, K)), flush=True)
    if args.sparse:
        print(json.dumps(_sparse_cost(imgs, fwd, bwd)), flush=True)


if __name__ == "__main__":
    main()
