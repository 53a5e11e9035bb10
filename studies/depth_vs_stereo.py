"""A depth network against the stereo matcher on a drive it was trained on and on one it never saw (issue 38).

The SGBM depth of each sampled stereo pair (:func:`dfvo.data.stereo_hints.hint_depth`: the training's depth hints,
metric to a median 2.4 % on drive 0005's LiDAR pixels; model card) is dense where LiDAR is sparse, so it shows which
part of the image a network gets wrong and whether it gets it wrong where it was trained too. For each network and
drive: the median prediction / SGBM ratio over the image's lower third (mostly road) and over the rows above it,
down from the Eigen crop's top (40 % of the height), at SGBM depths of 1-80 m. A network that fits the training
drive (drive 0001: both ratios ~1) but reads the held-out drive's upper rows far (ratio > 1) has learnt that drive's
scene rather than depth.

    python studies/depth_vs_stereo.py --weights dfvo/checkpoints/depth.safetensors \
        campaign/depth_scene_shadow/weights.safetensors [--every 8] [--out J]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from dfvo.data.image_io import read_image
from dfvo.data.kitti_raw import open_drives
from dfvo.data.stereo_hints import hint_depth
from dfvo.io.checkpoint import find_checkpoint
from dfvo.sources.networks import NetworkDepth

SHARED = Path(__file__).resolve().parent.parent.parent / "shared" / "data"
DRIVES = {"2011_09_26_drive_0001 (trained on)": (SHARED / "kitti_raw", "2011_09_26_drive_0001"),
          "2011_09_26_drive_0005 (held out)": (SHARED / "kitti_raw_test", "2011_09_26_drive_0005")}
CROP_TOP = 0.4  # the Eigen (Garg) crop's top row, as a fraction of the height: the sky above it is not scored
ROAD_FROM = 2.0 / 3.0  # the lower third of the image: mostly road on a car's camera


def region_ratios(pred: np.ndarray, stereo: np.ndarray, near: float = 1.0, far: float = 80.0) -> dict[str, float]:
    """Median prediction / stereo depth in the image's lower third and in the rows above it (from the crop's top).

    Args:
        pred: (H,W) predicted depth in metres. stereo: (H,W) stereo depth in metres, 0 where the matcher gave none.
        near, far: the stereo depths scored (metres).
    Returns:
        ``{"lower third": r, "upper rows": r, "pixels": n}`` (nan for a region without scored pixels).
    """
    rows = (np.arange(stereo.shape[0]) / stereo.shape[0])[:, None]
    valid = (stereo >= near) & (stereo <= far) & (rows >= CROP_TOP)
    ratio = pred / np.where(valid, stereo, 1.0)
    out: dict[str, float] = {}
    for name, region in (("lower third", rows >= ROAD_FROM), ("upper rows", rows < ROAD_FROM)):
        r = ratio[valid & region]
        out[name] = float(np.median(r)) if r.size else float("nan")
    out["pixels"] = int(valid.sum())
    return out


def drive_ratios(net: NetworkDepth, root: Path, drive: str, every: int) -> dict[str, float]:
    """:func:`region_ratios` pooled over every ``every``-th stereo pair of one KITTI raw drive."""
    (d,) = open_drives(root, [drive])
    preds, stereos = [], []
    for left, right in list(zip(d.left, d.right))[::every]:
        stereo = hint_depth(left, right, d.fx_native, d.baseline, d.native_size)[0].numpy()
        with torch.no_grad():
            pred = net(read_image(left)[None])
        preds.append(F.interpolate(pred.float(), size=stereo.shape, mode="bilinear", align_corners=False)[0, 0].numpy())
        stereos.append(stereo)
    return region_ratios(np.concatenate(preds, axis=1), np.concatenate(stereos, axis=1))  # side by side: rows kept


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--weights", nargs="+", required=True)
    p.add_argument("--every", type=int, default=8, help="every N-th stereo pair of each drive")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", default=None, help="write the JSON here too")
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    result = {}
    for w in a.weights:
        net = NetworkDepth(find_checkpoint(w, "--weights"))
        result[w] = {name: drive_ratios(net, root, drive, a.every) for name, (root, drive) in DRIVES.items()}
    text = json.dumps({"every": a.every, "networks": result}, indent=1)
    print(text)
    if a.out:
        Path(a.out).write_text(text + "\n")


if __name__ == "__main__":
    main()
