"""Benchmark the real-data loaders: decode time per frame and per sample. Prints one JSON object.

    OMP_NUM_THREADS=1 python benchmarks/datasets.py [--shared ../shared/data] [--repeats 3]

Numbers (milliseconds, median over repeats of the mean over all frames):
    read_image_png_gray_ms: ``read_image`` of KITTI odometry 06 image_0 (1226x370 8-bit gray PNG → (3,H,W) float).
    read_image_jpg_color_ms: ``read_image`` of the KITTI raw JPEGs (1242x375 colour).
    kitti_odom_sample_native_ms / kitti_odom_sample_640x192_ms: ``KittiOdometry[i]`` with the stereo pair.
    kitti_raw_snippet_640x192_ms: ``KittiRawSnippets[i]`` (4 images: i-1, i, i+1, right).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

import torch

from dfvo.data.image_io import list_images, read_image
from dfvo.data.kitti_odometry import KittiOdometry
from dfvo.data.kitti_raw import KittiRawSnippets


def _time_per_item(fn, items, repeats: int) -> float:
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        for item in items:
            fn(item)
        runs.append((time.perf_counter() - start) / len(items) * 1000.0)
    return round(statistics.median(runs), 2)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shared", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    odom_root = args.shared / "kitti_odom"
    raw_root = args.shared / "kitti_raw"
    if not odom_root.is_dir() or not raw_root.is_dir():
        raise SystemExit(f"needs {odom_root} and {raw_root} (the project's ../shared data)")
    out: dict[str, object] = {"machine": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
                              "torch_threads": torch.get_num_threads()}
    pngs = list_images(odom_root / "sequences" / "06" / "image_0")
    jpgs = list_images(next(raw_root.glob("*/*_sync")) / "image_02" / "data")[:51]
    out["read_image_png_gray_ms"] = _time_per_item(read_image, pngs, args.repeats)
    out["read_image_jpg_color_ms"] = _time_per_item(read_image, jpgs, args.repeats)
    native = KittiOdometry(odom_root, "06")
    out["kitti_odom_sample_native_ms"] = _time_per_item(native.__getitem__, range(len(native)), args.repeats)
    small = KittiOdometry(odom_root, "06", height=192, width=640)
    out["kitti_odom_sample_640x192_ms"] = _time_per_item(small.__getitem__, range(len(small)), args.repeats)
    raw = KittiRawSnippets(raw_root, 192, 640)
    out["kitti_raw_snippet_640x192_ms"] = _time_per_item(raw.__getitem__, range(0, len(raw), 4), args.repeats)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
