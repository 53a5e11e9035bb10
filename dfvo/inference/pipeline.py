"""One inference run: build the sequence, the sources and the tracker from the typed config, run the loop
(:mod:`dfvo.inference.loop`), write every frame's pose and diagnostics as it comes (:mod:`dfvo.inference.outputs`),
and finish with metrics, plots and the summary (:mod:`dfvo.inference.report`).

An interrupted run (Ctrl-C, SIGTERM) still finishes: the poses written so far are evaluated and plotted, and
``summary.json`` says ``partial``; then :class:`RunInterrupted` tells the command line to exit with 128 + signal.
Any other stop mid-run (an unreadable frame, a full disk) does the same with ``"stopped_by": "error"`` and the
error's message, then raises the error (with ``dfvo_partial`` = (poses written, frames) for the command line).
The run holds its output folder's lock throughout, and first removes an earlier run's outputs from it
(:mod:`dfvo.inference.outputs`).
"""

from __future__ import annotations

import logging
import signal
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig

from dfvo.inference.assembly import build_observers, build_sources, resolve_device
from dfvo.inference.config import InferConfig, PoseFormat
from dfvo.inference.frames import build_sequence
from dfvo.inference.live import run_live
from dfvo.inference.loop import resolve_overlap, track_sequence
from dfvo.inference.outputs import (
    FramesCsv,
    clear_previous_outputs,
    lock_out_dir,
    prepare_out_dir,
    writing,
)
from dfvo.inference.recording import RunInterrupted, SignalsToInterrupt, stamp, write_frame
from dfvo.inference.report import camera_height_report, finish_run, motion_report
from dfvo.inference.timing import StageTimer
from dfvo.io.json_io import write_json
from dfvo.io.trajectory import TrajectoryWriter
from dfvo.tracking import VisualOdometry
from dfvo.tracking.diagnostics import FrameDiagnostics, TrackerUsed
from dfvo.validation import typed

__all__ = ["RunInterrupted", "run_inference", "job_output_dir"]  # RunInterrupted is dfvo.inference.recording's

log = logging.getLogger("dfvo.infer")

# summary.json's "stopped_by" while tracking (replaced at the end; it stays when the process is killed outright)
UNFINISHED = "unfinished: the run is still going, or its process was killed before it could write its summary"


def job_output_dir(cfg: InferConfig) -> Path:
    """The folder this job writes to: Hydra's job folder when running under Hydra (``out_dir`` for a single run, a
    subfolder of it named by the job's overrides with ``-m``), else ``cfg.out_dir``."""
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized():
        return Path(HydraConfig.get().runtime.output_dir)
    return prepare_out_dir(cfg.out_dir)


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
    with lock_out_dir(out):  # one run per folder; a second one refuses (the kernel frees it if this one dies)
        clear_previous_outputs(out)  # a rerun into the folder: nothing of the earlier run survives
        return _prepare_and_run(icfg, out)


def _prepare_and_run(icfg: InferConfig, out: Path) -> dict[str, Any]:
    """:func:`run_inference` once the output folder is this run's: open the data and the sources, then track."""
    if icfg.num_threads:
        torch.set_num_threads(int(icfg.num_threads))
    device = resolve_device(icfg.device)
    data = typed(icfg.data) if isinstance(icfg.data, DictConfig) else icfg.data
    if data.kind == "stream":  # a live source: frames as they arrive (dfvo.inference.live)
        return run_live(icfg, data, out, device)
    seq = build_sequence(data, icfg.seq, icfg.img_res)
    if seq.length < 2:
        raise ValueError(f"sequence {seq.name} has {seq.length} frame(s); expected at least 2")
    src = build_sources(icfg, seq.world, device)
    observers = build_observers(icfg, out, seq)
    return _run(icfg, seq, src.flow, src.depth, src.refine, src.finetuner, observers, out, device, src.extra)


def _run(cfg: InferConfig, seq: Any, flow_src: Any, depth_src: Any, refine: Any, finetuner: Any,
         observers: list[Any], out: Path, device: str, extra: dict[str, Any]) -> dict[str, Any]:
    from tqdm import tqdm

    vo = VisualOdometry(cfg.tracker, cfg.flow.refine.pyramid)
    timer = StageTimer(cuda_sync=cfg.cuda_sync)
    pose_file = out / f"{seq.name}.txt"
    if cfg.pose_format == PoseFormat.tum and seq.timestamps is None:
        where = {"folder": " (give data.times=FILE, one line per frame)",
                 "kitti_raw": " (its image_02/timestamps.txt is missing)"}.get(cfg.data.kind, "")
        raise ValueError(f"pose_format=tum needs the frames' timestamps and {seq.name} has none{where}; use "
                         "pose_format=kitti")
    with writing(out / "summary.json"):
        write_json(out / "summary.json", {"sequence": seq.name, "frames": seq.length, "frames_written": None,
                                          "partial": True, "stopped_by": UNFINISHED, "pose_file": str(pose_file)})
    with writing(pose_file):
        poses = TrajectoryWriter(pose_file, cfg.pose_format.value)
    with writing(out / "frames.csv"):
        table = FramesCsv(out / "frames.csv")
    trajectory = [np.eye(4)]
    diagnostics: list[FrameDiagnostics] = []
    bar = tqdm(total=seq.length - 1, desc=f"dfvo {seq.name}", unit="frame", disable=not cfg.progress)
    stopped: RunInterrupted | None = None
    failed: Exception | None = None
    overlap = resolve_overlap(cfg.overlap, device)
    start = time.perf_counter()
    try:
        with writing(pose_file):
            poses.write(trajectory[0], stamp(seq, 0))
        with writing(table.path):
            table.write(FrameDiagnostics(frame=0, tracker=TrackerUsed.init))
        with SignalsToInterrupt() as interrupts:
            for record in track_sequence(seq, flow_src, depth_src, vo, refine=refine, batch_size=cfg.batch_size,
                                         timer=timer, device=device, finetuner=finetuner, overlap=overlap):
                with interrupts.held():
                    write_frame(record, poses, table, trajectory, diagnostics, observers, stamp(seq, record.index))
                bar.update(1)
                bar.set_postfix(fps=f"{len(diagnostics) / (time.perf_counter() - start):.2f}")
    except RunInterrupted as err:
        stopped = err
    except KeyboardInterrupt:
        stopped = RunInterrupted(signal.SIGINT)
    except Exception as err:  # any other stop mid-run (an unreadable frame, a full disk): partial outputs too
        failed = err
    finally:
        bar.close()
        for closable in (poses, table, *observers):
            try:
                closable.close()
            except OSError as err:  # a full disk: the close's flush fails; the error that stopped the run wins
                failed = failed or err
    wall = time.perf_counter() - start
    partial = None
    if stopped is not None:
        partial = signal.Signals(stopped.signum).name
        log.warning("interrupted by %s: %s holds the first %d of %d poses; writing partial results", partial,
                    pose_file, len(trajectory), seq.length)
    elif failed is not None:
        partial = "error"
        extra = {**extra, "error": str(failed)}
        log.error("stopped by an error after %d of %d poses (%s); writing partial results", len(trajectory),
                  seq.length, failed)
    extra = {**extra, "camera_height": camera_height_report(vo), "motion": motion_report(vo), "overlap": overlap.value,
             "torch_threads": torch.get_num_threads()}
    if timer.refine_cut is not None:
        cuts = timer.refine_cut["network_thread_units"]
        extra["refine_cut"] = {"units_per_batch": timer.refine_cut["units_per_batch"],
                               "network_thread_units_median": float(np.median(cuts)) if cuts else None,
                               "network_thread_units_last": cuts[-1] if cuts else None}
    try:
        summary = finish_run(seq, np.stack(trajectory), diagnostics, timer, wall, out, align=cfg.align,
                             pose_file=pose_file, warn_fallback_rate=cfg.warn_fallback_rate, partial=partial,
                             extra=extra)
    except Exception as err:
        if failed is None:
            raise
        log.error("the partial results could not be written either: %s", err)
    else:
        if failed is not None:
            failed.dfvo_partial = (summary["frames_written"], seq.length)  # for the command line's message
    if stopped is not None:
        raise stopped
    if failed is not None:
        raise failed
    return summary
