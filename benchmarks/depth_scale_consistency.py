"""How consistent is a depth network's metric scale from frame to frame on KITTI? (What DF-VO's scale recovery sees.)

DF-VO takes each frame's translation scale from the ratio of CNN depth to triangulated depth at the selected
correspondences, so the frame-to-frame spread of that ratio is the spread of the translation lengths, whatever the
flow. Here the triangulation uses the TRUE relative pose of every pair (KITTI ground truth), so the ratio
``z_cnn / z_true`` isolates the depth network: per frame its median over the correspondences the tracker would use
(shipped flow network + photometric refinement + local best-K at 0.1 px, rows below the top 30 %, CNN depth in
(0, 50] m), then over frames the mean (metric bias) and standard deviation (per-frame scale noise; a 10 % spread is
~0.12 m of RPE at KITTI speed); ``gross_error_fraction``: per frame the share of those points whose CNN depth is
off by more than a factor 2, averaged over frames (what makes the tracker's 1-D RANSAC lock onto a wrong scale;
low-parallax points add triangulation noise to it). ``parallax_3px`` repeats the statistics on the points with
more than 3 px of flow (their triangulation is well conditioned, so the ratio there is the network's alone),
with the mean ratio per true-depth band.

    python benchmarks/depth_scale_consistency.py --depth checkpoints/depth.safetensors

prints one JSON object. ``--depth`` takes a .safetensors / .pt DepthNet or a depth training ``.ckpt``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dfvo.data.kitti_odometry import KittiOdometry  # noqa: E402
from dfvo.matching.consistency import forward_backward_inconsistency  # noqa: E402
from dfvo.matching.flow_refinement import FlowRefinementConfig, refine_forward_backward  # noqa: E402
from dfvo.matching.selection import select_correspondences  # noqa: E402
from dfvo.sources.networks import NetworkDepth, NetworkFlow  # noqa: E402
from dfvo.tracking.scale import sample_depth, triangulated_depth  # noqa: E402

BANDS = ((0.0, 8.0), (8.0, 15.0), (15.0, 25.0), (25.0, 50.0))


def main() -> None:
    repo = Path(__file__).resolve().parents[1]
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--depth", default=str(repo / "dfvo/checkpoints/depth.safetensors"))
    p.add_argument("--depth-input-size", default=None, help="H,W the depth network runs at (default: metadata)")
    p.add_argument("--flip-average", action="store_true", help="depth.flip_average: blend with the mirrored image")
    p.add_argument("--flow", default=str(repo / "dfvo/checkpoints/flow.safetensors"))
    p.add_argument("--root", default=str(repo.parent / "shared/data/kitti_odom"))
    p.add_argument("--seq", default="06")
    p.add_argument("--height", type=int, default=192)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    size = None if args.depth_input_size is None else [int(v) for v in args.depth_input_size.split(",")]
    depth_src = NetworkDepth(args.depth, input_size=size, flip_average=args.flip_average)
    flow_src = NetworkFlow(args.flow)
    ds = KittiOdometry(args.root, args.seq, height=args.height, width=args.width, stereo=False)
    if ds.poses is None:
        raise SystemExit(f"{args.root}/poses/{args.seq}.txt is needed (true poses)")
    K = ds.intrinsics[None].double()
    per_frame, per_frame_all, gross, bands = [], [], [], {b: [] for b in BANDS}
    pairs = list(range(len(ds) - 1))
    for start in range(0, len(pairs), 4):
        ks = pairs[start:start + 4]
        prev = torch.stack([ds[k]["image"] for k in ks])
        cur = torch.stack([ds[k + 1]["image"] for k in ks])
        fwd, bwd = refine_forward_backward(prev, cur, *flow_src(prev, cur), FlowRefinementConfig())
        sel = select_correspondences(fwd, forward_backward_inconsistency(fwd, bwd))
        depth = depth_src(prev)
        for b, k in enumerate(ks):
            if bool(sel.failed[b]):
                continue
            T_j_i = np.linalg.inv(ds.poses[k + 1]) @ ds.poses[k]
            length = float(np.linalg.norm(T_j_i[:3, 3]))
            if length < 0.1:
                continue
            R = torch.from_numpy(T_j_i[:3, :3])[None]
            t = torch.from_numpy(T_j_i[:3, 3] / length)[None]
            pi, pj = sel.pts_i[b:b + 1], sel.pts_j[b:b + 1]
            z_cnn, ok = sample_depth(depth[b:b + 1], pi)
            z_tri, front = triangulated_depth(R, t, K, pi, pj)
            used = ok & front & sel.mask[b:b + 1]
            if int(used.sum()) >= 20:
                ratio_all = z_cnn[used] / (z_tri[used] * length)
                per_frame_all.append(float(ratio_all.median()))
                gross.append(float(((ratio_all > 2.0) | (ratio_all < 0.5)).double().mean()))
            m = used & ((pj - pi).norm(dim=-1) > 3.0)
            if int(m.sum()) < 20:
                continue
            z_true = z_tri[m] * length
            ratio = z_cnn[m] / z_true
            per_frame.append(float(ratio.median()))
            for lo, hi in BANDS:
                band = (z_true >= lo) & (z_true < hi)
                if int(band.sum()) >= 20:
                    bands[(lo, hi)].append(float(ratio[band].median()))
    r, r_all = np.array(per_frame), np.array(per_frame_all)
    print(json.dumps({
        "depth": args.depth, "flip_average": args.flip_average, "flow": args.flow, "sequence": args.seq,
        "resolution": [args.height, args.width],
        "depth_network_input": list(depth_src.input_size) if depth_src.input_size else None,
        "frames": len(r_all), "cnn_over_true_mean": round(float(r_all.mean()), 4),
        "cnn_over_true_per_frame_std": round(float(r_all.std()), 4),
        "gross_error_fraction": round(float(np.mean(gross)), 4),
        "parallax_3px": {
            "frames": len(r), "cnn_over_true_mean": round(float(r.mean()), 4),
            "cnn_over_true_per_frame_std": round(float(r.std()), 4),
            "per_depth_band": {f"{lo:g}-{hi:g} m": {"frames": len(v),
                                                     "mean": round(float(np.mean(v)), 3) if v else None,
                                                     "std": round(float(np.std(v)), 3) if v else None}
                               for (lo, hi), v in bands.items()}},
    }))


if __name__ == "__main__":
    main()
