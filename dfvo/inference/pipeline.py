"""One inference run: build the sequence, the sources and the tracker from the typed config, run the loop
(:mod:`dfvo.inference.loop`), write every frame's pose and diagnostics as it comes (:mod:`dfvo.inference.outputs`),
and finish with metrics, plots and the summary (:mod:`dfvo.inference.report`).

An interrupted run (Ctrl-C, SIGTERM) still finishes: the poses written so far are evaluated and plotted, and
``summary.json`` says ``partial``; then :class:`RunInterrupted` tells the command line to exit with 128 + signal.
"""

from __future__ import annotations

import logging
import signal
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig

from dfvo.eval.trajectory_io import TrajectoryWriter
from dfvo.inference.config import InferConfig, PoseFormat, typed
from dfvo.inference.frames import build_sequence
from dfvo.inference.loop import FrameRecord, track_sequence
from dfvo.inference.outputs import FramesCsv, prepare_out_dir
from dfvo.inference.report import finish_run
from dfvo.inference.timing import StageTimer
from dfvo.sources import NetworkFlow, build_depth_source, build_flow_source, check_sources
from dfvo.tracking import VisualOdometry
from dfvo.tracking.diagnostics import FrameDiagnostics, TrackerUsed

__all__ = ["RunInterrupted", "run_inference", "job_output_dir"]

log = logging.getLogger("dfvo.infer")


class RunInterrupted(KeyboardInterrupt):
    """The run was stopped by a signal after its partial outputs were written; ``signum`` says which."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def job_output_dir(cfg: InferConfig) -> Path:
    """The folder this job writes to: Hydra's job folder when running under Hydra (``out_dir`` for a single run, a
    subfolder of it named by the job's overrides with ``-m``), else ``cfg.out_dir``."""
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized():
        return Path(HydraConfig.get().runtime.output_dir)
    return prepare_out_dir(cfg.out_dir)


def resolve_device(name: str) -> str:
    """``auto`` -> ``cuda`` when torch sees a CUDA device, else ``cpu``; other names as given.

    Raises:
        ValueError: a ``cuda`` device asked for where torch sees none (one line saying what to use instead).
    """
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device={name}: CUDA is not available on this machine; use device=cpu or device=auto")
    return name


class _SignalsToInterrupt:
    """While active, SIGTERM (and SIGINT) raise :class:`RunInterrupted` in the main thread."""

    def __enter__(self) -> _SignalsToInterrupt:
        self.previous: dict[int, Any] = {}
        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                self.previous[sig] = signal.signal(sig, self._raise)
            except ValueError:  # not the main thread: keep the defaults
                pass
        return self

    @staticmethod
    def _raise(signum: int, frame: Any) -> None:
        raise RunInterrupted(signum)

    def __exit__(self, *exc: Any) -> None:
        for sig, handler in self.previous.items():
            signal.signal(sig, handler)


def run_inference(cfg: DictConfig | InferConfig) -> dict[str, Any]:
    """Run DF-VO on one sequence and write its outputs.

    Args:
        cfg: the composed config of ``infer.py`` (a DictConfig of :class:`InferConfig`, or the dataclass).

    Returns:
        The summary (also ``OUT/summary.json``): sequence, frames, fps, timing, fallbacks, metrics.

    Raises:
        RunInterrupted: after writing the partial outputs of a run stopped by SIGINT/SIGTERM.
        ValueError, OSError (and subclasses such as CheckpointError, DatasetError): bad settings or data, with a
            one-line message.
    """
    icfg: InferConfig = cfg if isinstance(cfg, InferConfig) else typed(cfg)
    out = prepare_out_dir(job_output_dir(icfg))  # before the (slow) sources: a bad out_dir fails at once
    if icfg.num_threads:
        torch.set_num_threads(int(icfg.num_threads))
    device = resolve_device(icfg.device)
    seq = build_sequence(typed(icfg.data) if isinstance(icfg.data, DictConfig) else icfg.data, icfg.seq,
                         icfg.img_res)
    if seq.length < 2:
        raise ValueError(f"sequence {seq.name} has {seq.length} frame(s); expected at least 2")
    check_sources(icfg.flow, icfg.depth, seq.world)  # every missing checkpoint in one error, before loading any
    flow_src = build_flow_source(icfg.flow, seq.world, device)
    depth_src = build_depth_source(icfg.depth, seq.world, device)
    refine = icfg.flow.refine if isinstance(flow_src, NetworkFlow) and icfg.flow.refine.iterations > 0 else None
    finetuner = None
    if icfg.online_finetune:
        if not isinstance(flow_src, NetworkFlow):
            raise ValueError(f"online_finetune=true needs flow=network (flow={flow_src.name} cannot be finetuned)")
        if flow_src.runtime != "torch":
            raise ValueError(f"online_finetune=true needs flow.runtime.kind=torch (flow.runtime.kind="
                             f"{flow_src.runtime} runs an exported copy of the network, which finetuning would not "
                             "update)")
        from dfvo.training.online_flow import OnlineFlowFinetuner

        finetuner = OnlineFlowFinetuner(flow_src.model, icfg.online)
    observers = _observers(icfg, out, seq)
    extra = {"sources": {"flow": flow_src.name, "depth": depth_src.name,
                         "flow_checkpoint": str(getattr(flow_src, "checkpoint", "")) or None,
                         "depth_checkpoint": str(getattr(depth_src, "checkpoint", "")) or None,
                         "flow_refinement": None if refine is None else asdict(refine),
                         "flow_runtime": getattr(flow_src, "runtime", None),
                         "depth_runtime": getattr(depth_src, "runtime", None)},
             "online_finetune": finetuner is not None, "device": device}
    return _run(icfg, seq, flow_src, depth_src, refine, finetuner, observers, out, device, extra)


def _observers(cfg: InferConfig, out: Path, seq: Any) -> list[Any]:
    """The per-frame loggers the config asks for (TensorBoard, the Rerun recording)."""
    observers: list[Any] = []
    if cfg.viewer.kind not in ("none", "rerun"):
        raise ValueError(f"viewer.kind={cfg.viewer.kind!r}; expected 'none' or 'rerun' (viewer=none|rerun)")
    if cfg.viewer.kind == "rerun":
        from dfvo.inference.rerun_observer import RerunObserver

        hw = tuple(seq.image(0).shape[-2:])
        observers.append(RerunObserver(out / "run.rrd", seq.K, hw, gt_poses=seq.poses, spawn=cfg.viewer.spawn))
    if cfg.tensorboard.enabled:
        from dfvo.inference.tb_logging import TensorboardObserver

        observers.append(TensorboardObserver(out / "tensorboard", cfg.tensorboard.every))
    return observers


def _run(cfg: InferConfig, seq: Any, flow_src: Any, depth_src: Any, refine: Any, finetuner: Any,
         observers: list[Any], out: Path, device: str, extra: dict[str, Any]) -> dict[str, Any]:
    from tqdm import tqdm

    vo = VisualOdometry(cfg.tracker)
    timer = StageTimer()
    pose_file = out / f"{seq.name}.txt"
    if cfg.pose_format == PoseFormat.tum and seq.timestamps is None:
        raise ValueError(f"pose_format=tum needs the frames' timestamps and {seq.name} has none (data.times=FILE "
                         "for a folder of frames); use pose_format=kitti")
    poses, table = TrajectoryWriter(pose_file, cfg.pose_format.value), FramesCsv(out / "frames.csv")
    trajectory = [np.eye(4)]
    diagnostics: list[FrameDiagnostics] = []
    poses.write(trajectory[0], _stamp(seq, 0))
    table.write(FrameDiagnostics(frame=0, tracker=TrackerUsed.init))
    bar = tqdm(total=seq.length - 1, desc=f"dfvo {seq.name}", unit="frame", disable=not cfg.progress)
    stopped: RunInterrupted | None = None
    start = time.perf_counter()
    try:
        with _SignalsToInterrupt():
            for record in track_sequence(seq, flow_src, depth_src, vo, refine=refine, batch_size=cfg.batch_size,
                                         timer=timer, device=device, finetuner=finetuner):
                _write_frame(record, poses, table, trajectory, diagnostics, observers, _stamp(seq, record.index))
                bar.update(1)
                bar.set_postfix(fps=f"{len(diagnostics) / (time.perf_counter() - start):.2f}")
    except RunInterrupted as err:
        stopped = err
    except KeyboardInterrupt:
        stopped = RunInterrupted(signal.SIGINT)
    finally:
        bar.close()
        poses.close()
        table.close()
        for obs in observers:
            obs.close()
    wall = time.perf_counter() - start
    if stopped is not None:
        log.warning("interrupted by %s: %s holds the first %d of %d poses; writing partial results",
                    signal.Signals(stopped.signum).name, pose_file, len(trajectory), seq.length)
    summary = finish_run(seq, np.stack(trajectory), diagnostics, timer, wall, out, align=cfg.align,
                         pose_file=pose_file, warn_fallback_rate=cfg.warn_fallback_rate,
                         partial=None if stopped is None else signal.Signals(stopped.signum).name, extra=extra)
    if stopped is not None:
        raise stopped
    return summary


def _stamp(seq: Any, index: int) -> float | None:
    return None if seq.timestamps is None else float(seq.timestamps[index])


def _write_frame(record: FrameRecord, poses: TrajectoryWriter, table: FramesCsv, trajectory: list[np.ndarray],
                 diagnostics: list[FrameDiagnostics], observers: list[Any], timestamp: float | None) -> None:
    T_w = record.result.T_w_cur.detach().cpu().double().numpy()
    poses.write(T_w, timestamp)
    table.write(record.result.diagnostics, record.stage_seconds)
    trajectory.append(T_w)
    diagnostics.append(record.result.diagnostics)
    for obs in observers:
        obs.on_frame(record)
