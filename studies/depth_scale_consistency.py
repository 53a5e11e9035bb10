"""How consistent is a depth network's metric scale from frame to frame? (What DF-VO's scale recovery sees.)

DF-VO takes each frame's translation scale from the ratio of CNN depth to triangulated depth at the selected
correspondences, so the frame-to-frame spread of that ratio is the spread of the translation lengths, whatever the
flow. Here the reference depth is true, so the ratio ``z_cnn / z_true`` isolates the depth network: per frame its
median over the correspondences the tracker would use (shipped flow network + photometric refinement + local best-K
at 0.1 px, rows below the top 30 %, CNN depth in (0, 50] m), then over frames the mean (metric bias) and standard
deviation (per-frame scale noise; a 10 % spread is ~0.12 m of RPE at KITTI speed); ``gross_error_fraction``: per
frame the share of those points whose CNN depth is off by more than a factor 2, averaged over frames (what makes the
tracker's 1-D RANSAC lock onto a wrong scale). ``parallax_3px`` repeats the statistics on the points with more than
3 px of flow, with the mean ratio per true-depth band (a ratio falling with depth: the network compresses far depth).

- KITTI odometry (default): ``z_true`` is triangulated with the TRUE relative pose of every pair (KITTI ground truth;
  low-parallax points add triangulation noise, hence ``parallax_3px``).
- Synthetic held-out worlds (``--synthetic drive,city,straight,highway``, or ``all``): ``z_true`` is the world's exact
  depth at the correspondences (sky excluded), ``--worlds-per-scenario`` worlds (seeds 1000, 1001, ...; never trained
  on) of ``--num-frames`` frames each; one block of statistics per scenario. ``dense`` adds the per-frame median of
  CNN / true depth over every pixel with true depth <= 80 m (lower 70 % of the image), the Eigen abs rel there, and
  the per-frame median per true-depth band (far-depth compression over whole surfaces, not only at the points).

    python studies/depth_scale_consistency.py --depth dfvo/checkpoints/depth.safetensors
    python studies/depth_scale_consistency.py --synthetic all --cache /tmp/dsc_synth.pt --depth W.safetensors

prints one JSON object. ``--depth`` takes a .safetensors / .pt DepthNet or a depth training ``.ckpt``. ``--cache FILE``
keeps the frames and their correspondences (which do not depend on the depth network): the first call writes it,
later calls with the same data settings evaluate another depth network in seconds.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from dfvo.matching.consistency import forward_backward_inconsistency
from dfvo.matching.flow_refinement import FlowRefinementConfig, refine_forward_backward
from dfvo.matching.selection import select_correspondences
from dfvo.sources.networks import NetworkDepth, NetworkFlow
from dfvo.tracking.scale import sample_depth, triangulated_depth

BANDS = ((0.0, 8.0), (8.0, 15.0), (15.0, 25.0), (25.0, 50.0))
DENSE_MAX_DEPTH = 80.0
DENSE_BANDS = (*BANDS, (50.0, DENSE_MAX_DEPTH))


def _correspondences(prev: torch.Tensor, cur: torch.Tensor, flow_src: NetworkFlow):
    """The tracker's correspondences (refined network flow, local best-K) of pairs prev (B,3,H,W) -> cur."""
    fwd, bwd = refine_forward_backward(prev, cur, *flow_src(prev, cur), FlowRefinementConfig())
    return select_correspondences(fwd, forward_backward_inconsistency(fwd, bwd))


def _record(image: torch.Tensor, pi: torch.Tensor, pj: torch.Tensor, z_true: torch.Tensor, usable: torch.Tensor,
            dense: torch.Tensor | None = None) -> dict:
    """One frame: image (3,H,W) as uint8, points (N,2) of it, true depth (N,) at them, usable (N,) bool, parallax
    (N,) pixels, and (synthetic) the dense true depth (1,H,W)."""
    rec = {"image": (image.clamp(0, 1) * 255).round().to(torch.uint8), "pts": pi.float(),
           "z_true": z_true.double(), "usable": usable, "parallax": (pj - pi).norm(dim=-1).float()}
    if dense is not None:
        rec["dense"] = dense.half()
    return rec


def kitti_records(root: str, seq: str, height: int, width: int, flow_src: NetworkFlow) -> list[dict]:
    """Frames of a KITTI odometry sequence with the depth of their correspondences triangulated with the true pose."""
    from dfvo.data.kitti_odometry import KittiOdometry

    ds = KittiOdometry(root, seq, height=height, width=width, stereo=False)
    if ds.poses is None:
        raise SystemExit(f"{root}/poses/{seq}.txt is needed (true poses)")
    K = ds.intrinsics[None].double()
    records, pairs = [], list(range(len(ds) - 1))
    for start in range(0, len(pairs), 4):
        ks = pairs[start:start + 4]
        prev = torch.stack([ds[k]["image"] for k in ks])
        sel = _correspondences(prev, torch.stack([ds[k + 1]["image"] for k in ks]), flow_src)
        for b, k in enumerate(ks):
            if bool(sel.failed[b]):
                continue
            T_cur_prev = np.linalg.inv(ds.poses[k + 1]) @ ds.poses[k]
            length = float(np.linalg.norm(T_cur_prev[:3, 3]))
            if length < 0.1:
                continue
            R = torch.from_numpy(T_cur_prev[:3, :3])[None]
            t = torch.from_numpy(T_cur_prev[:3, 3] / length)[None]
            pi, pj = sel.pts_i[b:b + 1], sel.pts_j[b:b + 1]
            z_tri, front = triangulated_depth(R, t, K, pi, pj)
            records.append(_record(prev[b], pi[0], pj[0], z_tri[0] * length, (front & sel.mask[b:b + 1])[0]))
    return records


def synthetic_records(scenario: str, per_scenario: int, num_frames: int, height: int, width: int,
                      flow_src: NetworkFlow) -> list[dict]:
    """Frames of the held-out worlds of ``scenario`` with the exact depth at their correspondences (sky excluded)."""
    from dfvo.synthetic import SKY_DEPTH, held_out_worlds

    records = []
    for spec in held_out_worlds([scenario], per_scenario):
        world = spec.make(num_frames=num_frames, height=height, width=width)
        pairs = list(range(num_frames - 1))
        for start in range(0, len(pairs), 4):
            ks = pairs[start:start + 4]
            prev = torch.stack([world.image(k) for k in ks])
            sel = _correspondences(prev, torch.stack([world.image(k + 1) for k in ks]), flow_src)
            for b, k in enumerate(ks):
                if bool(sel.failed[b]):
                    continue
                true = world.depth(k)
                pi, pj = sel.pts_i[b:b + 1], sel.pts_j[b:b + 1]
                z_true, _ = sample_depth(true[None], pi, max_depth=float("inf"), crop_top=0.0)
                usable = sel.mask[b:b + 1] & (z_true < SKY_DEPTH)
                records.append(_record(prev[b], pi[0], pj[0], z_true[0], usable[0], dense=true))
    return records


def _summary(values: list[float]) -> dict:
    return {"frames": len(values), "mean": round(float(np.mean(values)), 3) if values else None,
            "std": round(float(np.std(values)), 3) if values else None}


def statistics(records: list[dict], depth_src: NetworkDepth, batch: int = 8) -> dict:
    """CNN / true depth statistics of ``records`` (see the module docstring)."""
    per_frame, per_frame_all, gross, bands = [], [], [], {b: [] for b in BANDS}
    dense_ratio, dense_abs_rel, dense_bands = [], [], {b: [] for b in DENSE_BANDS}
    for start in range(0, len(records), batch):
        chunk = records[start:start + batch]
        depth = depth_src(torch.stack([r["image"] for r in chunk]).float() / 255.0)
        for b, rec in enumerate(chunk):
            pi = rec["pts"][None]
            z_cnn, ok = sample_depth(depth[b:b + 1], pi)
            used = (ok[0] & rec["usable"])
            z_true = rec["z_true"]
            if int(used.sum()) >= 20:
                ratio_all = z_cnn[0][used] / z_true[used]
                per_frame_all.append(float(ratio_all.median()))
                gross.append(float(((ratio_all > 2.0) | (ratio_all < 0.5)).double().mean()))
            m = used & (rec["parallax"] > 3.0)
            if int(m.sum()) >= 20:
                ratio = z_cnn[0][m] / z_true[m]
                per_frame.append(float(ratio.median()))
                for lo, hi in BANDS:
                    band = (z_true[m] >= lo) & (z_true[m] < hi)
                    if int(band.sum()) >= 20:
                        bands[(lo, hi)].append(float(ratio[band].median()))
            if "dense" in rec:
                gt, pred = rec["dense"].float(), depth[b]
                valid = (gt > 0) & (gt <= DENSE_MAX_DEPTH)
                valid[:, : int(0.3 * gt.shape[-2])] = False
                if int(valid.sum()) >= 100:
                    dense_ratio.append(float((pred[valid] / gt[valid]).median()))
                    dense_abs_rel.append(float(((pred[valid] - gt[valid]).abs() / gt[valid]).mean()))
                for lo, hi in DENSE_BANDS:
                    band = valid & (gt >= lo) & (gt < hi)
                    if int(band.sum()) >= 100:
                        dense_bands[(lo, hi)].append(float((pred[band] / gt[band]).median()))
    r, r_all = np.array(per_frame), np.array(per_frame_all)
    out = {"frames": len(r_all),
           "cnn_over_true_mean": round(float(r_all.mean()), 4) if len(r_all) else None,
           "cnn_over_true_per_frame_std": round(float(r_all.std()), 4) if len(r_all) else None,
           "gross_error_fraction": round(float(np.mean(gross)), 4) if gross else None,
           "parallax_3px": {
               "frames": len(r), "cnn_over_true_mean": round(float(r.mean()), 4) if len(r) else None,
               "cnn_over_true_per_frame_std": round(float(r.std()), 4) if len(r) else None,
               "per_depth_band": {f"{lo:g}-{hi:g} m": _summary(v) for (lo, hi), v in bands.items()}}}
    if dense_ratio:
        out["dense"] = {"frames": len(dense_ratio), "cnn_over_true_mean": round(float(np.mean(dense_ratio)), 4),
                        "cnn_over_true_per_frame_std": round(float(np.std(dense_ratio)), 4),
                        "abs_rel": round(float(np.mean(dense_abs_rel)), 4),
                        "per_depth_band": {f"{lo:g}-{hi:g} m": _summary(v) for (lo, hi), v in dense_bands.items()}}
    return out


def main() -> None:
    repo = Path(__file__).resolve().parents[1]
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--depth", default=str(repo / "dfvo/checkpoints/depth.safetensors"))
    p.add_argument("--depth-input-size", default=None, help="H,W the depth network runs at (default: metadata)")
    p.add_argument("--flip-average", action="store_true", help="depth.flip_average: blend with the mirrored image")
    p.add_argument("--flow", default=str(repo / "dfvo/checkpoints/flow.safetensors"))
    p.add_argument("--root", default=str(repo.parent / "shared/data/kitti_odom"))
    p.add_argument("--seq", default="06")
    p.add_argument("--synthetic", default=None,
                   help="comma-separated scenarios (drive,city,straight,highway) or 'all': held-out synthetic worlds "
                        "instead of KITTI")
    p.add_argument("--worlds-per-scenario", type=int, default=2)
    p.add_argument("--num-frames", type=int, default=30, help="frames per synthetic world")
    p.add_argument("--cache", default=None, help="file keeping the frames and correspondences (written once)")
    p.add_argument("--height", type=int, default=192)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    size = None if args.depth_input_size is None else [int(v) for v in args.depth_input_size.split(",")]
    depth_src = NetworkDepth(args.depth, input_size=size, flip_average=args.flip_average)
    if args.synthetic:
        from dfvo.synthetic import TRAINING_SCENARIOS
        scenarios = list(TRAINING_SCENARIOS) if args.synthetic == "all" else args.synthetic.split(",")
        key = {"synthetic": scenarios, "worlds": args.worlds_per_scenario, "frames": args.num_frames}
    else:
        scenarios, key = [], {"root": args.root, "sequence": args.seq}
    key.update(flow=args.flow, resolution=[args.height, args.width])
    cached = torch.load(args.cache, weights_only=False) if args.cache and Path(args.cache).exists() else None
    if cached is not None and cached["key"] != key:
        raise SystemExit(f"--cache {args.cache} holds {cached['key']}, not {key}: use another file")
    if cached is None:
        flow_src = NetworkFlow(args.flow)
        if scenarios:
            groups = {sc: synthetic_records(sc, args.worlds_per_scenario, args.num_frames, args.height, args.width,
                                            flow_src) for sc in scenarios}
        else:
            groups = {args.seq: kitti_records(args.root, args.seq, args.height, args.width, flow_src)}
        cached = {"key": key, "groups": groups}
        if args.cache:
            torch.save(cached, args.cache)
    head = {"depth": args.depth, "flip_average": args.flip_average, "flow": args.flow,
            "resolution": [args.height, args.width],
            "depth_network_input": list(depth_src.input_size) if depth_src.input_size else None}
    if scenarios:
        head.update(worlds_per_scenario=args.worlds_per_scenario, num_frames=args.num_frames)
        head["scenarios"] = {sc: statistics(cached["groups"][sc], depth_src) for sc in scenarios}
    else:
        head.update(sequence=args.seq, **statistics(cached["groups"][args.seq], depth_src))
    print(json.dumps(head))


if __name__ == "__main__":
    main()
