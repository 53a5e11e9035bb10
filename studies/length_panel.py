"""The accuracy panel of issue 24: every configuration on every case, end to end through ``infer.py``.

Cases (``--cases``): KITTI odometry 06 at ``data.step`` 1, 2, 3 (1.2, 2.4, 3.6 m a frame; its 51 frames) and
07 at 1, 2 (its 160 frames, 0.57 m a frame, a 96 deg turn); held-out synthetic worlds (seed 1000, never trained on)
of each scenario (drive, city, straight, highway; ``--synthetic-frames`` frames each); and, when ``--video`` names an
H.264 file of KITTI 07's frames (``--make-video`` writes one with PyAV), 07 read as a user's own video with the four
intrinsics only (no camera height: it is estimated); when ``../shared`` beside ``--kitti-root`` holds them, KITTI raw
drive 0005 (``kitti_raw_0005``: oxts ground truth, an Eigen test drive) and ``handheld_markers`` (210 hand-held
frames with marker-based poses, run with ``experiment=handheld`` unless the configuration names its own experiment;
its metric scale is the driving network's: read its true-length RPE and 7-DoF ATE); with ``--handheld-seeds``, the
synthetic hand-held worlds of those seeds, planar and corner (``synthetic_handheld_planar_sS``,
``synthetic_handheld_sS``; ``--synthetic-frames`` frames, the default ``tracker.motion=auto``), tabulated apart in
``OUT/handheld.md``: constant-motion frames, 7-DoF ATE, true-length RPE and ``auto``'s verdict.

Configurations (``--configs``, each a name from :data:`CONFIGS` or ``NAME:override,override``): the defaults, the
paper (``experiment=paper``), the classical flow (``flow=dis``) and each of issue 24's additions switched off alone.

Per run: RPE (m, deg) and ATE (m) as run (6-DoF alignment; ``ate_7dof_m`` with the scale aligned too) and with every
relative translation rescaled to its true length (direction and rotation only:
:func:`dfvo.eval.error_decomposition.scale_free`), the predicted/true length ratio (mean, std), the trackers used and
the FPS. Every run's folder stays under ``--out``; the JSON (``OUT/panel.json``) is rewritten after each run, so an
interrupted panel keeps what it measured; the markdown table (``OUT/panel.md``) has one row per configuration and the
geometric mean over the cases.

    python studies/length_panel.py --out runs/length_panel                      # ~25 min on 2 cores
    python studies/length_panel.py --out runs/length_panel --configs default,paper --cases kitti07
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from dfvo.eval import evaluate_trajectory
from dfvo.eval.error_decomposition import scale_free
from dfvo.io.trajectory import read_kitti_poses
from dfvo.synthetic.trajectory import HANDHELD_SCENARIOS

ROOT = Path(__file__).resolve().parent.parent
KITTI_07_INTRINSICS = {"fx": 707.0912, "fy": 707.0912, "cx": 601.8873, "cy": 183.1104}  # calib.txt P0 of 07
HANDHELD_MARKERS_INTRINSICS = {"fx": 420.506712, "fy": 420.610940, "cx": 355.208298, "cy": 250.336787}  # its K.txt

CONFIGS: dict[str, list[str]] = {
    "default": [],
    "paper": ["experiment=paper"],
    "flow=dis": ["flow=dis"],
    "no road homography": ["tracker.road_alignment.enabled=false"],
    "no parallax rule (GRIC alone)": ["tracker.model_selection.min_parallax_px=null"],
    "PnP length unfiltered": ["tracker.scale.fuse_pnp=false"],
    "filter trusts its first observation": ["tracker.scale_filter.warmup_frames=0"],
    "network road plane as the height observation": ["tracker.road_plane.points=depth",
                                                     "tracker.road_alignment.enabled=false"],
    "window bundle adjustment (opt-in)": ["tracker.window.enabled=true"],
}
SCENARIOS = ("drive", "city", "straight", "highway")


def handheld_seeds(text: str | None) -> list[int]:
    """``--handheld-seeds``: comma-separated seeds (``1000,1001``) or a range ``1000-1003``; None or empty: none."""
    if not text:
        return []
    try:
        if "-" in text:
            lo, hi = (int(v) for v in text.split("-"))
            return list(range(lo, hi + 1))
        return [int(v) for v in text.split(",")]
    except ValueError:
        raise SystemExit(f"--handheld-seeds={text!r}; expected seeds like 1000,1001 or a range 1000-1003") from None


def cases(args: argparse.Namespace) -> dict[str, list[str]]:
    """Case name -> infer.py overrides."""
    kitti = f"data.root={args.kitti_root}"
    out = {"kitti06": ["data=kitti_odom", kitti, "seq=06"],
           "kitti06_step2": ["data=kitti_odom", kitti, "seq=06", "data.step=2"],
           "kitti06_step3": ["data=kitti_odom", kitti, "seq=06", "data.step=3"],
           "kitti07": ["data=kitti_odom", kitti, "seq=07"],
           "kitti07_step2": ["data=kitti_odom", kitti, "seq=07", "data.step=2"]}
    from dfvo.synthetic import held_out_worlds
    for world in held_out_worlds(SCENARIOS, 1):
        speed = "null" if world.speed is None else (f"{world.speed}" if isinstance(world.speed, float)
                                                     else f"[{world.speed[0]},{world.speed[1]}]")
        out[f"synthetic_{world.scenario}"] = ["data=synthetic", f"seq={world.scenario}", f"data.seed={world.seed}",
                                              f"data.num_frames={args.synthetic_frames}", f"data.speed={speed}"]
    shared = Path(args.kitti_root).parent
    if (shared / "kitti_raw_test" / "2011_09_26" / "2011_09_26_drive_0005_sync").is_dir():
        out["kitti_raw_0005"] = ["data=kitti_raw", f"data.root={shared / 'kitti_raw_test'}",
                                 "seq=2011_09_26_drive_0005_sync"]
    markers = shared / "handheld_markers"
    if (markers / "images").is_dir():  # a hand-held camera: its own motion model (experiment=handheld)
        intr = [f"data.{k}={v}" for k, v in HANDHELD_MARKERS_INTRINSICS.items()]
        out["handheld_markers"] = ["data=folder", f"data.root={markers / 'images'}", *intr,
                                   f"data.gt={markers / 'poses.txt'}", "data.gt_format=kitti", "experiment=handheld"]
    for seed in handheld_seeds(getattr(args, "handheld_seeds", None)):
        for scenario in HANDHELD_SCENARIOS:
            out[f"synthetic_{scenario}_s{seed}"] = ["data=synthetic", f"seq={scenario}", f"data.seed={seed}",
                                                    f"data.num_frames={args.synthetic_frames}"]
    if args.video:
        intr = [f"data.{k}={v}" for k, v in KITTI_07_INTRINSICS.items()]
        out["kitti07_video"] = ["data=video", f"data.path={args.video}", *intr,
                                f"data.gt={Path(args.kitti_root) / 'poses' / '07.txt'}", "data.gt_format=kitti"]
    return out


def parse_configs(text: str) -> dict[str, list[str]]:
    """``--configs``: names of :data:`CONFIGS` separated by ``,``, or ``NAME:override,override`` entries separated by
    ``;`` (also a single one); an override's own list value ``key=[a,b]`` stays whole. Name -> infer.py overrides."""
    configs: dict[str, list[str]] = {}
    for spec in filter(None, text.split(";" if ";" in text or ":" in text else ",")):
        name, sep, overrides = spec.partition(":")
        if sep:
            configs[name] = [o for o in re.split(r",(?![^\[]*\])", overrides) if o]  # not inside [a,b]
        elif name in CONFIGS:
            configs[name] = CONFIGS[name]
        else:
            raise SystemExit(f"--configs: unknown {name!r}; expected one of {list(CONFIGS)} or NAME:override,...")
    return configs


def make_video(kitti_root: str, path: str) -> None:
    """KITTI 07's left images as an H.264 file (PyAV, crf 18, 10 fps): what a user's dash camera would record."""
    import av
    from PIL import Image

    frames = sorted((Path(kitti_root) / "sequences" / "07" / "image_0").glob("*.png"))
    if not frames:
        raise SystemExit(f"--make-video: no images under {Path(kitti_root) / 'sequences' / '07' / 'image_0'}")
    first = np.asarray(Image.open(frames[0]).convert("RGB"))
    h, w = first.shape[0] // 2 * 2, first.shape[1] // 2 * 2  # yuv420p needs even sizes
    with av.open(path, "w") as container:
        stream = container.add_stream("libx264", rate=10, options={"crf": "18"})
        stream.width, stream.height, stream.pix_fmt = w, h, "yuv420p"
        for f in frames:
            img = np.ascontiguousarray(np.asarray(Image.open(f).convert("RGB"))[:h, :w])
            for packet in stream.encode(av.VideoFrame.from_ndarray(img, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)


def ground_truth(overrides: list[str]) -> np.ndarray:
    """(N,4,4) the poses of the frames ``infer.py`` runs with these overrides (the loader's own selection)."""
    from hydra import compose, initialize_config_module

    from dfvo.inference.config import register_configs, typed
    from dfvo.inference.frames import build_sequence

    register_configs()
    with initialize_config_module("dfvo.conf.infer", version_base="1.3"):
        cfg = typed(compose("infer", overrides=overrides))
    seq = build_sequence(cfg.data, cfg.seq, cfg.img_res)
    if seq.poses is None:
        raise SystemExit(f"no ground truth for {' '.join(overrides)}")
    return np.asarray(seq.poses, dtype=np.float64)


def metrics(gt: np.ndarray, pred: np.ndarray) -> dict[str, Any]:
    true_lengths, _, direction, ratio = scale_free(gt, pred)

    def m(traj: np.ndarray) -> dict[str, float]:
        r = evaluate_trajectory(gt, traj, align="6dof")
        r7 = evaluate_trajectory(gt, traj, align="7dof")
        return {"rpe_m": round(r["rpe_m"], 5), "rpe_deg": round(r["rpe_deg"], 5), "ate_m": round(r["ate_m"], 4),
                "ate_7dof_m": round(r7["ate_m"], 4)}

    return {"as_run": m(pred), "true_lengths": m(true_lengths),
            "length_ratio": {"mean": round(float(ratio.mean()), 4), "std": round(float(ratio.std()), 4)},
            "direction_error_deg_median": round(float(np.median(direction)), 4)}


def infer_overrides(case: list[str], config: list[str]) -> list[str]:
    """A case's ``infer.py`` overrides followed by a configuration's; a configuration that names an experiment
    replaces the case's own (``handheld_markers`` runs ``experiment=handheld`` otherwise)."""
    if any(o.startswith("experiment=") for o in config):
        case = [o for o in case if not o.startswith("experiment=")]
    return [*case, *config]


def run(name: str, case: list[str], config: list[str], out: Path, threads: int) -> dict[str, Any]:
    folder = out / name
    cmd = [sys.executable, str(ROOT / "infer.py"), *infer_overrides(case, config), f"out_dir={folder}",
           "progress=false", f"num_threads={threads}"]
    started = time.time()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    record: dict[str, Any] = {"command": " ".join(["python infer.py", *infer_overrides(case, config)]),
                              "wall_s": round(time.time() - started, 1)}
    if proc.returncode != 0:
        record["error"] = (proc.stderr.strip().splitlines() or ["(no output)"])[-1]
        return record
    summary = json.loads((folder / "summary.json").read_text())
    pred = read_kitti_poses(summary["pose_file"])
    gt = ground_truth(case)
    if len(gt) != len(pred):
        record["error"] = f"{len(pred)} poses written for {len(gt)} ground-truth frames"
        return record
    record.update(metrics(gt, pred))
    record["fps"] = round(summary["fps"], 2)
    record["trackers"] = summary["fallback"]["trackers"]
    record["constant_motion"] = summary["fallback"]["constant_motion"]
    motion = summary.get("motion") or {}
    record["motion"] = {k: motion.get(k) for k in ("motion", "judged_from_frame", "revised_from_frame")}
    record["camera_height"] = summary.get("camera_height")
    return record


def table(result: dict[str, Any], case_names: list[str]) -> str:
    """Rows: configurations; cells: RPE m as run / with true lengths; last column: geometric means."""
    head = ["configuration", *case_names, "geomean as run / true-length"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for cname, runs in result["runs"].items():
        cells, logs, logs_t = [], [], []
        for case in case_names:
            r = runs.get(case)
            if r is None or "error" in r:
                cells.append("—" if r is None else "error")
                continue
            a, t = r["as_run"]["rpe_m"], r["true_lengths"]["rpe_m"]
            cells.append(f"{a:.4f} / {t:.4f}")
            logs.append(math.log(max(a, 1e-9)))  # exact sources (the oracle) reach 0
            logs_t.append(math.log(max(t, 1e-9)))
        gm = (f"{math.exp(sum(logs) / len(logs)):.4f} / {math.exp(sum(logs_t) / len(logs_t)):.4f}"
              if logs else "—")
        lines.append("| " + " | ".join([cname, *cells, gm]) + " |")
    return "\n".join(lines)


def is_handheld_world(case: str) -> bool:
    """A synthetic hand-held world's case (``--handheld-seeds``)."""
    return case.startswith(tuple(f"synthetic_{w}_s" for w in HANDHELD_SCENARIOS))


def handheld_table(result: dict[str, Any], case_names: list[str]) -> str:
    """Rows: configurations; cells of the hand-held worlds: constant-motion frames, 7-DoF ATE (m), true-length RPE
    (m) and ``auto``'s verdict (``motion@judged/revised`` frame); last column: the constant-motion frames in all."""
    names = [c for c in case_names if is_handheld_world(c)]
    if not names:
        return ""
    head = ["configuration", *names, "constant motion in all"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for cname, runs in result["runs"].items():
        cells, total = [], 0
        for case in names:
            r = runs.get(case)
            if r is None or "error" in r or "constant_motion" not in r:
                cells.append("—" if r is None else "error")
                continue
            m = r["motion"]
            total += r["constant_motion"]
            cells.append(f"{r['constant_motion']} CM, {r['as_run']['ate_7dof_m']:.4f} / "
                         f"{r['true_lengths']['rpe_m']:.5f}, {m['motion']}@{m['judged_from_frame']}/"
                         f"{m['revised_from_frame']}")
        lines.append("| " + " | ".join([cname, *cells, str(total)]) + " |")
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", default="runs/length_panel")
    p.add_argument("--kitti-root", default=str(ROOT.parent / "shared" / "data" / "kitti_odom"))
    p.add_argument("--configs", default=",".join(CONFIGS),
                   help="names of CONFIGS separated by ',', or entries NAME:override,override separated by ';'")
    p.add_argument("--cases", default=None, help="comma-separated case names (default: all)")
    p.add_argument("--synthetic-frames", type=int, default=60)
    p.add_argument("--video", default=None, help="H.264 file of KITTI 07's frames (case kitti07_video)")
    p.add_argument("--make-video", action="store_true", help="write --video from the KITTI 07 images first")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--handheld-seeds", default=None,
                   help="the synthetic hand-held worlds (planar and corner) of these seeds, e.g. 1000-1003")
    args = p.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.make_video:
        if not args.video:
            raise SystemExit("--make-video: name the file with --video PATH")
        make_video(args.kitti_root, args.video)
    all_cases = cases(args)
    names = list(all_cases) if args.cases is None else args.cases.split(",")
    unknown = [n for n in names if n not in all_cases]
    if unknown:
        raise SystemExit(f"--cases: unknown {unknown}; expected some of {list(all_cases)}")
    configs = parse_configs(args.configs)
    path = out / "panel.json"
    result: dict[str, Any] = json.loads(path.read_text()) if path.exists() else {"runs": {}}
    result.update({"machine": f"{platform.machine()}, {os.cpu_count()} cores, {args.threads} torch threads",
                   "date": time.strftime("%Y-%m-%d"), "command": " ".join(["python", *sys.argv]),
                   "configs": {**result.get("configs", {}), **configs}})
    for cname, overrides in configs.items():
        for case in names:
            slug = f"{cname}/{case}".replace(" ", "_").replace("(", "").replace(")", "").replace("=", "-")
            record = run(slug, all_cases[case], overrides, out, args.threads)
            result["runs"].setdefault(cname, {})[case] = record
            path.write_text(json.dumps(result, indent=1))
            shown = record.get("error") or f"{record['as_run']['rpe_m']:.4f} m (true-length " \
                                            f"{record['true_lengths']['rpe_m']:.4f})"
            print(f"{cname:45s} {case:20s} {shown}", flush=True)
    text = table(result, [n for n in names if not is_handheld_world(n)])  # the worlds of a hand: handheld.md
    (out / "panel.md").write_text(text + "\n")
    print(text)
    hand = handheld_table(result, names)
    if hand:
        (out / "handheld.md").write_text(hand + "\n")
        print(hand)


if __name__ == "__main__":
    main()
