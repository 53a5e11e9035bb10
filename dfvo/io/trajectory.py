"""Trajectory files, read and written: KITTI (12 or 13 numbers a line), TUM and EuRoC ground-truth CSV.

Convention:
    A :class:`Trajectory` holds camera-to-world poses ``T_w_c`` ``(N,4,4)`` float64, optionally timestamps ``(N,)``
    in seconds and frame indices ``(N,)`` int64, sorted by time (or by frame index).

    - ``kitti``: one pose a line, the top 3x4 of ``T_w_c`` row-major (12 numbers), optionally preceded by the
      frame index (13 numbers: the layout of the DF-VO authors' KITTI toolkit; frames may be sparse).
    - ``tum``: ``timestamp tx ty tz qx qy qz qw`` (seconds; Hamilton quaternion, scalar last); ``#`` comments.
    - ``euroc``: ``state_groundtruth_estimate0/data.csv``: a ``#timestamp [ns], p_RS_R_x, p_RS_R_y, p_RS_R_z,
      q_RS_w, q_RS_x, q_RS_y, q_RS_z, ...`` header, comma-separated rows; integer nanoseconds; quaternion
      scalar first; the columns after the quaternion (velocity, biases) are ignored. The pose is the body
      (IMU) frame's: moving it to the camera needs ``T_BS`` from ``cam0/sensor.yaml``.

    ``format="auto"`` decides from the content: a ``,``-separated file or a ``#timestamp`` header is EuRoC,
    else 12/13 numbers a line are KITTI and 8 are TUM. Malformed input raises ``ValueError`` (missing files
    ``FileNotFoundError``) with one line naming the file, the line and what was expected.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np

FORMATS = ("auto", "kitti", "tum", "euroc")
WRITE_FORMATS = ("kitti", "tum", "euroc")
EUROC_HEADER = "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []"
# where the ground truth lies inside a dataset folder (EuRoC mav0 / sequence folder, TUM RGB-D sequence folder)
GT_FILES_IN_FOLDER = ("mav0/state_groundtruth_estimate0/data.csv", "state_groundtruth_estimate0/data.csv",
                      "data.csv", "groundtruth.txt")


@dataclass
class Trajectory:
    """A trajectory: ``poses`` ``(N,4,4)`` ``T_w_c``, optional ``timestamps`` ``(N,)`` s, optional ``frame_ids``
    ``(N,)``; ``source`` names the file it came from (for messages)."""

    poses: np.ndarray
    timestamps: np.ndarray | None = None
    frame_ids: np.ndarray | None = None
    source: str = "<memory>"

    def __post_init__(self) -> None:
        self.poses = _check_poses(self.poses)
        if self.poses.shape[1] == 3:
            full = np.tile(np.eye(4), (len(self.poses), 1, 1))
            full[:, :3] = self.poses
            self.poses = full
        n = len(self.poses)
        for name, dtype in (("timestamps", np.float64), ("frame_ids", np.int64)):
            value = getattr(self, name)
            if value is not None:
                value = np.asarray(value, dtype=dtype)
                if value.shape != (n,):
                    raise ValueError(f"{self.source}: {name} must have shape ({n},), got {value.shape}")
                setattr(self, name, value)

    def __len__(self) -> int:
        return len(self.poses)

    def select(self, index: np.ndarray | slice) -> Trajectory:
        """The poses (and their stamps / ids) at ``index`` (integer array, bool mask or slice)."""
        stamps = None if self.timestamps is None else self.timestamps[index]
        ids = None if self.frame_ids is None else self.frame_ids[index]
        return Trajectory(self.poses[index], stamps, ids, self.source)


def _check_poses(poses: np.ndarray) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] not in ((4, 4), (3, 4)):
        raise ValueError(f"poses must have shape (N,4,4) or (N,3,4), got {poses.shape}")
    return poses


# ------------------------------------------------------------------------------------------------ quaternions


def rotation_to_quaternion(rot: np.ndarray) -> np.ndarray:
    """``(N,3,3)`` rotation matrices -> ``(N,4)`` unit quaternions ``(qx, qy, qz, qw)`` with ``qw >= 0``."""
    m = np.asarray(rot, np.float64)
    tr = np.trace(m, axis1=1, axis2=2)
    # 4 q_k^2 for k = x, y, z, w; build from the largest for accuracy (Shepperd's method).
    cand = np.stack([1 + 2 * m[:, 0, 0] - tr, 1 + 2 * m[:, 1, 1] - tr, 1 + 2 * m[:, 2, 2] - tr, 1 + tr], axis=1)
    k = np.argmax(cand, axis=1)
    s = 2.0 * np.sqrt(np.maximum(cand[np.arange(len(m)), k], 1e-300))  # 4 |q_k|
    sxy, sxz, syz = m[:, 0, 1] + m[:, 1, 0], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 2] + m[:, 2, 1]
    dx, dy, dz = m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]
    rows = {  # (qx, qy, qz, qw) * 4 q_k for each choice of k
        0: (cand[:, 0], sxy, sxz, dx), 1: (sxy, cand[:, 1], syz, dy),
        2: (sxz, syz, cand[:, 2], dz), 3: (dx, dy, dz, cand[:, 3]),
    }
    q = np.empty((len(m), 4))
    for c, cols in rows.items():
        sel = k == c
        q[sel] = np.stack([v[sel] for v in cols], axis=1) / s[sel, None]
    q *= np.where(q[:, 3:] < 0, -1.0, 1.0)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """``(N,4)`` quaternions ``(qx, qy, qz, qw)`` (normalised here) -> ``(N,3,3)`` rotation matrices."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], 1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], 1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], 1),
    ], 1)


# ------------------------------------------------------------------------------------------------ reading


def _data_lines(path: Path) -> list[tuple[int, str]]:
    """``(line number, stripped text)`` of the non-empty, non-``#`` lines of ``path``."""
    if not path.is_file():
        raise FileNotFoundError(f"trajectory file {path} does not exist")
    lines = [(n, s.strip()) for n, s in enumerate(path.read_text().splitlines(), start=1)]
    return [(n, s) for n, s in lines if s and not s.startswith("#")]


def _parse(path: Path, lines: list[tuple[int, str]], counts: tuple[int, ...], what: str, comma: bool = False,
           at_least: bool = False) -> np.ndarray:
    """Rows of numbers, all with the same count from ``counts`` (or ``>= counts[0]`` with ``at_least``)."""
    if not lines:
        raise ValueError(f"{path}: empty trajectory file (expected lines of {what})")
    rows: list[list[float]] = []
    width = None
    for lineno, text in lines:
        parts = [p.strip() for p in text.split(",")] if comma else text.replace(",", " ").split()
        ok = len(parts) >= counts[0] if at_least else len(parts) in counts
        if not ok or (width is not None and len(parts) != width):
            expected = f"{width} numbers" if width is not None else what
            raise ValueError(f"{path}:{lineno}: expected {expected}, got {len(parts)}: {text!r}")
        width = len(parts)
        try:
            rows.append([float(p) for p in parts])
        except ValueError:
            raise ValueError(f"{path}:{lineno}: non-numeric value in line: {text!r}") from None
    values = np.asarray(rows, dtype=np.float64)
    bad = np.flatnonzero(~np.isfinite(values).all(axis=1))
    if len(bad):
        lineno, text = lines[bad[0]]
        raise ValueError(f"{path}:{lineno}: non-finite value in line: {text!r}")
    return values


def _poses_from_quaternions(path: Path, lines: list[tuple[int, str]], xyz: np.ndarray, q_xyzw: np.ndarray):
    norms = np.linalg.norm(q_xyzw, axis=1)
    if np.any(norms < 1e-12):
        lineno, text = lines[int(np.argmax(norms < 1e-12))]
        raise ValueError(f"{path}:{lineno}: zero quaternion: {text!r}")
    poses = np.tile(np.eye(4), (len(xyz), 1, 1))
    poses[:, :3, :3] = quaternion_to_rotation(q_xyzw)
    poses[:, :3, 3] = xyz
    return poses


def _sorted_by(traj: Trajectory, key: np.ndarray) -> Trajectory:
    order = np.argsort(key, kind="stable")
    return traj if np.all(order == np.arange(len(order))) else traj.select(order)


def read_kitti(path: str | Path) -> Trajectory:
    """KITTI poses, 12 numbers a line or 13 with a leading frame index (kept as ``frame_ids``; sorted by it)."""
    path = Path(path)
    lines = _data_lines(path)
    values = _parse(path, lines, (12, 13), "12 numbers (3x4 [R|t] row-major) or 13 (frame index + 12)")
    poses = np.tile(np.eye(4), (len(values), 1, 1))
    poses[:, :3, :] = values[:, -12:].reshape(-1, 3, 4)
    if values.shape[1] == 12:
        return Trajectory(poses, source=str(path))
    ids = values[:, 0]
    bad = np.flatnonzero((ids < 0) | (ids != np.round(ids)))
    if len(bad):
        lineno, text = lines[bad[0]]
        raise ValueError(f"{path}:{lineno}: the first of 13 numbers must be a frame index (integer >= 0): {text!r}")
    traj = _sorted_by(Trajectory(poses, frame_ids=ids.astype(np.int64), source=str(path)), ids)
    dup = np.flatnonzero(np.diff(traj.frame_ids) == 0)
    if len(dup):
        raise ValueError(f"{path}: frame index {traj.frame_ids[dup[0]]} appears more than once")
    return traj


def read_tum(path: str | Path) -> Trajectory:
    """TUM ``timestamp tx ty tz qx qy qz qw`` lines (sorted by time)."""
    path = Path(path)
    lines = _data_lines(path)
    values = _parse(path, lines, (8,), "8 numbers (timestamp tx ty tz qx qy qz qw)")
    poses = _poses_from_quaternions(path, lines, values[:, 1:4], values[:, 4:8])
    return _sorted_by(Trajectory(poses, timestamps=values[:, 0], source=str(path)), values[:, 0])


def read_euroc(path: str | Path) -> Trajectory:
    """EuRoC ground-truth CSV (ns timestamps, position, quaternion w x y z, ...); timestamps in seconds."""
    path = Path(path)
    lines = _data_lines(path)
    values = _parse(path, lines, (8,), "at least 8 comma-separated numbers (timestamp [ns], p xyz, q wxyz)",
                    comma=True, at_least=True)
    poses = _poses_from_quaternions(path, lines, values[:, 1:4], values[:, [5, 6, 7, 4]])
    return _sorted_by(Trajectory(poses, timestamps=values[:, 0] * 1e-9, source=str(path)), values[:, 0])


READERS = {"kitti": read_kitti, "tum": read_tum, "euroc": read_euroc}


def resolve_trajectory_file(path: str | Path) -> Path:
    """``path`` itself when it is a file; for a dataset folder, its ground-truth file (:data:`GT_FILES_IN_FOLDER`)."""
    path = Path(path)
    if path.is_dir():
        for name in GT_FILES_IN_FOLDER:
            if (path / name).is_file():
                return path / name
        raise FileNotFoundError(f"{path} is a folder without a trajectory file (looked for "
                                f"{', '.join(GT_FILES_IN_FOLDER)})")
    if not path.is_file():
        raise FileNotFoundError(f"trajectory file {path} does not exist")
    return path


def detect_format(path: str | Path) -> str:
    """``kitti``, ``tum`` or ``euroc`` from the content of ``path`` (see the module's Convention)."""
    path = Path(path)
    with path.open() as f:
        head = [line.strip() for _, line in zip(range(50), f)]
    if any(s.startswith("#") and "timestamp" in s.lower() and "," in s for s in head):
        return "euroc"
    data = [s for s in head if s and not s.startswith("#")]
    if not data:
        raise ValueError(f"{path}: empty trajectory file (no data line to detect its format from)")
    if "," in data[0]:
        return "euroc"
    n = len(data[0].split())
    if n in (12, 13):
        return "kitti"
    if n == 8:
        return "tum"
    raise ValueError(f"{path}: cannot detect the trajectory format: the first data line has {n} numbers; expected "
                     "12 or 13 (kitti), 8 (tum: t tx ty tz qx qy qz qw) or a EuRoC CSV")


def read_trajectory(path: str | Path, format: str = "auto") -> Trajectory:
    """Read ``path`` (a file, or a dataset folder holding its ground truth) in ``format`` (``auto|kitti|tum|euroc``)."""
    if format not in FORMATS:
        raise ValueError(f"format={format!r}: expected one of {FORMATS}")
    path = resolve_trajectory_file(path)
    return READERS[detect_format(path) if format == "auto" else format](path)


def read_times(path: str | Path) -> np.ndarray:
    """A KITTI ``times.txt``: one timestamp (s) a line -> ``(N,)`` float64, strictly increasing (frame times that
    repeat or go back would pair frames with the wrong ground truth without a word).

    Raises:
        ValueError: a malformed or non-finite line, or a time not after the one before (file and line named).
    """
    path = Path(path)
    lines = _data_lines(path)
    times = _parse(path, lines, (1,), "one number (seconds)")[:, 0]
    back = np.flatnonzero(np.diff(times) <= 0)
    if len(back):
        k = int(back[0]) + 1
        raise ValueError(f"{path}:{lines[k][0]}: time {times[k]:.9g} s is not after the line before "
                         f"({times[k - 1]:.9g} s; {len(back)} such); expected one increasing time per frame")
    return times


def read_kitti_poses(path: str | Path) -> np.ndarray:
    """The ``(N,4,4)`` poses of a KITTI pose file (12 or 13 numbers a line; sorted by frame index)."""
    return read_kitti(path).poses


def read_tum_poses(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """``(timestamps (N,), poses (N,4,4))`` of a TUM trajectory file."""
    traj = read_tum(path)
    return traj.timestamps, traj.poses


# ------------------------------------------------------------------------------------------------ writing


def kitti_line(T_w_c: np.ndarray, frame_id: int | None = None) -> str:
    """One KITTI line for a ``(4,4)`` (or ``(3,4)``) pose: 12 numbers, 13 with a leading ``frame_id``."""
    text = " ".join(f"{v:.9e}" for v in np.asarray(T_w_c, dtype=np.float64)[:3, :4].reshape(-1))
    return text if frame_id is None else f"{int(frame_id)} {text}"


def tum_line(timestamp: float, T_w_c: np.ndarray, q_xyzw: np.ndarray | None = None) -> str:
    """One TUM line ``timestamp tx ty tz qx qy qz qw`` for a ``(4,4)`` pose (``q_xyzw``: its quaternion if known)."""
    T = np.asarray(T_w_c, dtype=np.float64)
    q = rotation_to_quaternion(T[None, :3, :3])[0] if q_xyzw is None else q_xyzw
    return f"{float(timestamp):.9f} " + " ".join(f"{v:.9e}" for v in (*T[:3, 3], *q))


def _stamps(poses: np.ndarray, timestamps: np.ndarray | None, what: str) -> np.ndarray:
    if timestamps is None:
        raise ValueError(f"the {what} format needs one timestamp per pose")
    stamps = np.asarray(timestamps, dtype=np.float64)
    if stamps.shape != (len(poses),):
        raise ValueError(f"timestamps must have shape ({len(poses)},), got {stamps.shape}")
    return stamps


def _write_lines(path: str | Path, lines: list[str]) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(line + "\n" for line in lines))
    return path


def write_kitti_poses(path: str | Path, poses: np.ndarray, frame_ids: np.ndarray | None = None) -> Path:
    """Write ``(N,4,4)`` / ``(N,3,4)`` poses as KITTI lines (13 numbers when ``frame_ids`` ``(N,)`` is given)."""
    poses = _check_poses(poses)
    ids = [None] * len(poses) if frame_ids is None else [int(i) for i in np.asarray(frame_ids).reshape(-1)]
    if len(ids) != len(poses):
        raise ValueError(f"frame_ids must have {len(poses)} entries, got {len(ids)}")
    return _write_lines(path, [kitti_line(T, i) for T, i in zip(poses, ids)])


def write_tum_poses(path: str | Path, poses: np.ndarray, timestamps: np.ndarray | None = None) -> Path:
    """Write poses as TUM lines; ``timestamps`` ``(N,)`` s default to the frame index."""
    poses = _check_poses(poses)
    stamps = _stamps(poses, np.arange(len(poses), dtype=float) if timestamps is None else timestamps, "tum")
    q = rotation_to_quaternion(poses[:, :3, :3])
    return _write_lines(path, [tum_line(t, T, qi) for t, T, qi in zip(stamps, poses, q)])


def write_euroc_poses(path: str | Path, poses: np.ndarray, timestamps: np.ndarray) -> Path:
    """Write poses as a EuRoC ground-truth CSV (header, ns timestamps, position, quaternion w x y z)."""
    poses = _check_poses(poses)
    stamps = _stamps(poses, timestamps, "euroc")
    q = rotation_to_quaternion(poses[:, :3, :3])[:, [3, 0, 1, 2]]
    rows = [f"{round(t * 1e9)}," + ",".join(f"{v:.9e}" for v in (*T[:3, 3], *qi)) for t, T, qi in zip(stamps, poses, q)]
    return _write_lines(path, [EUROC_HEADER, *rows])


def write_trajectory(path: str | Path, traj: Trajectory, format: str = "kitti") -> Path:
    """Write ``traj`` as ``kitti`` (13 numbers when it has ``frame_ids``), ``tum`` or ``euroc``."""
    if format == "kitti":
        return write_kitti_poses(path, traj.poses, traj.frame_ids)
    if format == "tum":
        return write_tum_poses(path, traj.poses, _stamps(traj.poses, traj.timestamps, "tum"))
    if format == "euroc":
        return write_euroc_poses(path, traj.poses, traj.timestamps)
    raise ValueError(f"format={format!r}: expected one of {WRITE_FORMATS}")


class TrajectoryWriter:
    """Streaming trajectory file: one flushed line per pose (an interrupted run leaves a valid prefix).

    Args:
        path: output file (parents created, truncated on open).
        format: ``"kitti"`` (12 numbers a line) or ``"tum"`` (``timestamp tx ty tz qx qy qz qw``; every
            :meth:`write` then needs its ``timestamp`` in seconds).

    Example:
        >>> with TrajectoryWriter(out / "06.txt", "tum") as w:  # doctest: +SKIP
        ...     w.write(T_w_c, timestamp=t)
    """

    def __init__(self, path: str | Path, format: str = "kitti") -> None:
        if format not in ("kitti", "tum"):
            raise ValueError(f"pose_format={format!r}: expected 'kitti' or 'tum'")
        self.path, self.format, self.count = Path(path), format, 0
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f: TextIO = self.path.open("w")

    def write(self, T_w_c: np.ndarray, timestamp: float | None = None) -> None:
        """Append one ``(4,4)`` camera-to-world pose (``timestamp`` in s, required for ``tum``)."""
        T = np.asarray(T_w_c, dtype=np.float64)
        if T.shape not in ((4, 4), (3, 4)):
            raise ValueError(f"{self.path}: a pose must have shape (4,4) or (3,4), got {T.shape}")
        if self.format == "tum":
            if timestamp is None:
                raise ValueError(f"{self.path}: pose_format=tum needs a timestamp for every pose (frame {self.count} "
                                 "has none); use pose_format=kitti for frames without timestamps")
            line = tum_line(timestamp, T)
        else:
            line = kitti_line(T)
        self._f.write(line + "\n")
        self._f.flush()
        self.count += 1

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> TrajectoryWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
