"""CPU time of the loop's hot paths in isolation, on real KITTI frames: the dense flow refinement, the pyramid
refinement at its candidates, one road-alignment search (41 plane heights over the road patch), and two parts of the
tracker: the 1-D RANSAC of the CNN-depth scale (``simple_scale``, a batch of ``--pairs`` frames of 1,550 depth
ratios, 80 % usable: the tracker's typical count on KITTI; its time depends on the shapes only) and the depth
network's road-plane fit of one frame (``depth_road_height`` on the network's depth of the first frame).

Each is run once to warm up, then ``--repeats`` times interleaved with the others (a shared machine's load falls on
all of them alike); prints one JSON object with the minimum and median milliseconds per frame pair (dense, pyramid:
a batch of ``--pairs`` pairs) or per search (road). The functions it calls have kept their signatures, so the same
file times an older commit too (``git worktree add /tmp/old COMMIT``, then run this file from there):

    OMP_NUM_THREADS=1 python benchmarks/hot_paths.py --root ../shared/data/kitti_odom --threads 1
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from kornia.color import rgb_to_grayscale

from dfvo.inference.config import typed
from dfvo.inference.frames import build_sequence
from dfvo.matching.flow_refinement import FlowRefinementConfig, RefinementMode, refine_consecutive
from dfvo.matching.pyramid_refinement import refine_pyramid
from dfvo.sources import build_depth_source, build_flow_source
from dfvo.tracking import road_scale
from dfvo.tracking.config import RoadAlignmentConfig, TrackerConfig
from dfvo.tracking.scale import simple_scale
from dfvo.tracking.scale_fusion import depth_road_height

REPO = Path(__file__).resolve().parent.parent


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--root", default=str(REPO.parent / "shared" / "data" / "kitti_odom"))
    p.add_argument("--seq", default="07")
    p.add_argument("--pairs", type=int, default=4)
    p.add_argument("--repeats", type=int, default=10)
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    with initialize_config_dir(config_dir=str(REPO / "dfvo" / "conf" / "infer"), version_base="1.3"):
        cfg = typed(compose("infer", overrides=["data=kitti_odom", f"data.root={args.root}", f"seq={args.seq}",
                                                f"data.end={args.pairs + 1}"]))
    seq = build_sequence(cfg.data, cfg.seq, cfg.img_res)
    images = torch.stack([seq.image(i) for i in range(args.pairs + 1)])
    fwd, bwd = build_flow_source(cfg.flow, None, "cpu")(images[:-1], images[1:])
    refine: FlowRefinementConfig = cfg.flow.refine
    dense_cfg = FlowRefinementConfig(**{**refine.__dict__, "mode": RefinementMode.dense})
    dense_fwd, dense_bwd = refine_consecutive(images, fwd, bwd, dense_cfg)

    grey = rgb_to_grayscale(images[:2].float())
    K = seq.K.to(torch.float32)
    normal = torch.tensor([0.0, 1.0, 0.0])
    R, t = torch.eye(3), torch.tensor([0.0, 0.0, 1.0])
    road_cfg = RoadAlignmentConfig()
    pixels, blocks = road_scale.road_patch(K, normal, 1.65, tuple(grey.shape[-2:]), road_cfg, 1.0)
    centre = math.log(1.65 / 1.0)
    heights = torch.linspace(centre - math.log(road_cfg.span), centre + math.log(road_cfg.span),
                             2 * road_cfg.steps - 1, dtype=torch.float64)

    depth = build_depth_source(cfg.depth, None, "cpu")(images[:1], [0])
    tracker_cfg = TrackerConfig()
    g = torch.Generator().manual_seed(0)
    z_tri = 1.0 + 40.0 * torch.rand(args.pairs, 1550, generator=g, dtype=torch.float64)
    z_cnn = 0.8 * z_tri * (1.0 + 0.05 * torch.randn(args.pairs, 1550, generator=g, dtype=torch.float64))
    usable = torch.rand(args.pairs, 1550, generator=g) < 0.8

    def generators() -> list[torch.Generator]:
        return [torch.Generator().manual_seed(b) for b in range(args.pairs)]

    paths = {  # name: (call, how many units one call does, the unit)
        "scale_ransac": (lambda: simple_scale(z_cnn, z_tri, usable, generators=generators()), args.pairs, "frame"),
        "road_plane": (lambda: depth_road_height(depth, K[None], tracker_cfg, torch.Generator().manual_seed(0), 1.65),
                       1, "frame"),
        "dense_refinement": (lambda: refine_consecutive(images, fwd, bwd, dense_cfg), args.pairs, "pair"),
        "pyramid_refinement": (lambda: refine_pyramid(images, dense_fwd, dense_bwd, refine.pyramid), args.pairs,
                               "pair"),
        "road_search": (lambda: road_scale._cost_profiles(grey[:1], grey[1:], K, R, t, normal, pixels, blocks,
                                                          heights), 1, "search"),
    }
    times: dict[str, list[float]] = {name: [] for name in paths}
    for fn, _, _ in paths.values():  # warm-up
        fn()
    for _ in range(args.repeats):
        for name, (fn, per, _) in paths.items():
            start = time.process_time()
            fn()
            times[name].append(1000.0 * (time.process_time() - start) / per)
    print(json.dumps({
        "threads": torch.get_num_threads(), "pairs": args.pairs, "size": list(images.shape[-2:]),
        "road_patch_pixels": int(pixels.shape[0]), "road_heights": int(heights.numel()),
        **{name: {"cpu_ms_min": round(min(v), 2), "cpu_ms_median": round(statistics.median(v), 2),
                  "per": paths[name][2]} for name, v in times.items()},
    }))


if __name__ == "__main__":
    main()
