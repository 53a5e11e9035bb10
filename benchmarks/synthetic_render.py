"""Speed of the synthetic world: seconds per frame with all outputs (left, right, depth, fwd/bwd flow, masks).

Prints one JSON object:
    sequential: frames rendered in order (what datasets and infer.py do; the next frame's cast is reused),
    cold: each frame rendered with empty caches (random access), both with mean/median/min wall seconds
    and the mean process CPU seconds (all threads; a contention-free lower bound on the work when the
    2-core machine is shared); plus resolution, number of frames, torch threads, the machine and its load.

Usage: python benchmarks/synthetic_render.py [--frames 20] [--height 192] [--width 640] [--threads 2]
       [--png docs/images/synthetic_frame.png --png-frame 22]   (also save a 2x2 preview: left, right,
       depth (inverse, magma), forward flow (hue = direction, saturation = magnitude, black = invalid))
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time

import torch

from dfvo.data.synthetic import SyntheticWorld


def _cpu_name() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def _stats(times: list[float], cpu: list[float]) -> dict[str, float]:
    return {"mean_s": round(statistics.mean(times), 4), "median_s": round(statistics.median(times), 4),
            "min_s": round(min(times), 4), "cpu_mean_s": round(statistics.mean(cpu), 4)}


def save_preview(world: SyntheticWorld, index: int, path: str) -> None:
    """Write a 2x2 PNG: left | right image, depth | colour-coded forward flow."""
    import matplotlib
    import numpy as np
    from PIL import Image

    s = world.render(index)
    left = s["image"].permute(1, 2, 0).numpy()
    right = s["image_right"].permute(1, 2, 0).numpy()
    inv = (1.0 / s["depth"][0]).numpy()
    depth = matplotlib.colormaps["magma"](np.clip(inv / np.percentile(inv, 99), 0, 1))[..., :3]
    f = s["flow_fwd"].numpy()
    mag = np.hypot(f[0], f[1])
    hsv = np.stack([(np.arctan2(-f[1], -f[0]) / np.pi + 1) / 2, np.clip(mag / np.percentile(mag, 99), 0, 1),
                    np.ones_like(mag)], -1)
    flow = matplotlib.colors.hsv_to_rgb(hsv) * s["flow_fwd_valid"][0].numpy()[..., None]
    grid = np.concatenate([np.concatenate([left, right], 1), np.concatenate([depth, flow], 1)], 0)
    Image.fromarray((grid * 255).round().astype(np.uint8)).save(path, optimize=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--height", type=int, default=192)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--png", default=None, help="also save a preview PNG of one frame here")
    ap.add_argument("--png-frame", type=int, default=22)
    args = ap.parse_args()
    if args.frames < 10:
        raise SystemExit("--frames must be >= 10")
    torch.set_num_threads(args.threads)
    world = SyntheticWorld(seed=args.seed, num_frames=args.frames + 2, height=args.height, width=args.width)
    world.render(0)  # warm-up (allocations, first calls)
    seq, seq_cpu, cold, cold_cpu = [], [], [], []
    for i in range(1, args.frames + 1):
        t, c = time.perf_counter(), time.process_time()
        world.render(i)
        seq.append(time.perf_counter() - t)
        seq_cpu.append(time.process_time() - c)
    for i in range(1, args.frames + 1):
        world._views.clear()
        world._images.clear()
        t, c = time.perf_counter(), time.process_time()
        world.render(i)
        cold.append(time.perf_counter() - t)
        cold_cpu.append(time.process_time() - c)
    if args.png:
        save_preview(SyntheticWorld(seed=args.seed, height=args.height, width=args.width), args.png_frame, args.png)
    print(json.dumps({
        "benchmark": "synthetic_render",
        "resolution": [args.height, args.width],
        "frames": args.frames,
        "outputs": ["image", "image_right", "depth", "flow_fwd", "flow_bwd", "flow_fwd_valid", "flow_bwd_valid",
                    "dynamic_mask"],
        "sequential": _stats(seq, seq_cpu),
        "cold": _stats(cold, cold_cpu),
        "torch_threads": torch.get_num_threads(),
        "machine": {"cpu": _cpu_name(), "cores": os.cpu_count(), "platform": platform.platform(),
                    "torch": torch.__version__, "load_avg_1min": os.getloadavg()[0]},
    }, indent=2))


if __name__ == "__main__":
    main()
