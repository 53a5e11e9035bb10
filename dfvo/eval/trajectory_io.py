"""Trajectory files: KITTI pose format (12 numbers a line) and TUM format, read and write.

Convention:
    Poses are camera-to-world ``T_w_c`` as ``(N, 4, 4)`` float64 numpy arrays. KITTI files hold the first
    three rows of each matrix, row-major. TUM files hold ``timestamp tx ty tz qx qy qz qw`` (Hamilton
    quaternion, scalar last). Malformed lines raise ``ValueError`` naming the file, the line and its content.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _parse_lines(path: Path, expected: int) -> np.ndarray:
    if not path.is_file():
        raise FileNotFoundError(f"trajectory file {path} does not exist")
    rows: list[list[float]] = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        parts = stripped.replace(",", " ").split()
        if len(parts) != expected:
            raise ValueError(f"{path}:{lineno}: expected {expected} numbers, got {len(parts)}: {stripped!r}")
        try:
            values = [float(p) for p in parts]
        except ValueError:
            raise ValueError(f"{path}:{lineno}: non-numeric value in line: {stripped!r}") from None
        if not np.all(np.isfinite(values)):
            raise ValueError(f"{path}:{lineno}: non-finite value in line: {stripped!r}")
        rows.append(values)
    if not rows:
        raise ValueError(f"{path}: empty trajectory file (expected lines of {expected} numbers)")
    return np.asarray(rows, dtype=np.float64)


def read_kitti_poses(path: str | Path) -> np.ndarray:
    """Read a KITTI pose file.

    Args:
        path: text file, one pose per line, 12 numbers (the 3x4 ``[R|t]`` row-major).

    Returns:
        ``(N, 4, 4)`` float64 poses ``T_w_c``.
    """
    values = _parse_lines(Path(path), 12)
    poses = np.tile(np.eye(4), (len(values), 1, 1))
    poses[:, :3, :] = values.reshape(-1, 3, 4)
    return poses


def _check_poses(poses: np.ndarray) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] not in ((4, 4), (3, 4)):
        raise ValueError(f"poses must have shape (N,4,4) or (N,3,4), got {poses.shape}")
    return poses


def write_kitti_poses(path: str | Path, poses: np.ndarray) -> None:
    """Write ``(N, 4, 4)`` or ``(N, 3, 4)`` poses as a KITTI pose file (12 numbers a line)."""
    poses = _check_poses(poses)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path, poses[:, :3, :].reshape(-1, 12), fmt="%.9e")


def rotation_to_quaternion(rot: np.ndarray) -> np.ndarray:
    """``(N,3,3)`` rotation matrices -> ``(N,4)`` unit quaternions ``(qx, qy, qz, qw)`` with ``qw >= 0``."""
    m = rot
    tr = np.trace(m, axis1=1, axis2=2)
    cand = np.stack([1 + 2 * m[:, 0, 0] - tr, 1 + 2 * m[:, 1, 1] - tr, 1 + 2 * m[:, 2, 2] - tr, 1 + tr], axis=1)
    k = np.argmax(cand, axis=1)
    q = np.empty((len(m), 4))
    # 4*q_k*q_* from the off-diagonal sums/differences, choosing the numerically largest component k.
    sym = {(0, 1): m[:, 0, 1] + m[:, 1, 0], (0, 2): m[:, 0, 2] + m[:, 2, 0], (1, 2): m[:, 1, 2] + m[:, 2, 1]}
    skew = {0: m[:, 2, 1] - m[:, 1, 2], 1: m[:, 0, 2] - m[:, 2, 0], 2: m[:, 1, 0] - m[:, 0, 1]}
    for i in range(len(m)):
        c = k[i]
        s = np.sqrt(max(cand[i, c], 1e-300))
        v = np.empty(4)
        v[c] = 0.5 * s
        for j in range(3):
            if j != c:
                v[j] = (sym[(min(c, j), max(c, j))][i] if c < 3 else skew[j][i]) / (2 * s)
        if c < 3:
            v[3] = skew[c][i] / (2 * s)
        q[i] = v
    q *= np.where(q[:, 3:] < 0, -1.0, 1.0)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """``(N,4)`` quaternions ``(qx, qy, qz, qw)`` (normalised here) -> ``(N,3,3)`` rotation matrices."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], 1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], 1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], 1),
    ], 1)


def read_tum_poses(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory file.

    Returns:
        ``(timestamps (N,), poses (N,4,4))``.
    """
    path = Path(path)
    values = _parse_lines(path, 8)
    norms = np.linalg.norm(values[:, 4:], axis=1)
    if np.any(norms < 1e-12):
        bad = int(np.argmax(norms < 1e-12))
        raise ValueError(f"{path}: zero quaternion in data row {bad + 1}")
    poses = np.tile(np.eye(4), (len(values), 1, 1))
    poses[:, :3, :3] = quaternion_to_rotation(values[:, 4:])
    poses[:, :3, 3] = values[:, 1:4]
    return values[:, 0], poses


def write_tum_poses(path: str | Path, poses: np.ndarray, timestamps: np.ndarray | None = None) -> None:
    """Write poses as ``timestamp tx ty tz qx qy qz qw``; timestamps default to the frame index."""
    poses = _check_poses(poses)
    stamps = np.arange(len(poses), dtype=np.float64) if timestamps is None else np.asarray(timestamps, float)
    if stamps.shape != (len(poses),):
        raise ValueError(f"timestamps must have shape ({len(poses)},), got {stamps.shape}")
    data = np.concatenate([stamps[:, None], poses[:, :3, 3], rotation_to_quaternion(poses[:, :3, :3])], axis=1)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path, data, fmt="%.9f")
