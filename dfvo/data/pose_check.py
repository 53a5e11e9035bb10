"""Ground truth is checked before it is trusted: poses that cannot be a camera's are left out, with one line saying
which and why.

Convention:
    ``poses`` (N,4,4) float64 ``T_w_c``; a row of NaN is a frame without ground truth (every reader's convention,
    left out and counted by the metrics). :func:`checked_poses` returns a copy in which the rows that cannot be
    trusted are NaN too, and logs one warning per kind of problem naming ``source`` (the file or dataset) and the
    first frames:

    - **not finite**: a row with a NaN or an infinity that is not all NaN (a corrupt packet or line);
    - **not a rotation**: ``R`` with ``max |RᵀR − I| > ROTATION_TOLERANCE`` or ``det R < 0`` (a scaled, sheared or
      mirrored matrix; a text file's rounding to 6 digits stays well inside the tolerance);
    - **a jump**: a single frame whose position leaves the path and comes back, i.e. both of its steps are longer
      than ``JUMP_FACTOR`` × the median step and than ``JUMP_MIN_M``, while the step over it is not (a GNSS glitch
      no vehicle or hand makes). A lasting jump (every later position moved) cannot be mended frame by frame: it is
      named in a warning and kept.
"""

from __future__ import annotations

import logging

import numpy as np

__all__ = ["checked_poses", "ROTATION_TOLERANCE", "JUMP_FACTOR", "JUMP_MIN_M"]

log = logging.getLogger("dfvo.data")
ROTATION_TOLERANCE = 1e-3
JUMP_FACTOR = 10.0
JUMP_MIN_M = 1.0
SHOWN = 5  # frames named in a warning line


def _frames(idx: np.ndarray) -> str:
    shown = ", ".join(str(int(i)) for i in idx[:SHOWN])
    return shown + (f" and {len(idx) - SHOWN} more" if len(idx) > SHOWN else "")


def _not_rotations(R: np.ndarray) -> np.ndarray:
    """(N,) bool: ``R`` (N,3,3) is not a proper rotation within :data:`ROTATION_TOLERANCE`."""
    gram = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max(axis=(-1, -2))
    return (gram > ROTATION_TOLERANCE) | (np.linalg.det(R) < 0)


def _spikes(pos: np.ndarray, known: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(single-frame spikes, other jumps)``: frame indices (see the module docstring) among ``known`` frames."""
    idx = np.flatnonzero(known)
    if len(idx) < 3:
        return np.zeros(0, int), np.zeros(0, int)
    step = np.linalg.norm(np.diff(pos[idx], axis=0), axis=1)  # step k: from idx[k] to idx[k+1]
    moving = step[step > 0]
    if len(moving) == 0:
        return np.zeros(0, int), np.zeros(0, int)
    limit = max(JUMP_FACTOR * float(np.median(moving)), JUMP_MIN_M)
    long = step > limit
    over = np.linalg.norm(pos[idx[2:]] - pos[idx[:-2]], axis=1)  # the step over idx[k+1]
    spike = long[:-1] & long[1:] & (over <= limit)
    spikes = idx[1:-1][spike]
    in_spike = np.zeros(len(step), bool)
    in_spike[:-1] |= spike
    in_spike[1:] |= spike
    return spikes, idx[1:][long & ~in_spike]


def checked_poses(poses: np.ndarray | None, source: str) -> np.ndarray | None:
    """``poses`` (N,4,4) with the rows that cannot be a camera's pose set to NaN (see the module docstring).

    Args:
        poses: (N,4,4) ``T_w_c`` or None (no ground truth; returned as is).
        source: what the poses were read from, for the warning lines (a file, or ``data=… seq=…``).

    Returns:
        (N,4,4) float64, a copy; None when ``poses`` is None.

    Raises:
        ValueError: ``poses`` is not (N,4,4).
    """
    if poses is None:
        return None
    poses = np.array(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"{source}: ground-truth poses must be (N,4,4), got {poses.shape}")
    missing = np.isnan(poses).all(axis=(1, 2))
    finite = np.isfinite(poses).all(axis=(1, 2))
    corrupt = np.flatnonzero(~finite & ~missing)
    if len(corrupt):
        log.warning("%s: ground-truth pose of frame(s) %s is not finite (NaN or infinite numbers); those frames are "
                    "evaluated without ground truth", source, _frames(corrupt))
    bad_rotation = np.zeros(len(poses), bool)
    bad_rotation[finite] = _not_rotations(poses[finite, :3, :3])
    if bad_rotation.any():
        log.warning("%s: ground-truth pose of frame(s) %s is not a rotation (RᵀR ≠ I or det R < 0: scaled, sheared "
                    "or mirrored); those frames are evaluated without ground truth", source,
                    _frames(np.flatnonzero(bad_rotation)))
    known = finite & ~bad_rotation
    spikes, jumps = _spikes(poses[:, :3, 3], known)
    if len(spikes):
        log.warning("%s: ground-truth position of frame(s) %s jumps off the path and back (more than %.0fx the "
                    "median step), which no camera does; those frames are evaluated without ground truth", source,
                    _frames(spikes), JUMP_FACTOR)
    if len(jumps):
        log.warning("%s: the ground-truth path jumps at frame(s) %s (a step more than %.0fx the median, kept): the "
                    "metrics over them are not to be trusted", source, _frames(jumps), JUMP_FACTOR)
    poses[~known] = np.nan
    poses[spikes] = np.nan
    return poses
