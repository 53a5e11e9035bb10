"""GPU check (issue 15): the batched inference, one training step per network, and CPU-vs-GPU agreement, as JSON.

Sections (each guarded: a failing section records its error and the others still run; exit status 1 if any failed):

    env        torch / CUDA / device / CPU facts
    audit      one batch through the inference loop on the device: where each output lives (flow, depth, poses,
               correspondences) and, on CUDA, where the host synchronises (torch's sync-debug warnings, by line)
    infer      KITTI 06 (``--kitti-root``, else the synthetic drive) with the default configuration at 640x192 for
               each ``--batches`` size: FPS of the overlapped loop (second of two runs, so start-up and autotuning
               are excluded) and ms per stage from a serial run with CUDA synchronised at every stage boundary
    agreement  the same sequence on the CPU (tracker seeds 0 and 1: the RANSAC noise level) and on the device
               (seed 0): RPE of each, their difference against the seed noise, trackers used
    train      a few optimiser steps of a depth (depth_stereo) and a flow (flow_supervised) network at 640x192 on
               the synthetic world (rendered on the device): it/s of the steps, peak memory

Usage:
    python benchmarks/gpu_check.py [--device auto|cuda|cpu] [--quick] [--out gpu_check.json]
        [--kitti-root ROOT] [--batches 16 64] [--sections env audit infer agreement train]
    python -m benchmarks.gpu_check ...     (the same from the root of a checkout where dfvo is not installed)

``--quick`` (for a CPU): 96x320, 9 frames, batch 4, 2+2 training steps at 64x128: checks every path runs.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
import traceback
import warnings
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import torch
from hydra import compose, initialize_config_dir

import dfvo.inference.loop as loop
from dfvo.inference.assembly import resolve_device
from dfvo.inference.config import typed
from dfvo.inference.pipeline import run_inference

REPO = Path(__file__).resolve().parents[1]
DEFAULT_KITTI = REPO.parent / "shared" / "data" / "kitti_odom"


def _device(name: str) -> str:
    try:
        return resolve_device(name)
    except ValueError as err:
        raise SystemExit(f"--device {name}: {err}") from None


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def _infer_cfg(args: argparse.Namespace, device: str, out: Path, batch: int, *extra: str) -> Any:
    h, w = (96, 320) if args.quick else (192, 640)
    ov = [f"img_res.height={h}", f"img_res.width={w}", f"out_dir={out}", "progress=false", f"batch_size={batch}",
          f"device={device}", "flow=network", "depth=network"]
    if args.kitti_root and Path(args.kitti_root, "sequences", "06").is_dir():
        ov += ["data=kitti_odom", f"data.root={args.kitti_root}", "seq=06", f"data.end={args.frames}"]
    else:
        ov += ["data=synthetic", f"data.num_frames={args.frames}"]
    with initialize_config_dir(config_dir=str(REPO / "dfvo" / "conf" / "infer"), version_base="1.3"):
        return compose("infer", overrides=ov + list(extra))


def section_env(args: argparse.Namespace, device: str) -> dict[str, Any]:
    out: dict[str, Any] = {"torch": torch.__version__, "cuda_available": torch.cuda.is_available(),
                           "device": device, "python": platform.python_version(), "cpu_count": os.cpu_count(),
                           "torch_threads": torch.get_num_threads(), "quick": args.quick}
    if device.startswith("cuda"):
        p = torch.cuda.get_device_properties(torch.device(device))
        out.update(gpu=p.name, capability=f"{p.major}.{p.minor}", gpu_memory_gib=round(p.total_memory / 2**30, 1),
                   cuda=torch.version.cuda, cudnn=torch.backends.cudnn.version())
    return out


def section_audit(args: argparse.Namespace, device: str) -> dict[str, Any]:
    """One batch through the loop on the device: where the outputs live, and where the host synchronises."""
    from omegaconf import DictConfig

    from dfvo.inference.frames import build_sequence
    from dfvo.inference.timing import StageTimer
    from dfvo.sources import build_depth_source, build_flow_source
    from dfvo.tracking import VisualOdometry

    with tempfile.TemporaryDirectory() as tmp:
        cfg = typed(_infer_cfg(args, device, Path(tmp), 4))
    data = typed(cfg.data) if isinstance(cfg.data, DictConfig) else cfg.data
    seq = build_sequence(data, cfg.seq, cfg.img_res)
    flow_src = build_flow_source(cfg.flow, seq.world, device)
    depth_src = build_depth_source(cfg.depth, seq.world, device)
    vo = VisualOdometry(cfg.tracker)
    syncs: Counter[str] = Counter()
    cuda = device.startswith("cuda")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        if cuda:
            torch.cuda.set_sync_debug_mode("warn")
        try:
            records = []
            for record in loop.track_sequence(seq, flow_src, depth_src, vo, refine=cfg.flow.refine, batch_size=4,
                                              timer=StageTimer(), device=device, overlap=False):
                records.append(record)
                if len(records) == 4:
                    break
        finally:
            if cuda:
                torch.cuda.set_sync_debug_mode(0)
    for w in caught:
        if "synchroniz" in str(w.message).lower():
            syncs[f"{Path(w.filename).name}:{w.lineno}"] += 1
    r = records[-1]
    m = r.result.matches
    return {
        "frames": len(records),
        "devices": {"image": str(r.image.device), "flow_fwd": str(r.flow_fwd.device),
                    "flow_bwd": str(r.flow_bwd.device), "depth_prev": str(r.depth_prev.device),
                    "T_w_cur": str(r.result.T_w_cur.device),
                    "correspondences": None if m is None else str(m.pts_prev.device)},
        "trackers": [rec.result.diagnostics.tracker.value for rec in records],
        "host_syncs_in_4_frames": sum(syncs.values()) if cuda else None,
        "host_sync_sites": dict(syncs.most_common(20)) if cuda else None,
    }


def _run(cfg: Any) -> dict[str, Any]:
    return run_inference(cfg)


def section_infer(args: argparse.Namespace, device: str) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for batch in args.batches:
        with tempfile.TemporaryDirectory() as tmp:
            runs = [_run(_infer_cfg(args, device, Path(tmp) / f"run{k}", batch, "overlap=full")) for k in range(2)]
            staged = _run(_infer_cfg(args, device, Path(tmp) / "staged", batch, "overlap=none", "cuda_sync=true"))
        s = runs[-1]
        out[f"batch_{batch}"] = {
            "frames": s["frames"], "fps": round(s["fps"], 2), "fps_first_run": round(runs[0]["fps"], 2),
            "fps_serial_synchronised": round(staged["fps"], 2),
            "ms_per_frame_by_stage": {k: round(v, 2) for k, v in staged["timing_ms_per_frame"].items()},
            "rpe_m": (s.get("metrics") or {}).get("rpe_m"), "fallback": s["fallback"]["trackers"],
            "peak_gpu_memory_gib": round(torch.cuda.max_memory_allocated() / 2**30, 2) if device != "cpu" else None,
        }
    return out


def _trajectory(summary: dict[str, Any]) -> np.ndarray:
    from dfvo.io.trajectory import read_kitti_poses

    return read_kitti_poses(summary["pose_file"])


def section_agreement(args: argparse.Namespace, device: str) -> dict[str, Any]:
    batch = min(args.batches)
    res = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, dev, seed in (("cpu_seed0", "cpu", 0), ("cpu_seed1", "cpu", 1), ("device_seed0", device, 0)):
            s = _run(_infer_cfg(args, dev, Path(tmp) / name, batch, f"tracker.seed={seed}"))
            res[name] = {"rpe_m": (s.get("metrics") or {}).get("rpe_m"), "trackers": s["fallback"]["trackers"],
                         "positions": _trajectory(s)[:, :3, 3]}
    cpu, other, dev = res["cpu_seed0"], res["cpu_seed1"], res["device_seed0"]
    noise = abs(cpu["rpe_m"] - other["rpe_m"]) if cpu["rpe_m"] is not None else None
    diff = abs(cpu["rpe_m"] - dev["rpe_m"]) if cpu["rpe_m"] is not None else None
    return {
        "rpe_m": {k: v["rpe_m"] for k, v in res.items()},
        "trackers": {k: v["trackers"] for k, v in res.items()},
        "rpe_seed_noise_m": noise, "rpe_device_vs_cpu_m": diff,
        "max_position_difference_m": float(np.abs(cpu["positions"] - dev["positions"]).max()),
        "agrees": None if diff is None else bool(diff <= max(0.005, 2.0 * noise)),
        "rule": "agrees when |RPE(device) - RPE(cpu)| <= max(0.005 m, 2 x |RPE(cpu, seed 0) - RPE(cpu, seed 1)|)",
    }


def _train_steps(args: argparse.Namespace, device: str, model: str) -> dict[str, Any]:
    import lightning as L

    from dfvo.training.config import register_configs
    from dfvo.training.datamodule import DFVODataModule
    from dfvo.training.runner import build_module, build_trainer

    register_configs()
    cuda = device.startswith("cuda")
    h, w = (64, 128) if args.quick else (192, 640)
    batch = args.train_batch or (8 if cuda else 1)
    warm, steps = (2, 2) if args.quick else (3, 10)

    class StepTimer(L.Callback):
        def __init__(self) -> None:
            self.times: list[float] = []
            self.start = 0.0

        def on_train_batch_start(self, trainer: Any, module: Any, batch: Any, batch_idx: int) -> None:
            _sync(device)
            if batch_idx == warm and cuda:
                torch.cuda.reset_peak_memory_stats()
            self.start = time.perf_counter()

        def on_train_batch_end(self, trainer: Any, module: Any, outputs: Any, batch: Any, batch_idx: int) -> None:
            _sync(device)
            self.times.append(time.perf_counter() - self.start)

    with tempfile.TemporaryDirectory() as tmp:
        ov = [f"model={model}", "data=synthetic", f"data.height={h}", f"data.width={w}", f"data.batch_size={batch}",
              "data.seeds=[0]", f"data.num_frames={max(8, batch * (warm + steps) + 2)}", "data.val_seeds=[]",
              f"data.device={'cuda' if cuda else 'cpu'}", f"trainer={'gpu' if cuda else 'default'}",
              f"trainer.max_steps={warm + steps}", "trainer.enable_progress_bar=false", "trainer.logger=false",
              "trainer.export_weights=false", "trainer.validate_at_stop=false", "model.monitor=null",
              f"runs_dir={tmp}", "name=step"]
        if not cuda:
            ov.append("trainer.accelerator=cpu")
        with initialize_config_dir(config_dir=str(REPO / "dfvo" / "conf" / "train"), version_base="1.3"):
            cfg = compose("train", overrides=ov)
        datamodule = DFVODataModule(cfg)
        module = build_module(cfg)
        trainer = build_trainer(cfg, Path(tmp) / "step", has_validation=False)
        timer = StepTimer()
        trainer.callbacks.append(timer)
        trainer.fit(module, datamodule=datamodule)
    measured = timer.times[warm:]
    return {"size": [h, w], "batch": batch, "precision": str(trainer.precision), "steps_measured": len(measured),
            "it_per_s": round(len(measured) / sum(measured), 3) if measured else None,
            "samples_per_s": round(batch * len(measured) / sum(measured), 2) if measured else None,
            "peak_gpu_memory_gib": round(torch.cuda.max_memory_allocated() / 2**30, 2) if cuda else None}


def section_train(args: argparse.Namespace, device: str) -> dict[str, Any]:
    out = {}
    for model in ("depth_stereo", "flow_supervised"):
        try:
            out[model] = _train_steps(args, device, model)
        except Exception as err:  # one model failing must not hide the other's numbers
            out[model] = {"error": f"{type(err).__name__}: {err}", "traceback": traceback.format_exc()[-3000:]}
    if any("error" in v for v in out.values()):
        raise RuntimeError(json.dumps(out))
    return out


SECTIONS = {"env": section_env, "audit": section_audit, "infer": section_infer, "agreement": section_agreement,
            "train": section_train}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="auto", help="auto | cuda | cuda:N | cpu")
    p.add_argument("--quick", action="store_true", help="small sizes and few frames/steps (a CPU test of the paths)")
    p.add_argument("--out", default="gpu_check.json")
    p.add_argument("--kitti-root", default=os.environ.get("DFVO_KITTI_ODOM_ROOT") or str(DEFAULT_KITTI))
    p.add_argument("--batches", type=int, nargs="+", default=None, help="inference batch sizes (default 16 64)")
    p.add_argument("--frames", type=int, default=None, help="frames of the sequence (default 51; quick 9)")
    p.add_argument("--train-batch", type=int, default=None, help="training batch (default 8 on CUDA, 1 on CPU)")
    p.add_argument("--sections", nargs="+", default=list(SECTIONS), choices=list(SECTIONS))
    args = p.parse_args()
    args.batches = args.batches or ([4] if args.quick else [16, 64])
    args.frames = args.frames or (9 if args.quick else 51)
    device = _device(args.device)
    if device.startswith("cuda"):
        torch.backends.cudnn.benchmark = True
    report: dict[str, Any] = {"date": time.strftime("%Y-%m-%d %H:%M:%S"), "sections": args.sections}
    failed = []
    for name in args.sections:
        start = time.perf_counter()
        try:
            report[name] = SECTIONS[name](args, device)
        except Exception as err:
            failed.append(name)
            report[name] = {"error": f"{type(err).__name__}: {err}"[:3000], "traceback": traceback.format_exc()[-3000:]}
        report.setdefault("seconds", {})[name] = round(time.perf_counter() - start, 1)
        Path(args.out).write_text(json.dumps(report, indent=2, default=str))  # partial results survive a timeout
    report["failed_sections"] = failed
    Path(args.out).write_text(json.dumps(report, indent=2, default=str))
    print(json.dumps(report, indent=2, default=str))
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
