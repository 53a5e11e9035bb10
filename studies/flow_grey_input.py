"""Does a flow network see a greyscale pair as it sees the colour one? KITTI odometry's frames are grey, KITTI raw's
colour; the flow networks' mixed training phases see KITTI raw in colour. For every network given, on pairs
(k, k + ``--gap``) of a KITTI raw drive (colour, resized bilinearly to 640x192), the flow of the colour pair against
the flow of the same pair in grey (ITU-R 601 luma in all three channels, as a grey KITTI frame is read): median and
mean end-point difference (px), the median flow length, and the difference from the first network's colour flow.

    python studies/flow_grey_input.py --drive ../shared/data/kitti_raw/2011_09_26/2011_09_26_drive_0001_sync \\
        checkpoints/flow.safetensors RUNS/flow_every/weights.safetensors

prints one JSON object (network -> numbers).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
from kornia.color import rgb_to_grayscale

from dfvo.data.image_io import read_image
from dfvo.io.checkpoint import find_checkpoint
from dfvo.sources.networks import NetworkFlow


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("checkpoints", nargs="+", help="flow weights files (the first is the reference)")
    p.add_argument("--drive", required=True, help="a KITTI raw drive folder (its image_02/data/*.jpg|png)")
    p.add_argument("--gap", type=int, default=2, help="frame gap of the pairs (default 2)")
    p.add_argument("--every", type=int, default=10, help="a pair every N frames (default 10)")
    p.add_argument("--pairs", type=int, default=10, help="number of pairs (default 10)")
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    files = sorted([*Path(a.drive, "image_02", "data").glob("*.jpg"), *Path(a.drive, "image_02", "data").glob("*.png")])
    starts = [k for k in range(0, len(files) - a.gap, a.every)][:a.pairs]
    if not starts:
        raise SystemExit(f"--drive {a.drive}: no image_02/data frames for pairs with --gap {a.gap}")
    size = (192, 640)
    A = torch.stack([read_image(files[k], size=size) for k in starts])
    B = torch.stack([read_image(files[k + a.gap], size=size) for k in starts])
    gA, gB = (rgb_to_grayscale(x).expand(-1, 3, -1, -1) for x in (A, B))
    out, ref = {}, None
    for ckpt in a.checkpoints:
        net = NetworkFlow(find_checkpoint(ckpt))
        with torch.no_grad():
            colour, _ = net(A, B)
            grey, _ = net(gA, gB)
        ref = colour if ref is None else ref
        d, r = (colour - grey).norm(dim=1), (colour - ref).norm(dim=1)
        out[ckpt] = {"colour_vs_grey_px": {"median": round(float(d.median()), 3), "mean": round(float(d.mean()), 3)},
                     "flow_length_median_px": round(float(colour.norm(dim=1).median()), 2),
                     "vs_first_colour_px": {"median": round(float(r.median()), 3), "mean": round(float(r.mean()), 3)}}
    print(json.dumps({"drive": a.drive, "gap": a.gap, "pairs": starts, "size": list(size), "networks": out}, indent=1))


if __name__ == "__main__":
    main()
