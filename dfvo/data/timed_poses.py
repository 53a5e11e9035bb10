"""Frame lists and their timestamped ground truth: text tables, nearest-timestamp association, unmatched policies.

Used by the EuRoC and TUM RGB-D readers, whose ground truth runs at its own rate (200 Hz, 100 Hz) and over its own
time span. The ground-truth files themselves are read by :mod:`dfvo.io.trajectory` (``read_euroc``,
``read_tum``) and frames are paired with poses by :func:`dfvo.io.association.match_timestamps` (nearest timestamp
within a tolerance, each pose used once, as evo and the TUM benchmark tools associate); what stays here is the
part that belongs to datasets: reading the frame lists, and what to do with frames that have no pose.

Convention:
    - Times are float64 seconds. Integer nanoseconds (EuRoC) become seconds as ``ns * 1e-9`` on both sides, the
      conversion :func:`dfvo.io.trajectory.read_euroc` applies to the ground truth, so equal nanosecond stamps
      stay equal; the float64 seconds resolve ~0.25 us at EuRoC's epoch times, far below any tolerance used.
    - ``unmatched`` policy for frames without a ground-truth pose within the tolerance:
      ``"trim"`` drops the frames before the first and after the last matched frame (ground truth often starts
      late or stops early) and refuses gaps inside; ``"nan"`` keeps every frame, unmatched frames get an all-NaN
      pose (evaluate on ``np.isfinite(poses[:, 0, 0])``); ``"none"`` ignores the ground truth.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np

from dfvo.data.image_io import DatasetError, require_file
from dfvo.io.association import match_timestamps

__all__ = ["UNMATCHED_POLICIES", "read_rows", "parse_floats", "read_ground_truth", "associate_frames",
           "attach_ground_truth"]

UNMATCHED_POLICIES = ("trim", "nan", "none")
log = logging.getLogger("dfvo.data")


def read_rows(path: str | Path, what: str, min_cols: int, sep: str | None = None) -> list[tuple[int, list[str]]]:
    """Non-empty, non-comment (``#``) lines of a text table as ``(line number, fields)``.

    Raises:
        DatasetNotFoundError: the file does not exist.
        DatasetError: a line has fewer than ``min_cols`` fields, or the file has no data line.
    """
    path = require_file(path, what)
    rows: list[tuple[int, list[str]]] = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        fields = [f.strip() for f in text.split(sep)] if sep else text.split()
        if len(fields) < min_cols:
            raise DatasetError(f"{what} {path} line {lineno}: {len(fields)} fields, expected at least {min_cols}: "
                               f"{text[:80]!r}")
        rows.append((lineno, fields))
    if not rows:
        raise DatasetError(f"{what} {path} has no data lines")
    return rows


def parse_floats(fields: list[str], path: Path | str, lineno: int, what: str) -> list[float]:
    """``fields`` as floats, or a :class:`DatasetError` naming the file and line."""
    try:
        values = [float(f) for f in fields]
    except ValueError:
        raise DatasetError(f"{what} {path} line {lineno}: expected numbers, got {' '.join(fields)[:80]!r}") from None
    if not np.all(np.isfinite(values)):
        raise DatasetError(f"{what} {path} line {lineno}: non-finite value in {' '.join(fields)[:80]!r}")
    return values


def read_ground_truth(path: str | Path, reader: Callable, what: str) -> tuple[np.ndarray, np.ndarray]:
    """``(timestamps (M,) s, poses (M,4,4))`` of a ground-truth file read by an :mod:`dfvo.io.trajectory`
    reader (``read_euroc``, ``read_tum``); its errors become :class:`DatasetError` naming ``what``.

    Raises:
        DatasetNotFoundError: the file does not exist.
        DatasetError: a malformed line (the eval reader's message: file, line number, what was expected).
    """
    path = require_file(path, what)
    try:
        traj = reader(path)
    except ValueError as err:
        raise DatasetError(f"{what}: {err}") from err
    return traj.timestamps, traj.poses


def associate_frames(frame_times_s: np.ndarray, gt_times_s: np.ndarray, tolerance_s: float) -> np.ndarray:
    """For each frame, the index of its ground-truth pose (nearest time within ``tolerance_s``, each pose used by
    one frame: :func:`dfvo.io.association.match_timestamps`), or -1.

    Args:
        frame_times_s: (N,) frame times in seconds. gt_times_s: (M,) ground-truth times in seconds (any order).
        tolerance_s: largest accepted ``|frame - gt|`` in seconds (inclusive).

    Returns:
        (N,) int64 indices into the ground truth (-1: no pose within the tolerance).
    """
    match = np.full(len(frame_times_s), -1, dtype=np.int64)
    i_frame, i_gt = match_timestamps(np.asarray(frame_times_s, np.float64), np.asarray(gt_times_s, np.float64),
                                     float(tolerance_s))
    match[i_frame] = i_gt
    return match


def attach_ground_truth(frame_times_s: np.ndarray, match: np.ndarray, gt_poses: np.ndarray, unmatched: str,
                        what: str, tolerance_s: float) -> tuple[np.ndarray, np.ndarray | None, str]:
    """Apply the ``unmatched`` policy to an association; return the frames kept, their poses and a report line.

    Args:
        frame_times_s: (N,) frame times in seconds (for the messages).
        match: (N,) index of each frame's ground-truth pose, -1 when none (:func:`associate_frames`).
        gt_poses: (M,4,4) ground-truth poses.
        unmatched: ``"trim"``, ``"nan"`` or ``"none"`` (module docstring).
        what: the sequence, for messages.
        tolerance_s: the association tolerance, for messages.

    Returns:
        ``(keep, poses, report)``: indices (into the N frames) to keep, (len(keep),4,4) poses or None, one line.

    Raises:
        ValueError: unknown policy.
        DatasetError: no frame matched, or (``"trim"``) unmatched frames between matched ones.
    """
    if unmatched not in UNMATCHED_POLICIES:
        raise ValueError(f"unmatched={unmatched!r}; expected one of {UNMATCHED_POLICIES}")
    n = len(match)
    if unmatched == "none":
        return np.arange(n), None, f"{what}: {n} frames, ground truth not used (unmatched=none)"
    hit = match >= 0
    n_hit = int(hit.sum())
    if n_hit == 0:
        raise DatasetError(f"{what}: none of the {n} frames (t = {frame_times_s[0]:.3f} .. {frame_times_s[-1]:.3f} s) "
                           f"has a ground-truth pose within {tolerance_s:g} s; check the time bases, raise the "
                           "tolerance, or run without ground truth (unmatched=none)")
    report = f"{what}: {n_hit} of {n} frames matched to ground truth within {tolerance_s:g} s"
    if unmatched == "nan":
        poses = np.full((n, 4, 4), np.nan)
        poses[hit] = gt_poses[match[hit]]
        if n_hit < n:
            report += f"; {n - n_hit} frames without ground truth have NaN poses (unmatched=nan)"
        return np.arange(n), poses, report
    first, last = int(np.argmax(hit)), n - 1 - int(np.argmax(hit[::-1]))
    inner = ~hit[first:last + 1]
    if inner.any():
        k = first + int(np.argmax(inner))
        raise DatasetError(f"{what}: {int(inner.sum())} frames inside the ground-truth span have no pose within "
                           f"{tolerance_s:g} s (first: frame {k}, t = {frame_times_s[k]:.6f} s); raise the tolerance "
                           "or keep them with NaN poses (unmatched=nan)")
    keep = np.arange(first, last + 1)
    if first or last < n - 1:
        report += (f"; dropped {first} frames before and {n - 1 - last} after the ground truth (unmatched=trim), "
                   f"kept frames {first}..{last}")
    return keep, gt_poses[match[keep]], report
