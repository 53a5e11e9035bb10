"""How far does a depth network move its road plane when a patch of road is darkened (a cast shadow)? Prints JSON.

The depth does not change under a shadow, so a network that sees the scene keeps its road where it was. For each
network (``--weights``) and each of ``--frames`` of KITTI odometry ``--seq``, the tracker's own road-plane height
(:func:`dfvo.tracking.scale_fusion.depth_road_height`) of the frame as it is and with one of three shadows (the left
half of the lower 40 % of the image, a diagonal band from the lower left, a horizontal band across the road at rows
0.70-0.85) at 45 % brightness; reported: the median and the largest relative change of the height per shadow.

    python studies/shadow_sensitivity.py --weights dfvo/checkpoints/depth.safetensors RUNS/NAME/weights.safetensors
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from dfvo.sources import build_depth_source  # noqa: E402
from dfvo.tracking.config import TrackerConfig  # noqa: E402
from dfvo.tracking.scale_fusion import depth_road_height  # noqa: E402
from studies.road_height import _sequence  # noqa: E402


def shadows(H: int, W: int) -> dict[str, torch.Tensor]:
    """(H,W) masks, 1 in the shadow."""
    v, u = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    return {"left half": ((u < W * 0.5) & (v > H * 0.6)).float(),
            "diagonal": ((u + (H - v) * 2.0 < W * 0.6) & (v > H * 0.55)).float(),
            "band": ((v > H * 0.7) & (v < H * 0.85)).float()}


def sensitivity(weights: str, root: str, seq: str, frames: list[int], darkening: float = 0.55) -> dict:
    cfg, sequence = _sequence("kitti_odom", root, seq, weights)
    source = build_depth_source(cfg.depth, None, "cpu")
    K = sequence.K.to(torch.float32)[None]
    images = torch.stack([sequence.image(i) for i in frames])

    def heights(x: torch.Tensor) -> np.ndarray:
        depth = source(x, frames)
        out = [depth_road_height(depth[b:b + 1], K, TrackerConfig(), torch.Generator().manual_seed(0)).height_unit
               for b in range(len(frames))]
        return np.array([h if h else np.nan for h in out])

    base = heights(images)
    result: dict = {"heights_m": [round(float(h), 3) for h in base]}
    for name, mask in shadows(*images.shape[-2:]).items():
        change = heights(images * (1 - darkening * mask)) / base - 1
        result[name] = {"median": round(float(np.nanmedian(change)), 4),
                        "largest": round(float(np.nanmax(np.abs(change))), 4)}
    return result


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--weights", nargs="+", default=["dfvo/checkpoints/depth.safetensors"])
    p.add_argument("--root", default=str(REPO.parent / "shared" / "data" / "kitti_odom"))
    p.add_argument("--seq", default="07")
    p.add_argument("--frames", default="40,55,70,85,100,115,130,145")
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    frames = [int(f) for f in a.frames.split(",")]
    print(json.dumps({w: sensitivity(w, a.root, a.seq, frames) for w in a.weights}, indent=1))


if __name__ == "__main__":
    main()
