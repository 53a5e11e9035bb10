"""The end of a run: ``metrics.json`` (with ground truth), the plots, ``summary.json`` and the log banner — also for
an interrupted run (``partial``: the poses written so far are evaluated against the same prefix of the truth)."""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Any

import numpy as np

from dfvo.data.sequence import FrameSequence
from dfvo.eval.odometry_metrics import aligned_prediction, evaluate_trajectory
from dfvo.inference.outputs import fallback_summary, writing
from dfvo.inference.timing import StageTimer
from dfvo.io.json_io import write_json
from dfvo.tracking.diagnostics import FrameDiagnostics, TrackerUsed

__all__ = ["hydra_choices", "hydra_overrides", "finish_run"]

log = logging.getLogger("dfvo.infer")

NOT_ABLATION_KEYS = ("out_dir", "data.root", "progress", "num_threads", "verbose", "device", "hydra.", "hydra/")
SEQUENCE_KEYS = ("seq", "data.seq")  # the ablation table's columns, not its rows


def hydra_choices() -> dict[str, str]:
    """The config-group choices of this Hydra job (empty outside Hydra), for the ablation table."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return {}
    return {k: str(v) for k, v in HydraConfig.get().runtime.choices.items()
            if not k.startswith("hydra") and "schema" not in k}


def hydra_overrides() -> dict[str, str]:
    """The command line's ``key=value`` overrides that are not group choices (e.g. ``flow.refine.iterations=0``),
    without paths and run settings; empty outside Hydra. The ablation table shows the ones that vary."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return {}
    groups = set(hydra_choices())
    out = {}
    for item in HydraConfig.get().overrides.task:
        key, sep, value = item.lstrip("+~").partition("=")
        if (sep and key not in groups and "@" not in key and key not in SEQUENCE_KEYS
                and not key.startswith(NOT_ABLATION_KEYS)):
            out[key] = value
    return out


def camera_height_report(vo: Any) -> dict[str, Any] | None:
    """``summary.json``'s ``camera_height``: the height the road observations used (given, or estimated from the
    depth network's road plane: value, spread, frames with a plane, or why it is unavailable); logged once. None when
    the run had none (``experiment=paper``)."""
    height = vo.fusion.camera_height
    if not height.enabled:
        return None
    report = height.report()
    if report["source"] == "estimated":
        log.info("camera height estimated from the depth network's road plane: %.3f m (spread %.1f %%, %d of %d "
                 "frames with a plane)", report["value_m"], 100 * (report["spread"] or 0.0),
                 report["frames_with_plane"], report["frames"])
    elif report["source"] is None:
        log.warning("no camera height: %s; the scale is the depth network's alone", report["unavailable_reason"])
    return report


def motion_report(vo: Any) -> dict[str, Any]:
    """``summary.json``'s ``motion``: the motion model the tracker ran (``tracker.motion``) and, with ``auto``, how it
    judged it (:meth:`dfvo.tracking.motion_model.MotionJudge.report`); logged once."""
    report = vo.motion.report()
    log.info("motion: %s (%s)", report["motion"], report["reason"])
    return report


def finish_run(seq: FrameSequence, pred: np.ndarray, diagnostics: list[FrameDiagnostics], timer: StageTimer,
               wall: float, out: Path, *, align: str, pose_file: Path, warn_fallback_rate: float,
               partial: str | None = None, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """Evaluate, plot and summarise a run; write ``metrics.json`` (when ground truth exists), ``trajectory.png``,
    ``frames.png`` (per-frame panel) and ``summary.json``.

    Args:
        seq: the sequence. pred: (M,4,4) poses written (M = N, or fewer when ``partial``).
        diagnostics: the M-1 tracked frames. timer: stage times. wall: seconds of the loop.
        align: alignment for the metrics. pose_file: the trajectory file written.
        partial: why the run stopped early: a signal's name, or ``"error"`` (with ``extra["error"]`` its message);
            None: it completed.
        extra: more fields for ``summary.json`` (sources, settings).

    Returns:
        The summary (as written).
    """
    from dfvo.eval.plots import plot_frames, plot_trajectory  # deferred: matplotlib, once per run

    tracked = len(diagnostics)
    summary: dict[str, Any] = {
        "sequence": seq.name, "frames": seq.length, "frames_written": len(pred), "partial": partial is not None,
        "stopped_by": partial, "pose_file": str(pose_file),
        "fps": tracked / wall if wall > 0 and tracked else None, "wall_s": wall,
        "timing_ms_per_frame": timer.ms_per_frame(tracked),
        "fallback": fallback_summary(diagnostics, warn_fallback_rate),
        "choices": hydra_choices(), "overrides": hydra_overrides(), **(extra or {}),
    }
    metrics = None
    gt_plotted, plotted = None, pred
    if seq.poses is not None and len(pred) >= 2:
        gt = seq.poses[: len(pred)]
        metrics = {"sequence": seq.name, **evaluate_trajectory(gt, pred, align=align)}
        if partial is not None:
            metrics["partial"] = f"first {len(pred)} of {seq.length} frames ({partial})"
        with writing(out / "metrics.json"):
            write_json(out / "metrics.json", metrics)
        # plotted as evaluated: both relative to their first frame (with ground truth), prediction aligned
        gt_plotted, _, plotted, _ = aligned_prediction(gt, pred, align=align)
    rows = [FrameDiagnostics(frame=0, tracker=TrackerUsed.init).as_row()] + [d.as_row() for d in diagnostics]
    if len(pred) >= 2:
        caption = None if partial is None else "partial run: " + (
            f"stopped by an error ({summary.get('error')})" if partial == "error" else partial)
        with writing(out / "trajectory.png"):
            plot_trajectory(gt_plotted, plotted, out / "trajectory.png", title=seq.name,
                            align=align if metrics is not None else None, metrics=metrics, caption=caption)
        with writing(out / "frames.png"):
            plot_frames(rows, out / "frames.png", pred=plotted, gt=gt_plotted, title=seq.name)
    summary["metrics"] = metrics
    with writing(out / "summary.json"):
        write_json(out / "summary.json", summary)
    _banner(summary, out)
    return summary


def _banner(summary: dict[str, Any], out: Path) -> None:
    fb = summary["fallback"]
    log.info("%s: %d frames%s, %.2f FPS, timing ms/frame %s", summary["sequence"], summary["frames_written"],
             " (partial)" if summary["partial"] else "", summary["fps"] or 0.0,
             {k: round(v, 1) for k, v in summary["timing_ms_per_frame"].items()})
    metrics = summary.get("metrics")
    if metrics is not None:
        log.info("metrics: %s", {k: v for k, v in metrics.items() if not isinstance(v, dict | list)})
    if fb["warn"]:
        msg = (f"\n{'!' * 78}\nWARNING: {fb['constant_motion']}/{fb['frames']} frames "
               f"({100 * fb['constant_motion_rate']:.0f}%) fell back to constant motion and PnP failed on "
               f"{fb['pnp_failed']} ({100 * fb['pnp_failed_rate']:.0f}%).\nThe trajectory is unreliable: check the "
               f"flow/depth sources, the image resolution and the intrinsics (see {out / 'frames.csv'}).\n"
               f"{'!' * 78}")
        log.warning("%d/%d frames fell back to constant motion, PnP failed on %d", fb["constant_motion"],
                    fb["frames"], fb["pnp_failed"])
        print(msg, file=sys.stderr, flush=True)
