"""End-to-end inference speed: frames per second of infer.py's loop and where the time goes.

Runs :func:`dfvo.inference.pipeline.run_inference` in-process (the same code as ``python infer.py``) and prints
one JSON object: resolution, sources, frames, ``fps`` (frame pairs per wall second, everything included),
``fps_without_loading`` (excluding frame reading / synthetic rendering, which is what a camera stream pays),
``timing_ms_per_frame`` per stage (load, flow, depth, tracker and any stage the tracker reports), the RPE/ATE
of the run, torch threads, machine and load average.

Sources:
    --sources oracle          true flow/depth of the synthetic world (their time is the renderer's)
    --sources network         checkpoints given by --flow-ckpt / --depth-ckpt
    --sources random-network  FlowNet/DepthNet with random weights (speed only: the poses are meaningless)

Usage: python benchmarks/infer_fps.py [--frames 20] [--height 192] [--width 640] [--threads 2]
       [--sources oracle|network|random-network] [--data synthetic|kitti_odom --root ROOT --seq 06]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

from dfvo.inference.pipeline import run_inference

REPO = Path(__file__).resolve().parents[1]


def _random_checkpoints(folder: Path, variant: str) -> tuple[Path, Path]:
    from safetensors.torch import save_file

    from dfvo.models.depth_net import DepthNet
    from dfvo.models.flow_net import FlowNet

    flow, depth = folder / "flow.safetensors", folder / "depth.safetensors"
    save_file({k: v.contiguous() for k, v in FlowNet(variant).state_dict().items()}, str(flow),
              metadata={"variant": variant})
    save_file({k: v.contiguous() for k, v in DepthNet().state_dict().items()}, str(depth))
    return flow, depth


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=20)
    p.add_argument("--height", type=int, default=192)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--batch-size", type=int, default=4)
    p.add_argument("--sources", choices=["oracle", "network", "random-network"], default="oracle")
    p.add_argument("--flow-ckpt", default="checkpoints/flow.safetensors")
    p.add_argument("--depth-ckpt", default="checkpoints/depth.safetensors")
    p.add_argument("--flow-variant", default="default")
    p.add_argument("--depth-scale", type=float, default=1.0)
    p.add_argument("--data", default="synthetic")
    p.add_argument("--root", default=None)
    p.add_argument("--seq", default=None)
    p.add_argument("--overrides", nargs="*", default=[], help="extra infer.yaml overrides (tracker=pnp ...)")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        ov = [f"data={args.data}", f"img_res.height={args.height}", f"img_res.width={args.width}",
              f"out_dir={tmp / 'out'}", "progress=false", f"batch_size={args.batch_size}",
              f"num_threads={args.threads}"]
        if args.data == "synthetic":
            ov.append(f"data.num_frames={args.frames}")
        else:
            ov += [f"data.root={args.root}", f"data.end={args.frames}"]
        if args.seq is not None:
            ov.append(f"seq={args.seq}")
        if args.sources == "oracle":  # explicit: the default `auto` would pick the shipped checkpoints
            ov += ["flow=oracle", "depth=oracle"]
        else:
            flow, depth = ((args.flow_ckpt, args.depth_ckpt) if args.sources == "network"
                           else _random_checkpoints(tmp, args.flow_variant))
            ov += ["flow=network", "depth=network", f"flow.checkpoint={flow}", f"depth.checkpoint={depth}",
                   f"depth.depth_scale={args.depth_scale}"]
        with initialize_config_dir(config_dir=str(REPO / "dfvo" / "conf" / "infer"), version_base="1.3"):
            cfg = compose("infer", overrides=ov + list(args.overrides))
        summary = run_inference(cfg)
    timing = summary["timing_ms_per_frame"]
    per_frame_ms = 1000.0 / summary["fps"]
    metrics = summary.get("metrics") or {}
    print(json.dumps({
        "data": args.data, "sources": args.sources, "resolution": [args.height, args.width],
        "frames": summary["frames"], "fps": round(summary["fps"], 3),
        "fps_without_loading": round(1000.0 / max(per_frame_ms - timing.get("load", 0.0), 1e-9), 3),
        "timing_ms_per_frame": {k: round(v, 2) for k, v in timing.items()},
        "rpe_m": metrics.get("rpe_m"), "rpe_deg": metrics.get("rpe_deg"), "ate_m": metrics.get("ate_m"),
        "fallback": summary["fallback"], "torch_threads": torch.get_num_threads(),
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "load_avg": os.getloadavg()[0],
    }, indent=2))


if __name__ == "__main__":
    main()
