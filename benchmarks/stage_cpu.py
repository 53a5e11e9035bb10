"""CPU time of the per-batch stages in isolation: flow network, depth network, flow refinement, per frame.

Runs the shipped networks (``infer.py``'s sources, built from its config) and the default refinement on KITTI
frames (``--root``, sequence ``--seq``, 640x192), for each batch size in ``--batches``: each stage is run once to warm
up, then ``--repeats`` times; the minimum process CPU time (``time.process_time``: all threads; it follows the work,
not a shared machine's load) divided by the batch size is printed as one JSON object per batch size, with the
minimum wall time beside it.

Usage (``docs/speed.md``):
    OMP_NUM_THREADS=1 python benchmarks/stage_cpu.py --root ../shared/data/kitti_odom --batches 2 4 8
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

from dfvo.inference.config import typed
from dfvo.inference.frames import build_sequence
from dfvo.matching.flow_refinement import refine_consecutive
from dfvo.sources import build_depth_source, build_flow_source

REPO = Path(__file__).resolve().parents[1]


def _measure(fn: Callable[[], object], frames: int, repeats: int) -> dict[str, float]:
    fn()
    cpu, wall = [], []
    for _ in range(repeats):
        c, w = time.process_time(), time.perf_counter()
        fn()
        cpu.append(time.process_time() - c)
        wall.append(time.perf_counter() - w)
    return {"cpu_ms_per_frame": round(1000.0 * min(cpu) / frames, 1),
            "wall_ms_per_frame": round(1000.0 * min(wall) / frames, 1)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--root", default="../shared/data/kitti_odom")
    p.add_argument("--seq", default="06")
    p.add_argument("--batches", type=int, nargs="+", default=[4])
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--overrides", nargs="*", default=[], help="infer.yaml overrides (flow.refine.iterations=1 ...)")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    n = max(args.batches) + 1
    with initialize_config_dir(config_dir=str(REPO / "dfvo" / "conf" / "infer"), version_base="1.3"):
        cfg = typed(compose("infer", overrides=["data=kitti_odom", f"data.root={args.root}", f"seq={args.seq}",
                                                "flow=network", "depth=network", f"data.end={n}",
                                                *args.overrides]))
    seq = build_sequence(cfg.data, cfg.seq, cfg.img_res)
    imgs = torch.stack([seq.image(i) for i in range(n)])
    flow_src = build_flow_source(cfg.flow, None, "cpu")
    depth_src = build_depth_source(cfg.depth, None, "cpu")
    for b in args.batches:
        im = imgs[:b + 1]
        fwd, bwd = flow_src(im[:-1], im[1:])
        print(json.dumps({
            "batch": b, "size": list(im.shape[-2:]), "threads": torch.get_num_threads(),
            "flow": _measure(lambda im=im: flow_src(im[:-1], im[1:]), b, args.repeats),
            "depth": _measure(lambda im=im: depth_src(im[:-1]), b, args.repeats),
            "refine": _measure(lambda im=im, f=fwd, w=bwd: refine_consecutive(im, f, w, cfg.flow.refine), b,
                               args.repeats),
        }), flush=True)


if __name__ == "__main__":
    main()
