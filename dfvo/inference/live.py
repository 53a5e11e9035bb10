"""``data=stream``: DF-VO on a live source (camera, network stream, growing video) as its frames arrive.

The frames come from :class:`dfvo.data.stream.StreamReader` (decoded in a background thread; ``data.realtime``
keeps only the latest frame when tracking falls behind) and go through :class:`dfvo.api.Odometry` (the pipeline of
``infer.py`` one frame at a time). Everything is written as it is produced, as for recorded data: the trajectory
``OUT/SEQ.txt`` (``data.seq``, default ``stream``), ``frames.csv`` with three more columns per frame
(``stream_frame``: the frame's number in the source, ``dropped_before``: frames dropped since the previous tracked
one, ``timestamp``: seconds), the observers (``output.rosbag``, ``viewer``, ``tensorboard``) and at the end the
plots and ``summary.json`` with a ``stream`` section (frames received, tracked and dropped, how the source ended).

How a run ends: the source ends (``end``), stalls for ``data.timeout_s`` (``stalled``), is cut or cannot be decoded
(``error``), a frame of another size is refused (``data.size_change=refuse``: ``refused``), ``data.max_frames`` is
reached, or Ctrl-C / SIGTERM. Each ends with one log line saying so and complete outputs for the frames tracked; a
source that cannot be opened, or that gives no frame at all, is an error (one line).
"""

from __future__ import annotations

import logging
import signal
import time
from pathlib import Path
from typing import Any

import numpy as np

from dfvo.data.image_io import DatasetError
from dfvo.data.sequence import FrameSequence
from dfvo.inference.api import SIZE_CHANGE, Odometry
from dfvo.inference.assembly import build_observers
from dfvo.inference.config import InferConfig
from dfvo.inference.outputs import FramesCsv
from dfvo.inference.recording import RunInterrupted, SignalsToInterrupt, write_frame
from dfvo.inference.report import camera_height_report, finish_run, motion_report
from dfvo.io.trajectory import TrajectoryWriter
from dfvo.tracking.diagnostics import FrameDiagnostics, TrackerUsed

__all__ = ["run_live", "LIVE_FIELDS"]

log = logging.getLogger("dfvo.infer")
LIVE_FIELDS = ["stream_frame", "dropped_before", "timestamp"]


def run_live(cfg: InferConfig, data: Any, out: Path, device: str) -> dict[str, Any]:
    """Track the live source of ``data`` (a :class:`~dfvo.inference.config.StreamDataConfig`) into ``out``.

    Returns:
        The summary (also ``OUT/summary.json``), with ``stream``: url, realtime, frames_received, frames_tracked,
        frames_dropped, ended_by, error.

    Raises:
        ImportError: PyAV missing. DatasetError: the source cannot be opened or gave no frame. ValueError: a bad
        setting. RunInterrupted: after writing the outputs of a run stopped by SIGINT/SIGTERM.
    """
    from dfvo.data.stream import StreamReader

    for key in ("start", "end", "step"):
        if getattr(data, key, None) is not None:
            raise ValueError(f"data=stream: data.{key} selects frames of a recording; a live source takes "
                             "data.max_frames= (stop after that many frames)")
    if data.size_change not in SIZE_CHANGE:
        raise ValueError(f"data.size_change={data.size_change!r}; expected one of {SIZE_CHANGE}")
    if data.max_frames is not None and int(data.max_frames) < 2:
        raise ValueError(f"data.max_frames={data.max_frames}; expected at least 2 (or null: until the source ends)")
    reader = StreamReader(data.url, realtime=data.realtime, timeout_s=data.timeout_s,
                          input_format=data.input_format, options=dict(data.options or {}))
    reader.open()  # a source that cannot be opened fails here, before the networks load
    try:
        odo = Odometry(cfg, fx=data.fx, fy=data.fy, cx=data.cx, cy=data.cy, dist=data.dist,
                       size_change=data.size_change)
    except BaseException:
        reader.close()
        raise
    name = data.seq or "stream"
    pose_file = out / f"{name}.txt"
    poses = TrajectoryWriter(pose_file, cfg.pose_format.value)
    table = FramesCsv(out / "frames.csv", extra_fields=LIVE_FIELDS)
    trajectory: list[np.ndarray] = []
    diagnostics: list[FrameDiagnostics] = []
    stamps: list[float] = []
    observers: list[Any] = []
    stopped: RunInterrupted | None = None
    refused: str | None = None
    start = time.perf_counter()
    try:
        with SignalsToInterrupt() as interrupts:
            reader.start()
            for frame in reader:
                try:
                    result = odo.step(frame.image, frame.timestamp)
                except ValueError as err:  # size_change=refuse
                    refused = str(err)
                    break
                extra = {"stream_frame": frame.index, "dropped_before": frame.dropped_before,
                         "timestamp": frame.timestamp}
                with interrupts.held():
                    if result.index == 0:
                        trajectory.append(np.eye(4))
                        poses.write(trajectory[0], frame.timestamp)
                        table.write(FrameDiagnostics(frame=0, tracker=TrackerUsed.init), None, extra)
                        observers = build_observers(cfg, out, _first_frame(name, odo, odo.last_image, frame.timestamp))
                    else:
                        write_frame(odo.last_record, poses, table, trajectory, diagnostics, observers, frame.timestamp,
                                     extra)
                    stamps.append(frame.timestamp)
                if data.max_frames is not None and len(trajectory) >= int(data.max_frames):
                    break
    except RunInterrupted as err:
        stopped = err
    except KeyboardInterrupt:
        stopped = RunInterrupted(signal.SIGINT)
    finally:
        reader.close()
        poses.close()
        table.close()
        for obs in observers:
            obs.close()
    wall = time.perf_counter() - start
    stats = _stream_stats(reader, len(trajectory), refused, stopped, data)
    _say_how_it_ended(stats, pose_file)
    if not trajectory:
        raise DatasetError(f"data.url={data.url}: no frame arrived ({stats['ended_by']}: "
                           f"{stats['error'] or 'no data'})")
    seq = FrameSequence(name, len(trajectory), odo.K, lambda i: None, None, None, np.asarray(stamps))
    summary = finish_run(seq, np.stack(trajectory), diagnostics, odo.timer, wall, out, align=cfg.align,
                         pose_file=pose_file, warn_fallback_rate=cfg.warn_fallback_rate,
                         partial=None if stopped is None else signal.Signals(stopped.signum).name,
                         extra={**odo.sources.extra, "stream": stats, "camera_height": camera_height_report(odo.vo),
                                "motion": motion_report(odo.vo)})
    if stopped is not None:
        raise stopped
    return summary


def _first_frame(name: str, odo: Any, image: Any, stamp: float) -> FrameSequence:
    """The first frame as a one-frame sequence, for the observers that need the image size, K and frame 0's time."""
    return FrameSequence(name, 1, odo.K, lambda i: image, None, None, np.asarray([stamp], dtype=np.float64))


def _stream_stats(reader: Any, tracked: int, refused: str | None, stopped: RunInterrupted | None,
                  data: Any) -> dict[str, Any]:
    stats = reader.stats()
    stats["frames_tracked"] = tracked
    if refused is not None:
        stats["ended_by"], stats["error"] = "refused", refused
    elif stopped is not None:
        stats["ended_by"] = f"interrupted ({signal.Signals(stopped.signum).name})"
    elif data.max_frames is not None and tracked >= int(data.max_frames):
        stats["ended_by"] = "max_frames"
    return stats


def _say_how_it_ended(stats: dict[str, Any], pose_file: Path) -> None:
    """One log line: how the source ended, frames tracked and dropped, where the poses are."""
    how = stats["ended_by"]
    text = (f"stream {stats['url']}: {how}{': ' + stats['error'] if stats.get('error') else ''}; "
            f"{stats['frames_tracked']} frames tracked, {stats['frames_dropped']} dropped "
            f"({stats['frames_received']} received); poses in {pose_file}")
    if how in ("end", "max_frames", "closed"):
        log.info(text)
    else:
        log.warning(text)
