"""Timestamped ground truth for frame sequences: text tables, quaternions, nearest-timestamp association.

Used by the EuRoC and TUM RGB-D readers, whose ground truth runs at its own rate (200 Hz, 100 Hz) and over
its own time span, so each frame takes the ground-truth pose nearest in time when it lies within a tolerance
(as evo and the TUM benchmark tools associate).

Convention:
    - Quaternions are Hamilton, ``(qx, qy, qz, qw)`` (scalar last); EuRoC's w-first columns are reordered by
      its reader. Poses are (N,4,4) float64 ``T_w_x``.
    - ``unmatched`` policy for frames without a ground-truth pose within the tolerance:
      ``"trim"`` drops the frames before the first and after the last matched frame (ground truth often starts
      late or stops early) and refuses gaps inside; ``"nan"`` keeps every frame, unmatched frames get an all-NaN
      pose (evaluate on ``np.isfinite(poses[:, 0, 0])``); ``"none"`` ignores the ground truth.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from dfvo.data.image_io import DatasetError, require_file

__all__ = ["UNMATCHED_POLICIES", "read_rows", "parse_floats", "poses_from_quaternions", "associate_nearest",
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


def poses_from_quaternions(t: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    """(N,4,4) float64 poses from (N,3) translations and (N,4) quaternions ``(qx, qy, qz, qw)`` (normalised here).

    Raises:
        ValueError: a quaternion of (near) zero norm.
    """
    q = np.asarray(q_xyzw, dtype=np.float64)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    if np.any(norm < 1e-9):
        raise ValueError(f"zero quaternion in row {int(np.argmax(norm[:, 0] < 1e-9))}")
    x, y, z, w = (q / norm).T
    R = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], 1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], 1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], 1),
    ], 1)
    T = np.tile(np.eye(4), (len(q), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = np.asarray(t, dtype=np.float64)
    return T


def associate_nearest(query: np.ndarray, reference: np.ndarray, tolerance: float | int) -> np.ndarray:
    """For each query time, the index of the nearest reference time if within ``tolerance``, else -1.

    Args:
        query: (N,) times (any order).
        reference: (M,) times (any order), same unit and dtype family as ``query`` (int64 ns stays exact).
        tolerance: largest accepted ``|query - reference|`` (inclusive), same unit.

    Returns:
        (N,) int64 indices into ``reference`` (-1: no reference time within the tolerance).
    """
    query, reference = np.asarray(query), np.asarray(reference)
    if len(reference) == 0:
        return np.full(len(query), -1, dtype=np.int64)
    order = np.argsort(reference, kind="stable")
    ref = reference[order]
    right = np.clip(np.searchsorted(ref, query), 0, len(ref) - 1)
    left = np.clip(right - 1, 0, len(ref) - 1)
    best = np.where(np.abs(query - ref[left]) <= np.abs(ref[right] - query), left, right)
    dt = np.abs(query - ref[best])
    return np.where(dt <= tolerance, order[best], -1).astype(np.int64)


def attach_ground_truth(frame_times_s: np.ndarray, match: np.ndarray, gt_poses: np.ndarray, unmatched: str,
                        what: str, tolerance_s: float) -> tuple[np.ndarray, np.ndarray | None, str]:
    """Apply the ``unmatched`` policy to an association; return the frames kept, their poses and a report line.

    Args:
        frame_times_s: (N,) frame times in seconds (for the messages).
        match: (N,) index of each frame's ground-truth pose, -1 when none (:func:`associate_nearest`).
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
