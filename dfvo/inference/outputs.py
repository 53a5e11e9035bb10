"""Files an inference run writes as frames are produced (an interrupted run leaves valid prefixes).

- ``SEQ.txt``: the trajectory, one line per input frame, flushed per line (KITTI or TUM format:
  :class:`dfvo.io.trajectory.TrajectoryWriter`).
- ``frames.csv``: one row per frame (frame 0 is the reference, tracker ``init``): the fields of
  :class:`~dfvo.tracking.diagnostics.FrameDiagnostics`, the seconds per stage and the 21 upper-triangle entries of
  the step's 6x6 covariance (``cov_rx_rx`` ... ``cov_tz_tz``, :mod:`dfvo.tracking.covariance`; empty on frame 0);
  a live stream adds its own columns (``stream_frame``, ``dropped_before``, ``timestamp``).
- ``metrics.json``, ``summary.json``, the plots: at the end (:mod:`dfvo.inference.report`); a first
  ``summary.json`` marked unfinished is written when tracking starts, so a run killed outright (SIGKILL, power loss)
  still says in OUT that it did not finish and which pose file it was writing.

One run at a time per folder: :func:`lock_out_dir` takes an exclusive lock (``OUT/.dfvo.lock``, ``flock``: the
kernel drops it when its process dies, so a killed run never blocks the folder); a second run refuses with one line.
A rerun into a folder replaces the previous run's outputs (:func:`clear_previous_outputs`): nothing stale survives
beside the new ones. A write that fails (a full disk, a quota) is one error naming the file (:func:`writing`).
"""

from __future__ import annotations

import csv
import errno
import json
import logging
import math
import os
import shutil
import socket
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from dfvo.geometry.pose_covariance import COVARIANCE_FIELDS
from dfvo.inference.config import InferConfig
from dfvo.tracking.diagnostics import DIAGNOSTIC_FIELDS, FrameDiagnostics

__all__ = ["prepare_out_dir", "FramesCsv", "CSV_FIELDS", "STAGE_FIELDS", "fallback_summary", "OutDirBusy",
           "OutDirLock", "lock_out_dir", "clear_previous_outputs", "RUN_OUTPUTS", "OutputWriteError", "writing",
           "is_bag", "remove_output"]

log = logging.getLogger("dfvo.infer")

LOCK_NAME = ".dfvo.lock"
# what a run writes into out_dir besides its pose file (named in summary.json) and Hydra's own infer.log / .hydra/
RUN_OUTPUTS = ("summary.json", "metrics.json", "frames.csv", "trajectory.png", "frames.png", "run.rrd",
               "tensorboard", "bag")
BAG_FILES = ("metadata.yaml", "*.db3", "*.mcap")  # what makes OUT/bag a bag (a killed run's has no metadata.yaml)

STAGE_FIELDS = ["t_flow", "t_refine", "t_depth", "t_tracker"]
CSV_FIELDS = [f for f in DIAGNOSTIC_FIELDS if not f.startswith("time_")] + STAGE_FIELDS + COVARIANCE_FIELDS


def prepare_out_dir(out_dir: Any) -> Path:
    """Create the output folder ``out_dir`` (parents included) and check that it is writable.

    Raises:
        ValueError: ``out_dir`` is not set.
        OSError: the folder cannot be created or written (a path component is a file, no permission, ...); the
            message names ``out_dir`` and the cause.
    """
    if out_dir is None or not str(out_dir).strip():
        raise ValueError("out_dir is not set; pass out_dir=FOLDER (created if missing)")
    out = Path(str(out_dir))
    blocker = next((p for p in (out, *out.parents) if p.exists() and not p.is_dir()), None)
    if blocker is not None:
        raise NotADirectoryError(f"out_dir={out}: cannot create the output folder, {blocker} is a file, not a "
                                 "folder; pass out_dir= a folder path")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise type(err)(f"out_dir={out}: cannot create the output folder ({err.strerror or err}); pass out_dir= a "
                        "writable folder path") from err
    if not os.access(out, os.W_OK | os.X_OK):
        raise PermissionError(f"out_dir={out}: the output folder is not writable; pass out_dir= a writable folder")
    return out


class _OneLineOSError(OSError):
    """An ``OSError(errno, message[, filename])`` whose text is the message alone (no ``[Errno N]`` prefix)."""

    def __str__(self) -> str:
        return str(self.args[1]) if len(self.args) > 1 else super().__str__()


class OutDirBusy(_OneLineOSError):
    """Another live run holds the output folder's lock."""


class OutDirLock:
    """Exclusive use of an output folder by this process: ``flock`` on ``OUT/.dfvo.lock`` (which holds the holder's
    pid, host and start time for the message of a refused run). Re-entrant within a process (the command line takes
    it before Hydra writes into the folder, the pipeline again for the job's folder); the file is removed on
    :meth:`release`, and the kernel drops the lock of a process that dies, so a stale file never blocks."""

    def __init__(self, out: Path, fd: int | None) -> None:
        self.out, self.path, self._fd, self._depth = out, out / LOCK_NAME, fd, 1

    def release(self) -> None:
        """Give the folder back (the last release of this process removes the lock file)."""
        self._depth -= 1
        if self._depth > 0 or self.out not in _HELD:
            return
        _HELD.pop(self.out, None)
        if self._fd is None:  # a platform without flock: nothing was locked
            return
        try:
            self.path.unlink(missing_ok=True)
        except OSError:
            pass
        os.close(self._fd)
        self._fd = None

    def __enter__(self) -> OutDirLock:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.release()


_HELD: dict[Path, OutDirLock] = {}


def lock_out_dir(out_dir: str | Path) -> OutDirLock:
    """Take the lock of the folder ``out_dir`` (created if missing) for this process; see :class:`OutDirLock`.

    Raises:
        OutDirBusy: a live process holds it (one line: the folder, the holder's pid and start, what to do).
    """
    out = Path(out_dir).resolve()
    held = _HELD.get(out)
    if held is not None:
        held._depth += 1
        return held
    out.mkdir(parents=True, exist_ok=True)
    path = out / LOCK_NAME
    try:
        import fcntl
    except ImportError:  # not POSIX (Windows): no lock, the folder is used as it is
        log.debug("no fcntl on this platform: out_dir %s is not locked", out)
        lock = _HELD[out] = OutDirLock(out, None)
        return lock
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 4096).decode(errors="replace")
            os.close(fd)
            raise OutDirBusy(errno.EBUSY, _busy_message(out_dir, holder)) from None
        try:
            same = os.stat(path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:  # the holder released (and removed) it between our open and our lock
            same = False
        if same:
            break
        os.close(fd)
    info = {"pid": os.getpid(), "host": socket.gethostname(), "since": time.strftime("%Y-%m-%d %H:%M:%S")}
    os.ftruncate(fd, 0)
    os.write(fd, json.dumps(info).encode())
    lock = _HELD[out] = OutDirLock(out, fd)
    return lock


def _busy_message(out_dir: str | Path, holder: str) -> str:
    try:
        info = json.loads(holder)
        who = f"pid {info['pid']} on {info['host']}, since {info['since']}"
    except (ValueError, KeyError, TypeError):
        who = "another process"
    return (f"out_dir={out_dir} is in use by another dfvo run ({who}); two runs in one folder would mix their "
            "files: wait for it to finish or pass another out_dir=")


def clear_previous_outputs(out: Path) -> list[str]:
    """Remove the outputs a previous run left in ``out`` (:data:`RUN_OUTPUTS`, and the pose file its
    ``summary.json`` names), so that everything in the folder after this run is this run's. Hydra's ``infer.log``
    and ``.hydra/`` are Hydra's to replace; other files are not touched. Returns the names removed (also logged)."""
    out = Path(out)
    names = list(RUN_OUTPUTS)
    try:
        previous = json.loads((out / "summary.json").read_text()).get("pose_file")
    except (OSError, ValueError, AttributeError):
        previous = None
    if isinstance(previous, str) and Path(previous).parent.resolve() == out.resolve():
        names.append(Path(previous).name)
    removed = []
    for name in names:
        path = out / name
        if name == "bag" and not is_bag(path):
            continue  # a folder of the user's own that happens to be called bag
        if not (path.exists() or path.is_symlink()):
            continue
        remove_output(path)
        removed.append(name)
    if removed:
        log.info("out_dir %s held an earlier run's outputs; removed %s (this run writes its own)", out,
                 ", ".join(removed))
    return removed


def is_bag(path: Path) -> bool:
    """``path`` is a folder holding a ROS 2 bag (:data:`BAG_FILES`), complete or left by a killed run."""
    return path.is_dir() and not path.is_symlink() and any(any(path.glob(p)) for p in BAG_FILES)


def remove_output(path: Path) -> None:
    """Remove an earlier run's output ``path`` (file or folder).

    Raises:
        OutputWriteError: it cannot be removed (read-only, another owner); one line naming the file that failed.
    """
    try:
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink()
    except OSError as err:
        failed = err.filename or path
        raise OutputWriteError(err.errno, f"cannot remove the earlier run's {path} ({failed}: "
                               f"{err.strerror or err}); remove it yourself or pass another out_dir=",
                               str(path)) from err


class OutputWriteError(_OneLineOSError):
    """A file of the run could not be written (disk full, quota, ...); the message names the file."""


@contextmanager
def writing(path: str | Path) -> Iterator[None]:
    """Turn an ``OSError`` raised inside the block (a write of ``path``) into an :class:`OutputWriteError` whose one
    line names ``path``: a failed ``write()`` itself says only ``[Errno 28] No space left on device``."""
    try:
        yield
    except OutputWriteError:
        raise
    except OSError as err:
        reason = err.strerror or str(err)
        hint = "; free space on its disk or pass another out_dir=" if err.errno in (errno.ENOSPC, errno.EDQUOT,
                                                                                     errno.EFBIG) else ""
        raise OutputWriteError(err.errno, f"cannot write {path}: {reason}{hint}", str(path)) from err


def _fmt(v: Any) -> Any:
    if v is None:
        return ""
    if isinstance(v, bool):
        return int(v)
    if hasattr(v, "value") and not isinstance(v, int | float | str):
        return v.value
    if isinstance(v, float):
        return "" if math.isnan(v) else f"{v:.6g}"
    return v


class FramesCsv:
    """Per-frame diagnostics, one flushed CSV row per frame (columns :data:`CSV_FIELDS`, then ``extra_fields``)."""

    def __init__(self, path: str | Path, extra_fields: list[str] | tuple[str, ...] = ()) -> None:
        self.path = Path(path)
        self.fields = CSV_FIELDS + [f for f in extra_fields if f not in CSV_FIELDS]
        self._f = self.path.open("w", newline="")
        self._w = csv.DictWriter(self._f, fieldnames=self.fields, extrasaction="ignore")
        self._w.writeheader()
        self._f.flush()

    def write(self, diagnostics: FrameDiagnostics, stage_seconds: dict[str, float] | None = None,
              extra: dict[str, Any] | None = None) -> None:
        """One row: the frame's diagnostics, its seconds per stage (``t_flow``, ...) and ``extra`` columns (the
        covariance's, a stream's)."""
        row = {**diagnostics.as_row(), **(stage_seconds or {}), **(extra or {})}
        self._w.writerow({k: _fmt(row.get(k)) for k in self.fields})
        self._f.flush()

    def close(self) -> None:
        self._f.close()


def fallback_summary(diagnostics: list[FrameDiagnostics],
                     threshold: float = InferConfig.warn_fallback_rate) -> dict[str, Any]:
    """Counts of the trackers used and of the frames that fell back to constant motion, whose PnP failed, or whose
    correspondences were selected under a relaxed forward-backward bound (``selection_relaxed``); with
    ``tracker.window`` also ``window``: frames whose step the window refined and frames it did not (the reasons are
    ``frames.csv``'s ``window_rejected``).

    Args:
        diagnostics: the tracked frames (frame 0 excluded).
        threshold: fraction above which ``warn`` is True.
    """
    n = max(len(diagnostics), 1)
    const = sum(d.constant_motion for d in diagnostics)
    pnp_fail = sum(d.pnp_failed for d in diagnostics)
    trackers: dict[str, int] = {}
    for d in diagnostics:
        name = d.tracker.value if d.tracker is not None else "none"
        trackers[name] = trackers.get(name, 0) + 1
    out = {"frames": len(diagnostics), "constant_motion": const, "pnp_failed": pnp_fail,
           "constant_motion_rate": const / n, "pnp_failed_rate": pnp_fail / n, "trackers": trackers,
           "selection_relaxed": sum(d.selection_max_inconsistency is not None for d in diagnostics)}
    out["warn"] = out["constant_motion_rate"] > threshold or out["pnp_failed_rate"] > threshold
    if any(d.window_tracks is not None or d.window_rejected is not None for d in diagnostics):
        refined = sum(d.window_length_ratio is not None for d in diagnostics)
        out["window"] = {"refined": refined, "not_refined": len(diagnostics) - refined}
    return out
