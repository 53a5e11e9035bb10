"""Speed of the synthetic world: milliseconds per frame, per scenario and resolution, on the CPU or a GPU.

Prints one JSON object with, for every (scenario, resolution):
    sequential: frames rendered in order with all outputs (left, right, depth, fwd/bwd flow, masks; what
        datasets and infer.py do; the next frame's cast is reused),
    cold: the same with empty caches (random access),
    flow_pair: one training item of ``SyntheticFlowDataset`` with frame skips (1, 2, 3) (left images of frames
        k and k+s, flow both ways, masks) with empty caches, what flow training renders per sample;
each as mean/median/min wall milliseconds and the mean process CPU milliseconds (all threads; on a shared
machine a contention-free lower bound on the work); plus torch threads, the device and the machine's load.

Usage: python benchmarks/synthetic_render.py [--scenarios drive,highway] [--sizes 192x640,96x320] [--frames 10]
       [--threads 1] [--device cpu|cuda] [--speed 2.0] [--png docs/images/synthetic_frame.png --png-frame 22]
       (--png also saves a 2x2 preview of the first scenario at the first size: left, right, depth (inverse,
       magma), forward flow (hue = direction, saturation = magnitude, black = invalid))
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time

import torch

from dfvo.synthetic import SyntheticFlowDataset, SyntheticWorld


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
    return {"mean_ms": round(1e3 * statistics.mean(times), 1), "median_ms": round(1e3 * statistics.median(times), 1),
            "min_ms": round(1e3 * min(times), 1), "cpu_mean_ms": round(1e3 * statistics.mean(cpu), 1)}


def save_preview(world: SyntheticWorld, index: int, path: str) -> None:
    """Write a 2x2 PNG: left | right image, depth | colour-coded forward flow."""
    import matplotlib
    import numpy as np
    from PIL import Image

    s = {k: v.cpu() for k, v in world.render(index).items()}
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


def _timed(fn, device: torch.device) -> tuple[float, float]:
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    t, c = time.perf_counter(), time.process_time()
    fn()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter() - t, time.process_time() - c


def bench(scenario: str, height: int, width: int, frames: int, seed: int, device: torch.device,
          speed: float | None) -> dict:
    """Timings of one scenario at one resolution (see the module docstring)."""
    world = SyntheticWorld(seed=seed, num_frames=frames + 4, height=height, width=width, scenario=scenario,
                           speed=speed, device=device)
    world.render(0)  # warm-up (allocations, first calls)
    seq, seq_cpu, cold, cold_cpu, pair, pair_cpu = [], [], [], [], [], []
    for i in range(1, frames + 1):
        w, c = _timed(lambda i=i: world.render(i), device)
        seq.append(w)
        seq_cpu.append(c)
    for i in range(1, frames + 1):
        world._views.clear()
        world._images.clear()
        w, c = _timed(lambda i=i: world.render(i), device)
        cold.append(w)
        cold_cpu.append(c)
    ds = SyntheticFlowDataset([seed], num_frames=frames + 4, height=height, width=width, frame_skips=(1, 2, 3),
                              scenario=scenario, speed=speed, device=device)
    order = torch.randperm(len(ds), generator=torch.Generator().manual_seed(0))[:frames].tolist()
    for n in order:
        ds.worlds[0]._views.clear()
        ds.worlds[0]._images.clear()
        w, c = _timed(lambda n=n: ds[n], device)
        pair.append(w)
        pair_cpu.append(c)
    return {"scenario": scenario, "resolution": [height, width], "frames": frames,
            "objects": len(world._scene.half), "vehicles": world._scene.num_dynamic,
            "sequential": _stats(seq, seq_cpu), "cold": _stats(cold, cold_cpu), "flow_pair": _stats(pair, pair_cpu)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", default="drive,highway")
    ap.add_argument("--sizes", default="192x640,96x320", help="comma-separated HxW")
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--speed", type=float, default=None, help="camera speed in m/frame (default: the scenario's)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--png", default=None, help="also save a preview PNG of one frame here")
    ap.add_argument("--png-frame", type=int, default=22)
    args = ap.parse_args()
    if args.frames < 3:
        raise SystemExit("--frames must be >= 3")
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",")]
    scenarios = args.scenarios.split(",")
    results = [bench(sc, h, w, args.frames, args.seed, device, args.speed) for sc in scenarios for h, w in sizes]
    if args.png:
        h, w = sizes[0]
        save_preview(SyntheticWorld(seed=args.seed, num_frames=args.png_frame + 2, height=h, width=w,
                                    scenario=scenarios[0], speed=args.speed, device=device), args.png_frame, args.png)
    print(json.dumps({
        "benchmark": "synthetic_render",
        "outputs": {"sequential/cold": ["image", "image_right", "depth", "flow_fwd", "flow_bwd", "flow_fwd_valid",
                                        "flow_bwd_valid", "dynamic_mask"],
                    "flow_pair": ["image", "image_next", "flow_fwd", "flow_bwd", "flow_fwd_valid", "flow_bwd_valid",
                                  "dynamic_mask"]},
        "results": results,
        "torch_threads": torch.get_num_threads(),
        "device": str(device) if device.type != "cuda" else torch.cuda.get_device_name(device),
        "machine": {"cpu": _cpu_name(), "cores": os.cpu_count(), "platform": platform.platform(),
                    "torch": torch.__version__, "load_avg_1min": os.getloadavg()[0]},
    }, indent=2))


if __name__ == "__main__":
    main()
