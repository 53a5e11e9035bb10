"""Files an inference run writes, each as frames are produced (an interrupted run leaves valid prefixes).

- ``SEQ.txt``: KITTI pose format, one line per input frame (row-major top 3x4 of ``T_w_c``), flushed per line.
- ``frames.csv``: one row per frame (frame 0 is the reference, tracker ``init``): tracker used, correspondences,
  inliers, GRIC scores, scale, fallback reason, per-stage seconds.
- ``metrics.json`` (through :func:`dfvo.eval.evaluate_trajectory`) and ``trajectory.png``
  (:func:`dfvo.eval.plot_trajectory`) at the end.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

import numpy as np

from dfvo.io.json_io import write_json

__all__ = ["PoseWriter", "FramesCsv", "CSV_FIELDS", "write_json", "fallback_summary"]

CSV_FIELDS = ["frame", "tracker", "num_correspondences", "num_inliers", "gric_e", "gric_h", "scale",
              "fallback_reason", "constant_motion", "pnp_failed", "t_flow", "t_refine", "t_depth", "t_tracker"]


def pose_line(T: np.ndarray) -> str:
    """One KITTI pose-file line for a (4,4) pose (12 numbers, row-major 3x4)."""
    return " ".join(f"{v:.9e}" for v in np.asarray(T, dtype=np.float64)[:3, :4].reshape(-1))


class PoseWriter:
    """Append poses to a KITTI pose file, one flushed line each.

    Args:
        path: output file (truncated on open).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f = self.path.open("w")
        self.count = 0

    def write(self, T_w_c: np.ndarray) -> None:
        """Append one (4,4) camera-to-world pose."""
        self._f.write(pose_line(T_w_c) + "\n")
        self._f.flush()
        self.count += 1

    def close(self) -> None:
        self._f.close()


def _fmt(v: Any) -> Any:
    if v is None:
        return ""
    if hasattr(v, "item") and getattr(v, "numel", lambda: 1)() == 1:
        v = v.item()
    if isinstance(v, float):
        return "" if math.isnan(v) else f"{v:.6g}"
    return v


class FramesCsv:
    """Per-frame diagnostics, one flushed CSV row per frame (columns :data:`CSV_FIELDS`, extra keys dropped)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._f = self.path.open("w", newline="")
        self._w = csv.DictWriter(self._f, fieldnames=CSV_FIELDS, extrasaction="ignore")
        self._w.writeheader()
        self._f.flush()

    def write(self, row: dict[str, Any]) -> None:
        self._w.writerow({k: _fmt(row.get(k)) for k in CSV_FIELDS})
        self._f.flush()

    def close(self) -> None:
        self._f.close()


def fallback_summary(rows: list[dict[str, Any]], threshold: float = 0.2) -> dict[str, Any]:
    """Fraction of tracked frames that fell back to constant motion or whose PnP failed.

    Args:
        rows: per-frame rows (frame 0 excluded) with bool ``constant_motion`` and ``pnp_failed``.
        threshold: fraction above which ``warn`` is True.
    """
    n = max(len(rows), 1)
    const = sum(bool(r.get("constant_motion")) for r in rows)
    pnp_fail = sum(bool(r.get("pnp_failed")) for r in rows)
    trackers: dict[str, int] = {}
    for r in rows:
        trackers[str(r.get("tracker"))] = trackers.get(str(r.get("tracker")), 0) + 1
    out = {"frames": len(rows), "constant_motion": const, "pnp_failed": pnp_fail,
           "constant_motion_rate": const / n, "pnp_failed_rate": pnp_fail / n, "trackers": trackers}
    out["warn"] = out["constant_motion_rate"] > threshold or out["pnp_failed_rate"] > threshold
    return out
