"""How good is a flow checkpoint on real KITTI frames, where there is no true flow? Measured against the true poses.

For every frame pair (k, k + ``--step``) of a KITTI odometry snippet the true relative pose gives the fundamental matrix
``F = K^-T [t]x R K^-1``; a correct flow puts every pixel of frame i on its epipolar line in frame j, so the
Sampson distance of (x, x + flow(x)) to F is a lower bound of the flow's error (it misses errors along the line).
Reported (pixels of the working resolution, 640x192 by default), over all pixels of all pairs, and over the
correspondences the tracker would use (local best-K with the official 0.1 px forward-backward threshold):

    - ``epipolar_px``: median and 90th percentile of the Sampson distance, fraction of pixels under 1 px;
    - ``fb_px``: forward-backward inconsistency percentiles, fraction of pixels under 0.1 px and under 1 px;
    - ``epipolar_by_fb_px``: per band of forward-backward inconsistency (px), its share of the pixels and their median
      Sampson distance: how well the consistency the selection ranks by tells the flow's error;
    - ``selection``: pairs where local best-K fails (→ constant motion), median epipolar error of the selected;
    - ``selected_by_texture``: the selected correspondences per band of their Shi–Tomasi score in frame k (the
      smaller eigenvalue of the refinement's 11x11 structure tensor, :func:`dfvo.matching.image_ops.shi_tomasi`):
      share and median Sampson distance. ``--min-texture T`` selects only among pixels scoring at least T
      (``tracker.correspondence.min_texture``).

Pairs with almost no translation (< 0.1 m) are skipped: F is undefined there. ``--refine-iterations N`` applies the
pipeline's photometric refinement (``flow.refine``, N Gauss-Newton iterations; 0 = the network's flow as it is) to
the forward and backward flows before everything is measured. ``--source dis`` measures OpenCV's DIS flow (the
classical baseline of ``flow=dis``, preset ``--preset``) the same way. Examples:

    python studies/kitti_flow_quality.py --checkpoint checkpoints/flow.safetensors --refine-iterations 0
    python studies/kitti_flow_quality.py --source dis --refine-iterations 0

prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from dfvo.data.kitti_odometry import KittiOdometry
from dfvo.eval.epipolar import fundamental_from_pose
from dfvo.geometry.two_view import sampson_sq
from dfvo.matching.consistency import forward_backward_inconsistency
from dfvo.matching.flow_refinement import FlowRefinementConfig, refine_forward_backward
from dfvo.matching.image_ops import shi_tomasi
from dfvo.matching.selection import select_correspondences
from dfvo.sources import find_checkpoint
from dfvo.sources.dis import DISFlow
from dfvo.sources.networks import NetworkFlow

FB_BANDS = ((0.0, 0.025), (0.025, 0.05), (0.05, 0.1), (0.1, 0.5), (0.5, 1.0))  # px, for epipolar_by_fb_px
TEXTURE_BANDS = (0.0, 1e-5, 3e-5, 1e-4, 2e-4, 4e-4, 1e-3, float("inf"))  # Shi-Tomasi edges, selected_by_texture


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--source", choices=("network", "dis"), default="network", help="flow source (default network)")
    p.add_argument("--checkpoint", default="checkpoints/flow.safetensors",
                   help="--source network: flow checkpoint (.safetensors, or .ckpt / .pt state dict)")
    p.add_argument("--preset", default="medium", help="--source dis: ultrafast | fast | medium")
    p.add_argument("--variant", default=None, help="FlowNet variant (default: from the checkpoint)")
    p.add_argument("--input-size", default=None, help="H,W the network runs at (default: checkpoint metadata)")
    p.add_argument("--root", default=str(Path(__file__).resolve().parents[2] / "shared/data/kitti_odom"))
    p.add_argument("--seq", default="06")
    p.add_argument("--step", type=int, default=1, help="pairs (k, k + step), as infer.py's data.step (default 1)")
    p.add_argument("--height", type=int, default=192)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--refine-iterations", type=int, default=5, help="photometric refinement iterations (0: none)")
    p.add_argument("--min-texture", type=float, default=0.0,
                   help="select only pixels whose Shi-Tomasi score is at least this (0: all, the default)")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    size = None if args.input_size is None else [int(v) for v in args.input_size.split(",")]
    if args.source == "dis":
        src = DISFlow(args.preset)
    else:
        src = NetworkFlow(find_checkpoint(args.checkpoint), args.variant, input_size=size)
    ds = KittiOdometry(args.root, args.seq, height=args.height, width=args.width, stereo=False)
    K = ds.intrinsics.double().numpy()
    H, W = args.height, args.width
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64),
                            indexing="ij")
    grid = torch.stack([xs, ys], -1).view(1, -1, 2)
    epi, fb, sel_epi, epi_by_fb, sel_texture = [], [], [], [], []
    failed = skipped = 0
    t_flow = t_refine = 0.0
    if args.step < 1:
        raise SystemExit(f"--step {args.step}: expected a positive frame gap")
    pairs = [k for k in range(len(ds) - args.step)]
    for start in range(0, len(pairs), args.batch):
        ks = pairs[start:start + args.batch]
        prev = torch.stack([ds[k]["image"] for k in ks])
        cur = torch.stack([ds[k + args.step]["image"] for k in ks])
        t0 = time.perf_counter()
        fwd, bwd = src(prev, cur)
        t_flow += time.perf_counter() - t0
        t0 = time.perf_counter()
        if args.refine_iterations > 0:
            fwd, bwd = refine_forward_backward(prev, cur, fwd, bwd,
                                               FlowRefinementConfig(iterations=args.refine_iterations))
        t_refine += time.perf_counter() - t0
        incon = forward_backward_inconsistency(fwd, bwd)
        texture = shi_tomasi(prev, 11, 1.0)
        sel = select_correspondences(fwd, incon.masked_fill(texture < args.min_texture, float("inf")))
        for b, k in enumerate(ks):
            T_prev_cur = np.linalg.inv(ds.poses[k]) @ ds.poses[k + args.step]
            if np.linalg.norm(T_prev_cur[:3, 3]) < 0.1:
                skipped += 1
                continue
            F = torch.from_numpy(fundamental_from_pose(T_prev_cur, K))[None, None]
            x_j = grid + fwd[b].permute(1, 2, 0).reshape(1, -1, 2).double()
            d = sampson_sq(F, grid, x_j)[0, 0].sqrt()
            ok = torch.isfinite(d)
            epi.append(d[ok].float())
            inc = incon[b].flatten()
            inc_ok = torch.isfinite(inc)
            fb.append(inc[inc_ok])
            epi_by_fb.append(torch.stack([inc.double(), d]).T[ok & inc_ok])
            if bool(sel.failed[b]):
                failed += 1
                continue
            m = sel.mask[b]
            xi, xj = sel.pts_i[b][m].double()[None], sel.pts_j[b][m].double()[None]
            sel_epi.append(sampson_sq(F, xi, xj)[0, 0].sqrt().float())
            u, v = sel.pts_i[b][m].long().unbind(-1)
            sel_texture.append(texture[b, 0, v, u])
    epi_all, fb_all = torch.cat(epi), torch.cat(fb)
    sel_all = torch.cat(sel_epi) if sel_epi else torch.zeros(0)
    pairs_fb_epi = torch.cat(epi_by_fb).float()
    sel_tex = torch.cat(sel_texture) if sel_texture else torch.zeros(0)

    def q(x: torch.Tensor, v: float) -> float | None:
        return round(float(torch.quantile(x[torch.randperm(len(x))[:1_000_000]], v)), 3) if len(x) else None

    print(json.dumps({
        "source": args.source if args.source == "network" else f"dis ({args.preset})",
        "checkpoint": args.checkpoint if args.source == "network" else None,
        "variant": getattr(src, "variant", None), "network_input": getattr(src, "input_size", None),
        "sequence": args.seq, "step": args.step, "pairs": len(pairs) - skipped, "skipped_static": skipped,
        "resolution": [H, W],
        "epipolar_px": {"median": q(epi_all, 0.5), "p90": q(epi_all, 0.9),
                        "under_1px": round(float((epi_all < 1).float().mean()), 3)},
        "fb_px": {"median": q(fb_all, 0.5), "p10": q(fb_all, 0.1),
                  "under_0.1px": round(float((fb_all < 0.1).float().mean()), 4),
                  "under_1px": round(float((fb_all < 1).float().mean()), 3)},
        "epipolar_by_fb_px": {f"{lo}-{hi}": {"share": round(float(m.float().mean()), 4),
                                             "median": q(pairs_fb_epi[m, 1], 0.5)}
                              for lo, hi in FB_BANDS
                              for m in [(pairs_fb_epi[:, 0] >= lo) & (pairs_fb_epi[:, 0] < hi)]},
        "selection": {"failed_pairs": failed, "median_epipolar_px": q(sel_all, 0.5),
                      "mean_epipolar_px": round(float(sel_all.mean()), 4) if len(sel_all) else None,
                      "selected": len(sel_all), "min_texture": args.min_texture},
        "selected_by_texture": {f"{lo:g}-{hi:g}": {"share": round(float(m.float().mean()), 4) if len(m) else None,
                                                   "median": q(sel_all[m], 0.5)}
                                for lo, hi in zip(TEXTURE_BANDS[:-1], TEXTURE_BANDS[1:])
                                for m in [(sel_tex >= lo) & (sel_tex < hi)]},
        "refine_iterations": args.refine_iterations,
        "flow_seconds_per_pair": round(t_flow / len(pairs), 4),
        "refine_seconds_per_pair": round(t_refine / len(pairs), 4),
    }))


if __name__ == "__main__":
    main()
