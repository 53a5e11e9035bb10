"""Files an inference run writes as frames are produced (an interrupted run leaves valid prefixes).

- ``SEQ.txt``: the trajectory, one line per input frame, flushed per line (KITTI or TUM format:
  :class:`dfvo.io.trajectory.TrajectoryWriter`).
- ``frames.csv``: one row per frame (frame 0 is the reference, tracker ``init``): the fields of
  :class:`~dfvo.tracking.diagnostics.FrameDiagnostics`, the seconds per stage and the 21 upper-triangle entries of
  the step's 6x6 covariance (``cov_rx_rx`` ... ``cov_tz_tz``, :mod:`dfvo.tracking.covariance`; empty on frame 0);
  a live stream adds its own columns (``stream_frame``, ``dropped_before``, ``timestamp``).
- ``metrics.json``, ``summary.json``, the plots: at the end (:mod:`dfvo.inference.report`).
"""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path
from typing import Any

from dfvo.inference.config import InferConfig
from dfvo.tracking.covariance import COVARIANCE_FIELDS
from dfvo.tracking.diagnostics import DIAGNOSTIC_FIELDS, FrameDiagnostics

__all__ = ["prepare_out_dir", "FramesCsv", "CSV_FIELDS", "STAGE_FIELDS", "fallback_summary"]

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
    """Counts of the trackers used and of the frames that fell back to constant motion or whose PnP failed.

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
           "constant_motion_rate": const / n, "pnp_failed_rate": pnp_fail / n, "trackers": trackers}
    out["warn"] = out["constant_motion_rate"] > threshold or out["pnp_failed_rate"] > threshold
    return out
