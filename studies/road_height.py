"""How high does the depth network put the camera above the road, sequence by sequence? (The camera height a user's
own video gets, ``tracker.camera_height.estimate``.)

Without a given camera height the tracker takes the median of the depth network's per-frame road-plane heights
(:func:`dfvo.tracking.scale_fusion.depth_road_height`), so every step length of a video inherits that median's error.
This study runs the shipped depth network over whole sequences (KITTI odometry and KITTI raw: the camera is 1.65 m
above the road in all of them) and reports, per sequence and per road band (rows and columns of the image the plane
is fitted in), the median height over frames and its robust spread. A band that removed the error would give 1.65 m
everywhere; a network whose metric scale near the road changes from scene to scene gives different medians whatever
the band.

``--run DIR`` adds, for a KITTI odometry run of ``infer.py`` (``frames.csv``) with ground-truth poses, the camera
height that the photometric road alignment measures in that run's translation unit times the true step length
(``camera_height * true length / scale_homography`` per frame): the road's own height, independent of the network.

    python studies/road_height.py --kitti-odom ../shared/data/kitti_odom --seqs 06,07 \\
        --kitti-raw ../shared/data/kitti_raw --drives 2011_09_26_drive_0001
    python studies/road_height.py --kitti-odom ../shared/data/kitti_odom --seqs 07 --run runs/07

prints one JSON object.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
from pathlib import Path

import numpy as np
import torch
from hydra import compose, initialize_config_dir

from dfvo.inference.config import typed
from dfvo.inference.frames import build_sequence
from dfvo.sources import build_depth_source
from dfvo.tracking.camera_height import CameraHeight
from dfvo.tracking.config import CameraHeightConfig, TrackerConfig
from dfvo.tracking.scale_fusion import depth_road_height

REPO = Path(__file__).resolve().parents[1]
KITTI_CAMERA_HEIGHT = 1.65
# name -> tracker.road_plane fields; "default" is the band the tracker uses
BANDS: dict[str, dict[str, float]] = {
    "default": {},
    "rows 0.6-0.8 (farther)": {"min_row_fraction": 0.6, "max_row_fraction": 0.8},
    "rows 0.8-0.95 (nearer)": {"min_row_fraction": 0.8, "max_row_fraction": 0.95},
    "columns +-0.1 (narrower)": {"max_col_offset_fraction": 0.1},
    "columns +-0.35 (wider)": {"max_col_offset_fraction": 0.35},
}


def _sequence(kind: str, root: str, seq: str, depth_checkpoint: str | None = None):
    extra = [f"depth.checkpoint={depth_checkpoint}"] if depth_checkpoint else []
    with initialize_config_dir(config_dir=str(REPO / "dfvo" / "conf" / "infer"), version_base="1.3"):
        cfg = typed(compose("infer", overrides=[f"data={kind}", f"data.root={root}", f"seq={seq}", *extra]))
    return cfg, build_sequence(cfg.data, cfg.seq, cfg.img_res)


def network_heights(kind: str, root: str, seq: str, batch: int = 8, depth_checkpoint: str | None = None) -> dict:
    """Median network road height (m) and spread over the frames of one sequence, per band (``depth_checkpoint``:
    another depth network than the shipped one)."""
    cfg, frames = _sequence(kind, root, seq, depth_checkpoint)
    depth_src = build_depth_source(cfg.depth, None, "cpu")
    K = frames.K.to(torch.float32)[None]
    base = TrackerConfig()
    # the tracker's own estimator per band: the median of the per-frame heights and its robust spread
    heights = {name: CameraHeight(None, base.camera_height) for name in BANDS}
    per_frame: dict[str, list[float | None]] = {name: [] for name in BANDS}
    for start in range(0, frames.length, batch):
        idx = list(range(start, min(frames.length, start + batch)))
        depth = depth_src(torch.stack([frames.image(i) for i in idx]), idx)
        for b in range(len(idx)):
            for name, fields in BANDS.items():
                tcfg = dataclasses.replace(base, road_plane=dataclasses.replace(base.road_plane, **fields))
                height = depth_road_height(depth[b:b + 1], K, tcfg, torch.Generator().manual_seed(0)).height_unit
                heights[name].observe(height)
                per_frame[name].append(height)
    return {"frames": frames.length, "bands": {
        name: {"median_m": round(h.estimate, 4), "vs_1.65": round(h.estimate / KITTI_CAMERA_HEIGHT - 1, 4),
               "spread": None if h.spread is None else round(h.spread, 4), "frames_with_plane": len(h.heights),
               **heights_in_use(per_frame[name], base.camera_height)}
        if h.estimate is not None else None for name, h in heights.items()}}


def heights_in_use(per_frame: list[float | None], cfg: CameraHeightConfig,
                   truth: float = KITTI_CAMERA_HEIGHT) -> dict:
    """The camera height a video's tracker uses frame by frame (its causal estimator, :class:`CameraHeight`, fed the
    network's per-frame road heights in order, None where no plane): the value farthest from ``truth``
    (``in_use_worst_m``) and the fraction of frames whose value in use is off by more than 5 %, or unavailable
    (``in_use_off_5pct``): a network whose road reads far on a sequence's first frames gets a median near ``truth``
    over the whole sequence but lends the tracker a wrong height while it starts."""
    estimator, used = CameraHeight(None, cfg), []
    for height in per_frame:
        estimator.observe(height)
        used.append(estimator.value)
    known = [u for u in used if u is not None]
    worst = max(known, key=lambda u: abs(u / truth - 1.0)) if known else None
    off = sum(1 for u in used if u is None or abs(u / truth - 1.0) > 0.05)
    return {"in_use_worst_m": None if worst is None else round(worst, 4),
            "in_use_off_5pct": round(off / max(len(used), 1), 4)}


def photometric_height(run: Path, poses_file: Path) -> dict:
    """The road's height from a run's photometric road alignment and the true step lengths (see the docstring)."""
    poses = np.loadtxt(poses_file).reshape(-1, 3, 4)
    lengths = np.linalg.norm(np.diff(poses[:, :, 3], axis=0), axis=1)
    values = []
    with open(run / "frames.csv", newline="") as f:
        for row in csv.DictReader(f):
            try:
                frame, height, scale = int(row["frame"]), float(row["camera_height"]), float(row["scale_homography"])
            except (KeyError, ValueError):
                continue
            if np.isfinite(height) and np.isfinite(scale) and scale > 0 and 0 < frame <= len(lengths):
                values.append(float(lengths[frame - 1] * height / scale))
    if not values:
        return {"frames": 0}
    q25, q50, q75 = np.percentile(values, [25, 50, 75])
    return {"frames": len(values), "median_m": round(float(q50), 4), "q25_m": round(float(q25), 4),
            "q75_m": round(float(q75), 4)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--kitti-odom", default=str(REPO.parent / "shared" / "data" / "kitti_odom"))
    p.add_argument("--seqs", default="06,07", help="KITTI odometry sequences (comma-separated; '' for none)")
    p.add_argument("--kitti-raw", default=str(REPO.parent / "shared" / "data" / "kitti_raw"))
    p.add_argument("--drives", default="", help="KITTI raw drives (comma-separated)")
    p.add_argument("--run", action="append", default=[],
                   help="an infer.py output folder of a KITTI odometry sequence (its frames.csv; repeatable)")
    p.add_argument("--depth-checkpoint", default=None, help="a depth network other than the shipped one")
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    out: dict = {"true_camera_height_m": KITTI_CAMERA_HEIGHT, "network": {}, "photometric": {}}
    for seq in filter(None, args.seqs.split(",")):
        out["network"][f"kitti_odom {seq}"] = network_heights("kitti_odom", args.kitti_odom, seq,
                                                              depth_checkpoint=args.depth_checkpoint)
    for drive in filter(None, args.drives.split(",")):
        out["network"][f"kitti_raw {drive}"] = network_heights("kitti_raw", args.kitti_raw, drive,
                                                               depth_checkpoint=args.depth_checkpoint)
    for run in args.run:
        summary = json.loads((Path(run) / "summary.json").read_text())
        seq = str(summary.get("sequence", Path(run).name))
        poses = Path(args.kitti_odom) / "poses" / f"{seq}.txt"
        out["photometric"][run] = {"sequence": seq, **photometric_height(Path(run), poses)}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
