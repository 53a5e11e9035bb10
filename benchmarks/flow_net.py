"""Benchmark the flow network: forward+backward time per 640x192 pair, and AEPE / Out-1 on held-out synthetic
worlds for all visible pixels and for the correspondences forward-backward selection keeps (the paper's
"+ BestN" rows). Prints one JSON object.

    python benchmarks/flow_net.py                                  # timing of both variants, untrained eval
    python benchmarks/flow_net.py --checkpoint runs/flow_sup/last.ckpt --variant small --skip-timing

Metrics (all in pixels of the evaluation resolution):
    aepe: mean end-point error over the pixels with ground truth (visible in the next frame, as the paper's
        non-occluded KITTI evaluation); out1_pct: % of those pixels with error > 1 px.
    local_best_k / best_n: the same two numbers over the selected correspondences whose pixel is visible,
        plus n_selected (mean per pair), failed (pairs where selection fell back) and occluded_pct (% of
        selected pixels that are actually occluded: they have no true match).
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import torch

from dfvo.matching.consistency import forward_backward_inconsistency
from dfvo.matching.selection import select_correspondences
from dfvo.models.flow_net import FlowNet
from dfvo.synthetic import SyntheticWorld
from dfvo.training.flow_module import load_flow_weights


@torch.no_grad()
def time_forward_backward(net: FlowNet, height: int = 192, width: int = 640, repeats: int = 5) -> dict[str, float]:
    """Median wall time (ms) of ``net.forward_backward`` on one (1,3,H,W) pair after one warm-up call."""
    net.eval()
    a, b = torch.rand(1, 3, height, width), torch.rand(1, 3, height, width)
    net.forward_backward(a, b)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        net.forward_backward(a, b)
        times.append((time.perf_counter() - t0) * 1e3)
    times.sort()
    return {"median_ms": round(times[len(times) // 2], 1), "min_ms": round(times[0], 1)}


def render_pairs(seeds: list[int], num_frames: int, height: int, width: int, stride: int = 1) -> list[dict]:
    """Held-out pairs (image, image_next, flow_fwd, flow_fwd_valid), each tensor with a batch dim of 1."""
    pairs = []
    for seed in seeds:
        world = SyntheticWorld(seed=seed, num_frames=num_frames, height=height, width=width)
        for k in range(0, num_frames - 1, stride):
            s = world.render(k, right=False)
            pairs.append({"image": s["image"][None], "image_next": world.image(k + 1)[None],
                          "flow_fwd": s["flow_fwd"][None], "flow_fwd_valid": s["flow_fwd_valid"][None]})
    return pairs


@torch.no_grad()
def evaluate_pairs(net: FlowNet, pairs: list[dict], num: int = 2000) -> dict[str, dict[str, float]]:
    """AEPE / Out-1 over all visible pixels and over the fb-selected correspondences (see module docstring)."""
    net.eval()
    acc = {"all": [0.0, 0.0, 0, 0, 0, 0], "local_best_k": [0.0, 0.0, 0, 0, 0, 0], "best_n": [0.0, 0.0, 0, 0, 0, 0]}
    for p in pairs:
        fwd, bwd = net.forward_backward(p["image"], p["image_next"])
        gt, valid = p["flow_fwd"], p["flow_fwd_valid"]
        err = (fwd - gt).norm(dim=1, keepdim=True)
        e = err[valid]
        a = acc["all"]
        a[0] += e.sum().item()
        a[1] += (e > 1.0).sum().item()
        a[2] += e.numel()
        a[4] += 1
        incon = forward_backward_inconsistency(fwd, bwd)
        w = gt.shape[-1]
        for method in ("local_best_k", "best_n"):
            c = select_correspondences(fwd, incon, method=method, num=num)
            m = c.mask[0]
            pix = c.pts_i[0][m].round().long()
            idx = pix[:, 1] * w + pix[:, 0]
            gt_at = gt[0].flatten(1)[:, idx].T
            vis = valid[0, 0].flatten()[idx]
            e_sel = ((c.pts_j[0][m] - c.pts_i[0][m]) - gt_at).norm(dim=1)[vis]
            r = acc[method]
            r[0] += e_sel.sum().item()
            r[1] += (e_sel > 1.0).sum().item()
            r[2] += e_sel.numel()
            r[3] += int(m.sum().item() - vis.sum().item())
            r[4] += 1
            r[5] += int(c.failed[0].item())
    out = {}
    for key, (s, o, n, occ, pairs_n, failed) in acc.items():
        row = {"aepe": round(s / max(n, 1), 4), "out1_pct": round(100 * o / max(n, 1), 2)}
        if key != "all":
            row.update({"n_selected": round((n + occ) / max(pairs_n, 1), 1), "failed": failed,
                        "occluded_pct": round(100 * occ / max(n + occ, 1), 2)})
        out[key] = row
    out["all"]["pairs"] = len(pairs)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", default=None, help="FlowModule .ckpt or FlowNet .safetensors/.pt")
    parser.add_argument("--variant", default="small", help="variant of the checkpoint (default|small|tiny)")
    parser.add_argument("--seeds", default="100,101", help="held-out synthetic world seeds")
    parser.add_argument("--num-frames", type=int, default=40)
    parser.add_argument("--stride", type=int, default=2, help="evaluate every k-th pair")
    parser.add_argument("--height", type=int, default=96)
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--time-size", default="192x640",
                        help="HxW of the timed pair (96x320: the size inference runs the network at)")
    parser.add_argument("--skip-timing", action="store_true")
    parser.add_argument("--skip-eval", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    result: dict = {"machine": f"{platform.processor() or platform.machine()}, torch threads {args.threads}",
                    "torch": torch.__version__}
    if not args.skip_timing:
        th, tw = (int(v) for v in args.time_size.split("x"))
        key = f"forward_backward_{tw}x{th}"
        result[key] = {}
        for variant in ("default", "small", "tiny"):
            net = FlowNet(variant)
            params = sum(p.numel() for p in net.parameters())
            result[key][variant] = {**time_forward_backward(net, th, tw), "params": params}
    if not args.skip_eval:
        net = FlowNet(args.variant)
        if args.checkpoint:
            load_flow_weights(net, args.checkpoint)
        seeds = [int(s) for s in args.seeds.split(",")]
        pairs = render_pairs(seeds, args.num_frames, args.height, args.width, args.stride)
        result["eval"] = {"checkpoint": args.checkpoint, "variant": args.variant, "seeds": seeds,
                          "resolution": [args.height, args.width], **evaluate_pairs(net, pairs)}
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
