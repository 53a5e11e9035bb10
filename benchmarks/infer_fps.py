"""End-to-end inference speed: frames per second of infer.py's loop and where the time goes.

Runs :func:`dfvo.inference.pipeline.run_inference` in-process (the same code as ``python infer.py``) and prints
one JSON object: resolution, sources, frames, ``fps`` (frame pairs per wall second, everything included; with
``--repeat N`` the best of N runs, each run's in ``fps_runs``), ``fps_without_loading`` (excluding the main thread's
frame reading / synthetic rendering, which is what a camera stream pays), ``timing_ms_per_frame`` per stage (load,
flow, refine, depth, tracker, the tracker's own split into selection / E-tracker / sequential part, and the
``wait_*`` stages of the overlapped loop: stages run in three threads, so they overlap and their sum can exceed
``1000 / fps``), ``cpu_ms_per_frame`` (process CPU time: ``loop``, everything per frame, and each stage; it follows
the work, not a shared machine's load: compare it in the serial loop, ``--overlap none`` or ``load``),
``thread_cpu_ms_per_frame`` (each stage's CPU time in the thread that ran it: with ``overlap=full`` on two cores, one
torch thread per busy thread, it is the stage's own work while the threads overlap), ``refine_cut`` (``overlap=full``:
where the refinement was cut between the two threads, dfvo/inference/refine_split.py),
``work_per_frame`` (load-independent counts: refined pixel-iterations, network input pixels,
correspondences), the RPE/ATE of the run, the runtime that ran each network (``runtime``: torch, onnxruntime,
openvino), torch threads, machine and the 1-minute load average before and after (the machine may be shared: compare
variants back to back, and trust the work counts over the clock).

Default: KITTI odometry 07, all frames, the shipped networks (``--root``: ``$DFVO_KITTI_ODOM_ROOT``, else
``../shared/data/kitti_odom`` beside the repository).

``--compare A B``: two configurations (each a quoted list of infer.py overrides, ``""`` for the defaults) run back
to back in one process: one short warm-up run of each (``--warmup-frames``, not reported), then ``--rounds`` rounds
in alternating order (A B, B A, ...), so both see the same machine load. Prints ``{"compare": {A: report, B:
report}, "fps_ratio": median over rounds of FPS(B) / FPS(A), "fps_ratio_rounds": [...], "cpu_ratio": the same for
the loop's CPU ms per frame}``; each report is the fastest of its rounds, with every round's FPS in ``fps_runs``.
On a shared machine the ratio is the number to quote.

Sources:
    --sources oracle          true flow/depth of the synthetic world (their time is the renderer's)
    --sources network         checkpoints given by --flow-ckpt / --depth-ckpt (default)
    --sources random-network  FlowNet/DepthNet with random weights (speed only: the poses are meaningless)

Usage: python benchmarks/infer_fps.py [--frames N] [--height 192] [--width 640] [--threads 2]
       [--sources oracle|network|random-network] [--data synthetic|kitti_odom --root ROOT --seq 07]
       [--repeat N] [--overlap none|load|full|auto] [--no-overlap] [--device cpu|cuda|auto]
       [--overrides flow.refine.iterations=5 ...] [--compare "A overrides" "B overrides" [--rounds 2]]

KITTI 07 with the defaults (issue 27's figure), and PyTorch against OpenVINO back to back:

    OMP_NUM_THREADS=2 python benchmarks/infer_fps.py
    OMP_NUM_THREADS=2 python benchmarks/infer_fps.py --compare "runtime=torch" "runtime=openvino"
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import statistics
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

import dfvo.inference.pipeline as pipeline
from dfvo.inference.config import InferConfig, OverlapMode
from dfvo.inference.pipeline import run_inference
from dfvo.inference.timing import StageTimer

REPO = Path(__file__).resolve().parents[1]
KITTI_ODOM = os.environ.get("DFVO_KITTI_ODOM_ROOT") or str(REPO.parent / "shared" / "data" / "kitti_odom")


def _random_checkpoints(folder: Path, variant: str) -> tuple[Path, Path]:
    from safetensors.torch import save_file

    from dfvo.models.depth_net import DepthNet
    from dfvo.models.flow_net import FlowNet

    flow, depth = folder / "flow.safetensors", folder / "depth.safetensors"
    save_file({k: v.contiguous() for k, v in FlowNet(variant).state_dict().items()}, str(flow),
              metadata={"variant": variant})
    save_file({k: v.contiguous() for k, v in DepthNet().state_dict().items()}, str(depth))
    return flow, depth


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=None, help="frames (default: all of a KITTI sequence, 20 "
                   "synthetic)")
    p.add_argument("--height", type=int, default=192)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--batch-size", type=int, default=4)
    p.add_argument("--sources", choices=["oracle", "network", "random-network", "dis"], default="network")
    p.add_argument("--flow-ckpt", default="checkpoints/flow.safetensors")
    p.add_argument("--depth-ckpt", default="checkpoints/depth.safetensors")
    p.add_argument("--flow-variant", default="default")
    p.add_argument("--depth-scale", type=float, default=1.0)
    p.add_argument("--data", default="kitti_odom")
    p.add_argument("--root", default=None, help=f"dataset root (kitti_odom default: {KITTI_ODOM})")
    p.add_argument("--seq", default=None, help="sequence (kitti_odom default: 07)")
    p.add_argument("--overrides", nargs="*", default=[], help="extra infer.yaml overrides (tracker=pnp ...)")
    p.add_argument("--repeat", type=int, default=1, help="runs; the fastest is reported (each in fps_runs)")
    p.add_argument("--overlap", choices=[m.value for m in OverlapMode], default=None,
                   help=f"loop threads (infer.py overlap=); default {InferConfig.overlap.value!r}")
    p.add_argument("--no-overlap", action="store_true", help="the serial loop: --overlap none")
    p.add_argument("--device", default="cpu", help="cpu | cuda | auto")
    p.add_argument("--compare", nargs=2, default=None, metavar=("A", "B"),
                   help="two quoted override lists run back to back, alternating (see the module docstring)")
    p.add_argument("--rounds", type=int, default=2, help="--compare: rounds of A and B (alternating order)")
    p.add_argument("--warmup-frames", type=int, default=9, help="--compare: frames of each warm-up run")
    args = p.parse_args()
    if args.data == "kitti_odom":
        args.root = args.root or KITTI_ODOM
        args.seq = args.seq or "07"
    elif args.frames is None:
        args.frames = 20
    torch.set_num_threads(args.threads)
    args.overlap = "none" if args.no_overlap else (args.overlap or InferConfig.overlap.value)
    load_before = os.getloadavg()[0]
    if args.compare:
        print(json.dumps(_compare(args, load_before), indent=2))
        return
    runs = [_run_once(args) for _ in range(max(1, args.repeat))]
    summary, cfg = max(runs, key=lambda r: r[0]["fps"])
    print(json.dumps(_report(args, summary, cfg, [r[0]["fps"] for r in runs], load_before), indent=2))


def _compare(args: argparse.Namespace, load_before: float) -> dict[str, object]:
    """Configurations A and B back to back: a warm-up run of each, then alternating rounds (A B, B A, ...)."""
    names = list(args.compare)
    extra = {name: shlex.split(name) for name in names}
    base = list(args.overrides)

    def run(name: str, frames: int | None) -> tuple[dict, object]:
        ns = argparse.Namespace(**{**vars(args), "overrides": base + extra[name], "frames": frames})
        return _run_once(ns)

    for name in names:  # warm-up: exports, caches, first-touch allocations; not reported
        run(name, args.warmup_frames)
    runs: dict[str, list[tuple[dict, object]]] = {name: [] for name in names}
    for r in range(max(1, args.rounds)):
        for name in (names if r % 2 == 0 else names[::-1]):
            runs[name].append(run(name, args.frames))
    a, b = (runs[n] for n in names)
    fps_ratios = [rb[0]["fps"] / ra[0]["fps"] for ra, rb in zip(a, b)]
    cpu_ratios = [rb[0]["cpu_ms_per_frame"]["loop"] / ra[0]["cpu_ms_per_frame"]["loop"] for ra, rb in zip(a, b)]
    reports = {}
    for name in names:
        summary, cfg = max(runs[name], key=lambda r: r[0]["fps"])
        args_n = argparse.Namespace(**{**vars(args), "overrides": base + extra[name]})
        reports[name] = _report(args_n, summary, cfg, [r[0]["fps"] for r in runs[name]], load_before)
    return {"compare": reports, "order": names, "rounds": max(1, args.rounds),
            "fps_ratio": round(statistics.median(fps_ratios), 3), "fps_ratio_rounds": [round(x, 3) for x in fps_ratios],
            "cpu_ratio": round(statistics.median(cpu_ratios), 3), "cpu_ratio_rounds": [round(x, 3) for x in cpu_ratios],
            "load_avg_before": round(load_before, 2), "load_avg_after": round(os.getloadavg()[0], 2)}


class _LoopMeter:
    """Wraps the pipeline's ``track_sequence``: keeps the run's StageTimer and the process CPU seconds of the loop
    (everything per frame, the per-frame outputs included; not the start-up or the final report)."""

    def __init__(self) -> None:
        self.timer: StageTimer | None = None
        self.cpu_seconds = 0.0
        self.original = pipeline.track_sequence

    def __call__(self, *args: object, **kwargs: object) -> Iterator[object]:
        self.timer = kwargs["timer"]
        start = time.process_time()
        try:
            yield from self.original(*args, **kwargs)
        finally:
            self.cpu_seconds = time.process_time() - start


def _run_once(args: argparse.Namespace) -> tuple[dict, object]:
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        ov = [f"data={args.data}", f"img_res.height={args.height}", f"img_res.width={args.width}",
              f"out_dir={tmp / 'out'}", "progress=false", f"batch_size={args.batch_size}",
              f"num_threads={args.threads}", f"device={args.device}", f"overlap={args.overlap}"]
        if args.data == "synthetic":
            ov.append(f"data.num_frames={args.frames}")
        else:
            ov += [f"data.root={args.root}"] + ([] if args.frames is None else [f"data.end={args.frames}"])
        if args.seq is not None:
            ov.append(f"seq={args.seq}")
        if args.sources == "oracle":  # explicit: the default `auto` would pick the shipped checkpoints
            ov += ["flow=oracle", "depth=oracle"]
        elif args.sources == "dis":  # the classical flow (OpenCV DIS) with the depth network
            ov += ["flow=dis", "depth=network", f"depth.checkpoint={args.depth_ckpt}",
                   f"depth.depth_scale={args.depth_scale}"]
        else:
            flow, depth = ((args.flow_ckpt, args.depth_ckpt) if args.sources == "network"
                           else _random_checkpoints(tmp, args.flow_variant))
            ov += ["flow=network", "depth=network", f"flow.checkpoint={flow}", f"depth.checkpoint={depth}",
                   f"depth.depth_scale={args.depth_scale}"]
        with initialize_config_dir(config_dir=str(REPO / "dfvo" / "conf" / "infer"), version_base="1.3"):
            cfg = compose("infer", overrides=ov + list(args.overrides))
        meter = _LoopMeter()
        pipeline.track_sequence = meter
        try:
            summary = run_inference(cfg)
        finally:
            pipeline.track_sequence = meter.original
    frames = max(int(summary["frames"]) - 1, 1)  # tracked frames
    summary["cpu_ms_per_frame"] = {"loop": round(1000.0 * meter.cpu_seconds / frames, 2),
                                   **{k: round(v, 2) for k, v in meter.timer.cpu_ms_per_frame(frames).items()}}
    summary["thread_cpu_ms_per_frame"] = {k: round(v, 2)
                                          for k, v in meter.timer.thread_cpu_ms_per_frame(frames).items()}
    return summary, cfg


def _work(cfg: object, summary: dict) -> dict[str, object]:
    """Load-independent work per frame: refined pixel-iterations (forward and backward), network input sizes."""
    h, w = int(cfg.img_res.height), int(cfg.img_res.width)
    refine = summary.get("sources", {}).get("flow_refinement")
    return {
        "refine_pixel_iterations": 0 if not refine else 2 * h * w * int(refine["iterations"]),
        "refine_method": None if not refine else str(refine.get("method", "symmetric")),
        "correspondences": int(cfg.tracker.correspondence.num_correspondences),
        "working_pixels": h * w,
    }


def _report(args: argparse.Namespace, summary: dict, cfg: object, fps_runs: list[float],
            load_before: float) -> dict[str, object]:
    timing = summary["timing_ms_per_frame"]
    per_frame_ms = 1000.0 / summary["fps"]
    overlap = summary.get("overlap", args.overlap)  # the mode that ran (``auto`` resolved)
    loading_ms = timing.get("load", 0.0) if overlap == "none" else timing.get("wait_load", 0.0)
    metrics = summary.get("metrics") or {}
    return {
        "data": args.data, "sources": args.sources, "resolution": [args.height, args.width],
        "frames": summary["frames"], "fps": round(summary["fps"], 3), "fps_runs": [round(f, 3) for f in fps_runs],
        "overlap": overlap, "device": summary.get("device"), "refine_cut": summary.get("refine_cut"),
        "fps_without_loading": round(1000.0 / max(per_frame_ms - loading_ms, 1e-9), 3),
        "timing_ms_per_frame": {k: round(v, 2) for k, v in timing.items()},
        "cpu_ms_per_frame": summary["cpu_ms_per_frame"],
        "thread_cpu_ms_per_frame": summary["thread_cpu_ms_per_frame"],
        "work_per_frame": _work(cfg, summary),
        "rpe_m": metrics.get("rpe_m"), "rpe_deg": metrics.get("rpe_deg"), "ate_m": metrics.get("ate_m"),
        "runtime": {k: summary.get("sources", {}).get(f"{k}_runtime") for k in ("flow", "depth")},
        "overrides": list(args.overrides),
        "fallback": summary["fallback"], "torch_threads": torch.get_num_threads(),
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "load_avg_before": round(load_before, 2), "load_avg_after": round(os.getloadavg()[0], 2),
    }


if __name__ == "__main__":
    main()
