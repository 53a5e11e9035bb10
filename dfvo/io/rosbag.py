"""ROS 2 bags without a ROS install: the trajectory as ``nav_msgs/msg/Odometry`` and ``tf2_msgs/msg/TFMessage``
(and the ground truth when there is one), written with the pure-Python ``rosbags`` library (the ``ros`` extra:
``pip install "dfvo[ros]"``).

Convention:
    - Topics: ``/dfvo/odometry`` (``nav_msgs/msg/Odometry``: ``header.frame_id`` = the world frame, ``child_frame_id``
      = the camera frame), ``/tf`` (``tf2_msgs/msg/TFMessage``: world -> camera), ``/dfvo/ground_truth``
      (``nav_msgs/msg/Odometry``, child ``<camera>_gt``, zero covariance; frames with ground truth only). One message
      per topic and frame, frame 0 included; the storage is sqlite3 (``BAG.db3``, what ``ros2 bag`` reads without
      plugins) or MCAP (``BAG.mcap``, ``storage="mcap"``: what Foxglove opens directly, and ``ros2 bag`` with its
      MCAP plugin), message definitions of ROS 2 Humble.
    - Frames: the world is the first camera's frame; the camera frame is the optical frame (x right, y down,
      z forward; REP 103's ``_optical`` convention), so ``pose`` is ``T_w_c`` exactly as in the trajectory file.
    - ``pose.covariance``: the world pose's covariance, propagated to first order from the per-frame step covariances
      (:func:`dfvo.tracking.covariance.propagate_pose_covariance`; frame 0 has zeros), in ROS order (x, y, z,
      rotation about X, Y, Z; fixed world axes). ``twist``: the step divided by the time between the frames, in the
      camera frame (linear, angular), with the step's covariance mapped the same way. Without timestamps the frames
      are stamped 0.1 s apart (:data:`NOMINAL_PERIOD_S`) and the twist is unknown (zero, ``covariance[0] = -1``).
    - Each message is inserted as its frame is produced and committed per frame, so a crash leaves the messages so
      far in ``BAG.db3`` (``ros2 bag reindex`` restores its ``metadata.yaml``); in MCAP each frame's messages are
      one chunk, written and flushed at once (a crash leaves an MCAP without its summary, which ``mcap recover``
      restores); :meth:`OdometryBagWriter.close` finalises the bag (the inference run calls it also when interrupted
      by Ctrl-C or SIGTERM).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dfvo.geometry.pose_covariance import (
    propagate_pose_covariance,
    ros_pose_covariance,
    ros_twist_covariance,
    so3_log,
)

__all__ = ["OdometryBagWriter", "ROS_HINT", "NOMINAL_PERIOD_S", "TOPIC_ODOMETRY", "TOPIC_TF", "TOPIC_GROUND_TRUTH",
           "STORAGES", "rotation_to_quaternion", "import_rosbags"]

ROS_HINT = 'output.rosbag=true needs the rosbags library: pip install "dfvo[ros]"'
NOMINAL_PERIOD_S = 0.1
TOPIC_ODOMETRY = "/dfvo/odometry"
TOPIC_TF = "/tf"
TOPIC_GROUND_TRUTH = "/dfvo/ground_truth"
ODOMETRY = "nav_msgs/msg/Odometry"
TF = "tf2_msgs/msg/TFMessage"
STORAGES = ("sqlite3", "mcap")


def import_rosbags() -> tuple[Any, Any]:
    """``(rosbags.rosbag2.Writer, the ROS 2 Humble typestore)``, or ``ImportError`` with :data:`ROS_HINT`."""
    try:
        from rosbags.rosbag2 import Writer
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise ImportError(ROS_HINT) from None
    return Writer, get_typestore(Stores.ROS2_HUMBLE)


def rotation_to_quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion ``(x, y, z, w)`` (ROS order, ``w >= 0``) of a (3,3) rotation matrix (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s
    v = np.asarray(q) / np.linalg.norm(q)
    if v[3] < 0:
        v = -v
    return float(v[0]), float(v[1]), float(v[2]), float(v[3])


class OdometryBagWriter:
    """Writes a trajectory frame by frame into a new ROS 2 bag folder (see the module docstring).

    Args:
        path: the bag folder to create (must not exist). world_frame, camera_frame: frame ids.
        ground_truth: (N,4,4) ``T_w_c`` of the frames (NaN rows: none), or None; written relative to its first pose
            (as the estimate starts at the identity).
        storage: ``sqlite3`` or ``mcap`` (:data:`STORAGES`).

    Raises:
        ImportError: ``rosbags`` missing (one line). FileExistsError: ``path`` exists. ValueError: another storage.
    """

    def __init__(self, path: str | Path, world_frame: str = "odom", camera_frame: str = "camera",
                 ground_truth: np.ndarray | None = None, storage: str = "sqlite3") -> None:
        if str(storage) not in STORAGES:
            raise ValueError(f"output.rosbag_storage={storage!r}; expected one of {list(STORAGES)}")
        Writer, self.typestore = import_rosbags()
        self.path = Path(path)
        if self.path.exists():
            raise FileExistsError(f"output.rosbag: {self.path} exists already; the bag is written into a new folder")
        self.world_frame, self.camera_frame = world_frame, camera_frame
        self.gt = None
        if ground_truth is not None:
            gt = np.asarray(ground_truth, dtype=np.float64)
            first = next((k for k in range(len(gt)) if np.isfinite(gt[k]).all()), None)
            self.gt = None if first is None else np.linalg.inv(gt[first]) @ gt
        from rosbags.rosbag2 import StoragePlugin

        plugin = StoragePlugin.MCAP if str(storage) == "mcap" else StoragePlugin.SQLITE3
        self.writer = Writer(self.path, version=9, storage_plugin=plugin)
        self.writer.open()
        ts = self.typestore
        self.conn_odom = self.writer.add_connection(TOPIC_ODOMETRY, ODOMETRY, typestore=ts)
        self.conn_tf = self.writer.add_connection(TOPIC_TF, TF, typestore=ts)
        self.conn_gt = self.writer.add_connection(TOPIC_GROUND_TRUTH, ODOMETRY, typestore=ts) \
            if self.gt is not None else None
        self.cov_w = torch.zeros(6, 6, dtype=torch.float64)
        self.T_w_prev: np.ndarray | None = None
        self.stamp_prev: float | None = None
        self.frames = 0
        self.closed = False

    # ------------------------------------------------------------------------------------------ messages
    def _header(self, stamp: float, frame_id: str) -> Any:
        T = self.typestore.types
        sec = math.floor(stamp)
        nanosec = min(int(round((stamp - sec) * 1e9)), 999_999_999)
        return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=int(sec), nanosec=nanosec),
                                        frame_id=frame_id)

    def _pose(self, T_w_c: np.ndarray) -> Any:
        T = self.typestore.types
        x, y, z, w = rotation_to_quaternion(T_w_c[:3, :3])
        return T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=float(T_w_c[0, 3]), y=float(T_w_c[1, 3]), z=float(T_w_c[2, 3])),
            orientation=T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w))

    def _odometry(self, stamp: float, child: str, T_w_c: np.ndarray, pose_cov: list[float],
                  twist: tuple[np.ndarray, np.ndarray], twist_cov: list[float]) -> Any:
        T = self.typestore.types
        v, w = twist
        vec = T["geometry_msgs/msg/Vector3"]
        return T[ODOMETRY](
            header=self._header(stamp, self.world_frame), child_frame_id=child,
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=self._pose(T_w_c),
                                                          covariance=np.asarray(pose_cov, dtype=np.float64)),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](linear=vec(x=float(v[0]), y=float(v[1]), z=float(v[2])),
                                                   angular=vec(x=float(w[0]), y=float(w[1]), z=float(w[2]))),
                covariance=np.asarray(twist_cov, dtype=np.float64)))

    def _tf(self, stamp: float, T_w_c: np.ndarray) -> Any:
        T = self.typestore.types
        x, y, z, w = rotation_to_quaternion(T_w_c[:3, :3])
        transform = T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=float(T_w_c[0, 3]), y=float(T_w_c[1, 3]),
                                                       z=float(T_w_c[2, 3])),
            rotation=T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w))
        return T[TF](transforms=[T["geometry_msgs/msg/TransformStamped"](
            header=self._header(stamp, self.world_frame), child_frame_id=self.camera_frame, transform=transform)])

    def _put(self, conn: Any, msg: Any, msgtype: str, stamp: float) -> None:
        self.writer.write(conn, int(round(stamp * 1e9)), self.typestore.serialize_cdr(msg, msgtype))

    # ------------------------------------------------------------------------------------------ frames
    def write(self, index: int, T_w_c: np.ndarray, covariance: torch.Tensor | np.ndarray | None,
              timestamp: float | None = None) -> None:
        """Frame ``index`` with its pose ``T_w_c`` (4,4) and its step's covariance (6,6; None or frame 0: zeros),
        taken at ``timestamp`` seconds (None: ``index * NOMINAL_PERIOD_S``, twist unknown). Frames come in order."""
        T_w_c = np.asarray(T_w_c, dtype=np.float64)
        stamp = float(timestamp) if timestamp is not None else index * NOMINAL_PERIOD_S
        cov_step = torch.zeros(6, 6, dtype=torch.float64) if covariance is None else \
            torch.as_tensor(np.asarray(covariance), dtype=torch.float64)
        twist = (np.zeros(3), np.zeros(3))
        twist_cov = [0.0] * 36
        if self.T_w_prev is None:
            self.cov_w = torch.zeros(6, 6, dtype=torch.float64)
        else:
            T_step = np.linalg.inv(self.T_w_prev) @ T_w_c
            self.cov_w = propagate_pose_covariance(self.cov_w, torch.from_numpy(self.T_w_prev), cov_step,
                                                   torch.from_numpy(T_step))
            dt = None if timestamp is None or self.stamp_prev is None else stamp - self.stamp_prev
            if dt is not None and dt > 0:
                Rt = T_step[:3, :3].T
                twist = (Rt @ T_step[:3, 3] / dt, Rt @ so3_log(T_step[:3, :3]).numpy() / dt)
                twist_cov = ros_twist_covariance(cov_step, torch.from_numpy(T_step), dt)
            else:
                twist_cov[0] = -1.0  # unknown (no time between the frames)
        pose_cov = ros_pose_covariance(self.cov_w)
        self._put(self.conn_odom, self._odometry(stamp, self.camera_frame, T_w_c, pose_cov, twist, twist_cov),
                  ODOMETRY, stamp)
        self._put(self.conn_tf, self._tf(stamp, T_w_c), TF, stamp)
        if self.conn_gt is not None and index < len(self.gt) and np.isfinite(self.gt[index]).all():
            self._put(self.conn_gt, self._odometry(stamp, f"{self.camera_frame}_gt", self.gt[index], [0.0] * 36,
                                                   (np.zeros(3), np.zeros(3)), [0.0] * 36), ODOMETRY, stamp)
        self._commit()
        self.T_w_prev, self.stamp_prev = T_w_c, stamp
        self.frames += 1

    def _commit(self) -> None:
        # the sqlite3 storage of rosbags keeps one transaction until close, its MCAP storage a chunk of up to 1 MiB in
        # memory; committing (closing the chunk and flushing) per frame makes the messages so far durable
        # (attributes of the library's storage objects: nothing happens if they have another shape)
        storage = getattr(self.writer, "storage", None)
        conn = getattr(storage, "conn", None)
        if conn is not None and hasattr(conn, "commit"):
            conn.commit()
        chunk, bio = getattr(storage, "chunk", None), getattr(storage, "bio", None)
        if hasattr(storage, "close_chunk") and hasattr(getattr(chunk, "bio", None), "tell") and chunk.bio.tell() \
                and hasattr(bio, "flush"):
            storage.close_chunk()
            bio.flush()

    def close(self) -> None:
        """Finalise the bag (``metadata.yaml``); idempotent."""
        if not self.closed:
            self.closed = True
            self.writer.close()

    def __enter__(self) -> OdometryBagWriter:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
