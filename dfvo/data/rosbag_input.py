"""ROS 1 and ROS 2 bags as frame sequences: the images of one camera topic, its calibration, and ground truth from a
pose topic of the same bag, read with the pure-Python ``rosbags`` library (the ``ros`` extra; no ROS install).

Convention:
    - A bag is a ROS 1 ``.bag`` file, a ROS 2 bag folder (``metadata.yaml`` beside its storage files) or one ROS 2
      storage file (``.db3``: sqlite3, ``.mcap``). A ROS 2 folder without ``metadata.yaml`` that holds one storage
      file (a recording cut short) is read from that file, with a warning.
    - Frames are the messages of one image topic (``sensor_msgs/Image`` or ``sensor_msgs/CompressedImage``) in the
      order of their header stamps: ``timestamps[i]`` is frame ``i``'s ``header.stamp`` in float64 seconds
      (``sec + nanosec * 1e-9``). Messages received out of order are sorted, a stamp received twice is one frame
      (the first message received) and gaps stay as they are, as ``data=video`` sorts and de-duplicates its
      presentation times and keeps a variable frame rate; one warning line counts what was sorted and dropped.
      Stamps that are all zero (a driver that does not stamp) are replaced by the bag's receive times, with a
      warning.
    - Pixels: ``mono8``/``8UC1``, ``mono16``/``16UC1``, ``rgb8``, ``bgr8``, ``rgba8``, ``bgra8``, ``rgb16``, ``bgr16``
      and the 8-bit Bayer mosaics ``bayer_rggb8``, ``bayer_bggr8``, ``bayer_gbrg8``, ``bayer_grbg8`` (kornia's
      bilinear demosaicking, :func:`debayer`) become (3,H,W) float32 RGB in [0,1] exactly as
      :func:`dfvo.data.image_io.array_to_image` converts the same pixels (8-bit / 255, 16-bit / 65535 or 12-bit
      data / 4095, grey replicated); a ``CompressedImage`` (JPEG, PNG) is decoded by Pillow as a file of the same bytes
      (:func:`dfvo.data.image_io.decode_image`). So a frame equals the PNG of its pixels read by ``data=folder``.
      The first pass reads the stamps only; frames are decoded on demand (in order: each message read once) and the
      last ``cache`` kept.
    - Intrinsics ``fx, fy, cx, cy`` in pixels of the stored frames and OpenCV distortion come from the camera's
      ``sensor_msgs/CameraInfo`` (the first message): ``K`` of the full sensor is moved to the image by ``binning``
      and ``roi`` as ROS's image_geometry does (``fx / binning_x``, ``(cx - roi.x_offset) / binning_x``, the same in
      y); ``D`` of ``plumb_bob`` (5 coefficients) or ``rational_polynomial`` (8) is OpenCV's order. Values given
      as settings (``data.fx`` ... ``data.dist``) replace the CameraInfo's, one warning line naming those that
      disagree. They are checked by :mod:`dfvo.data.intrinsics_check` and frames are undistorted as ``data=folder``
      does (:class:`~dfvo.data.image_folder.FramePrep`).
    - Ground truth: a pose topic (``geometry_msgs/PoseStamped``, ``nav_msgs/Odometry``,
      ``geometry_msgs/TransformStamped``, ``tf2_msgs/TFMessage``) gives ``T_parent_body`` (4,4, metres) at its header
      stamps; the camera's pose is ``T_w_c = T_parent_body @ T_body_camera``, where ``T_body_camera`` is given
      (``[x, y, z, qx, qy, qz, qw]``, ROS order, or 16 numbers of a row-major 4x4) or composed along the bag's
      ``/tf_static`` tree from the body's frame to the images' ``header.frame_id`` (the identity when the body is the
      camera's frame, or when a ``PoseStamped`` names no body: then its poses are the camera's). Each frame takes
      the pose of nearest stamp within ``gt_tolerance`` seconds (:func:`dfvo.data.timed_poses.associate_frames`,
      i.e. :func:`dfvo.io.association.match_timestamps`); frames without one get NaN poses.
    - ``rosbags`` is imported on use: without it, :func:`open_rosbag` raises ``ImportError`` with one line
      (:data:`ROSBAG_HINT`).
"""

from __future__ import annotations

import logging
import sqlite3
import struct
import threading
import weakref
from collections import Counter, OrderedDict, deque
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dfvo.data.image_folder import FramePrep
from dfvo.data.image_io import DatasetError, DatasetNotFoundError, array_to_image, decode_image
from dfvo.data.intrinsics_check import check_intrinsics
from dfvo.data.sequence import FrameSequence
from dfvo.data.timed_poses import associate_frames, attach_ground_truth
from dfvo.geometry.camera import intrinsics_matrix
from dfvo.io.trajectory import quaternion_to_rotation

__all__ = ["ROSBAG_HINT", "ENCODINGS", "seconds", "IMAGE_TYPES", "POSE_TYPES", "RosBag", "BagImages", "BagCamera",
           "PoseTrack", "image_array", "debayer", "camera_from_info", "read_pose_topic", "static_transforms",
           "chain_transform", "body_to_camera", "open_rosbag"]

log = logging.getLogger("dfvo.data")

ROSBAG_HINT = 'data=rosbag needs the rosbags library: pip install "dfvo[ros]"'
BAG_EXPECTED = "expected a ROS 1 .bag file, a ROS 2 bag folder (metadata.yaml) or a ROS 2 .db3/.mcap file"
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
IMAGE_TYPES = (IMAGE, COMPRESSED)
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
TRANSFORM_STAMPED = "geometry_msgs/msg/TransformStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
POSE_TYPES = (POSE_STAMPED, ODOMETRY, TRANSFORM_STAMPED, TF_MESSAGE)
TF_STATIC = "/tf_static"
SEEK_AHEAD = 16  # read forward rather than restart when the wanted frame is at most this many messages ahead
DISTORTION_COUNTS = {"plumb_bob": 5, "rational_polynomial": 8}

# encoding (as ROS names it; matched ignoring case) -> (channels, numpy dtype, layout)
ENCODINGS: dict[str, tuple[int, str, str]] = {
    "mono8": (1, "u1", "mono"), "8UC1": (1, "u1", "mono"),
    "mono16": (1, "u2", "mono"), "16UC1": (1, "u2", "mono"),
    "rgb8": (3, "u1", "rgb"), "bgr8": (3, "u1", "bgr"), "rgba8": (4, "u1", "rgba"), "bgra8": (4, "u1", "bgra"),
    "rgb16": (3, "u2", "rgb"), "bgr16": (3, "u2", "bgr"),
    "bayer_rggb8": (1, "u1", "rggb"), "bayer_bggr8": (1, "u1", "bggr"), "bayer_gbrg8": (1, "u1", "gbrg"),
    "bayer_grbg8": (1, "u1", "grbg"),
}
_ENCODINGS_LOWER = {k.lower(): v for k, v in ENCODINGS.items()}


def import_anyreader() -> Any:
    """``rosbags.highlevel.AnyReader``, or ``ImportError`` with :data:`ROSBAG_HINT`."""
    try:
        from rosbags.highlevel import AnyReader
    except ImportError:
        raise ImportError(ROSBAG_HINT) from None
    return AnyReader


def _bag_errors() -> tuple[type[BaseException], ...]:
    """What the library raises on a damaged or foreign file (each becomes one :class:`DatasetError` line)."""
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as ReaderError1
    from rosbags.rosbag2 import ReaderError as ReaderError2
    from rosbags.serde import SerdeError

    return (AnyReaderError, ReaderError1, ReaderError2, SerdeError, sqlite3.DatabaseError, struct.error, EOFError,
            OSError, KeyError, IndexError)


def _stamp_ns(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def seconds(stamps_ns: np.ndarray) -> np.ndarray:
    """Integer nanoseconds as float64 seconds, ``sec + nanosec * 1e-9`` (one rounding: at epoch times a float64 of
    nanoseconds would already be 256 ns coarse)."""
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    return (stamps_ns // 1_000_000_000).astype(np.float64) + (stamps_ns % 1_000_000_000).astype(np.float64) * 1e-9


def _pose_matrix(position: Any, orientation: Any, what: str) -> np.ndarray:
    q = np.array([[orientation.x, orientation.y, orientation.z, orientation.w]], dtype=np.float64)
    t = np.array([position.x, position.y, position.z], dtype=np.float64)
    norm = float(np.linalg.norm(q))
    if not np.isfinite(norm) or norm < 1e-9 or not np.isfinite(t).all():
        raise DatasetError(f"{what}: a pose with quaternion {q[0].tolist()} and position {t.tolist()}; expected a "
                           "unit quaternion (x, y, z, w) and a finite position")
    T = np.eye(4)
    T[:3, :3] = quaternion_to_rotation(q)[0]
    T[:3, 3] = t
    return T


# ------------------------------------------------------------------------------------------------ the bag
class RosBag:
    """One bag, opened on demand: its topics, and the messages of chosen topics in receive order.

    Each thread reads through a reader of its own (an sqlite3 connection stays in the thread that opened it; the
    inference loop decodes frames in a loader thread).

    Args:
        path: a ROS 1 ``.bag`` file, a ROS 2 bag folder, or a ROS 2 ``.db3`` / ``.mcap`` file.

    Attributes:
        path: what is read (the storage file of a folder without ``metadata.yaml``). topics: ``{name: (message type,
        message count)}``. ros1: True for a ROS 1 bag.

    Raises:
        ImportError: rosbags missing. DatasetNotFoundError: no such path. DatasetError: not a bag, or a damaged one.
    """

    def __init__(self, path: str | Path) -> None:
        self._AnyReader = import_anyreader()
        self._errors = _bag_errors()
        self.given = Path(path)
        self.path = self._storage(self.given)
        self._local = threading.local()
        self._readers: list[Any] = []  # every thread's, closed with the bag (or when it is garbage-collected)
        self._finalizer = weakref.finalize(self, _close_readers, self._readers)
        reader = self._reader()
        self.ros1 = not reader.is2
        self.topics: dict[str, tuple[str, int]] = {}
        for conn in reader.connections:
            msgtype, count = self.topics.get(conn.topic, (conn.msgtype, 0))
            self.topics[conn.topic] = (msgtype, count + int(conn.msgcount))

    def _storage(self, path: Path) -> Path:
        if not path.exists():
            raise DatasetNotFoundError(f"data.path={path}: no such file or folder ({BAG_EXPECTED})")
        if path.is_dir() and not (path / "metadata.yaml").is_file():
            files = sorted([*path.glob("*.db3"), *path.glob("*.mcap")])
            if len(files) != 1:
                raise DatasetError(f"data.path={path}: a folder without metadata.yaml and {len(files)} .db3/.mcap "
                                   f"files; {BAG_EXPECTED}")
            log.warning("data.path=%s has no metadata.yaml (a recording cut short?): reading %s itself "
                        "(ros2 bag reindex restores the metadata)", path, files[0].name)
            return files[0]
        return path

    def fail(self, err: BaseException) -> DatasetError:
        """A library error as one line naming the bag."""
        text = " ".join(str(a) for a in getattr(err, "args", ()) if a) or type(err).__name__
        return DatasetError(f"data.path={self.given}: cannot read the bag ({text.strip().rstrip('.')}); "
                            f"{BAG_EXPECTED}, complete (a recording cut short needs rosbag reindex / ros2 bag reindex)")

    def _reader(self) -> Any:
        reader = getattr(self._local, "reader", None)
        if reader is None:
            from rosbags.typesys import Stores, get_typestore

            try:
                reader = self._AnyReader([self.path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
                reader.open()
            except self._errors as err:
                raise self.fail(err) from None
            self._local.reader = reader
            self._readers.append(reader)
        return reader

    def messages(self, topics: list[str] | tuple[str, ...], start_ns: int | None = None,
                 raw: bool = False) -> Iterator[tuple[str, str, int, Any]]:
        """``(topic, message type, receive time ns, message)`` of ``topics`` in receive order from ``start_ns`` on
        (``raw``: the serialized bytes instead of the message)."""
        reader = self._reader()
        conns = [c for c in reader.connections if c.topic in topics]
        if not conns:
            return
        it = reader.messages(connections=conns, start=start_ns)
        while True:
            try:
                conn, t_ns, data = next(it)
                msg = data if raw else reader.deserialize(data, conn.msgtype)
            except StopIteration:
                return
            except self._errors as err:
                raise self.fail(err) from None
            yield conn.topic, conn.msgtype, int(t_ns), msg

    def deserialize(self, data: bytes, msgtype: str) -> Any:
        try:
            return self._reader().deserialize(data, msgtype)
        except self._errors as err:
            raise self.fail(err) from None

    def of_types(self, types: tuple[str, ...]) -> list[str]:
        return [t for t, (m, _) in sorted(self.topics.items()) if m in types]

    def describe(self, topics: list[str] | None = None) -> str:
        names = sorted(self.topics) if topics is None else topics
        return ", ".join(f"{t} ({self.topics[t][0]}, {self.topics[t][1]} messages)" for t in names) or "none"

    def close(self) -> None:
        """Close the readers (reading again in a thread reopens its reader)."""
        self._local = threading.local()
        _close_readers(self._readers)


def _close_readers(readers: list[Any]) -> None:
    while readers:
        try:
            readers.pop().close()
        except Exception:  # noqa: BLE001 - another thread's sqlite3 connection refuses; it closes when collected
            pass


# ------------------------------------------------------------------------------------------------ pixels
# ROS names a mosaic by the colours of its top-left 2x2 block, row by row; kornia's CFA names the same mosaics the
# other way round (checked: every interior pixel equals the normalised-convolution demosaicking of the sampled values)
KORNIA_CFA = {"rggb": "BG", "bggr": "RG", "gbrg": "GR", "grbg": "GB"}


def debayer(raw: np.ndarray, pattern: str) -> np.ndarray:
    """Bilinear demosaicking of an (H,W) Bayer mosaic (H and W even) by :func:`kornia.color.raw_to_rgb`; ``pattern``
    names the colours of the top-left 2x2 block row by row (``rggb``, ``bggr``, ``gbrg``, ``grbg``). Returns (H,W,3)
    float32 RGB in the raw's units: each sampled value is kept, each missing one is the mean of its nearest samples
    of that colour."""
    from kornia.color import CFA, raw_to_rgb

    x = torch.from_numpy(np.ascontiguousarray(raw, dtype=np.float32))[None, None]
    return raw_to_rgb(x, CFA[KORNIA_CFA[pattern]])[0].permute(1, 2, 0).contiguous().numpy()


def image_array(msg: Any, what: str) -> np.ndarray:
    """A ``sensor_msgs/Image``'s pixels as an (H,W) or (H,W,3) RGB uint8/uint16 array (Bayer: float32 in [0,1]).

    Raises:
        DatasetError: an unknown encoding, or fewer bytes than ``height * step`` (one line naming ``what``).
    """
    encoding = str(msg.encoding)
    spec = _ENCODINGS_LOWER.get(encoding.lower())
    if spec is None:
        raise DatasetError(f"{what}: image encoding {encoding!r} is not supported; expected one of "
                           f"{', '.join(ENCODINGS)}")
    channels, dtype, layout = spec
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    itemsize = np.dtype(dtype).itemsize
    row = w * channels * itemsize
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    if h <= 0 or w <= 0 or step < row or data.size < h * step:
        raise DatasetError(f"{what}: {data.size} bytes for a {w}x{h} {encoding} image with step {step}; expected "
                           f"step >= {row} and at least height * step = {h * max(step, row)} bytes")
    if layout in KORNIA_CFA and (h % 2 or w % 2):
        raise DatasetError(f"{what}: a {w}x{h} {encoding} mosaic; expected an even width and height (whole 2x2 "
                           "Bayer blocks)")
    rows = np.ascontiguousarray(data[: h * step].reshape(h, step)[:, :row])
    arr = rows.view(np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")).reshape(h, w, channels)
    arr = arr.astype(np.dtype(dtype), copy=False)
    if layout == "mono":
        return arr[..., 0]
    if layout in ("rgb", "rgba"):
        return arr[..., :3]
    if layout in ("bgr", "bgra"):
        return np.ascontiguousarray(arr[..., 2::-1])
    return debayer(arr[..., 0], layout) * np.float32(1.0 / 255.0)


def _frame_tensor(msg: Any, msgtype: str, what: str) -> torch.Tensor:
    if msgtype == COMPRESSED:
        fmt = str(msg.format)
        if "compresseddepth" in fmt.lower():
            raise DatasetError(f"{what}: CompressedImage format {fmt!r} is a depth image; expected a camera image "
                               "(jpeg or png)")
        return decode_image(bytes(msg.data), f"{what} (CompressedImage format {fmt!r})")
    return array_to_image(image_array(msg, what))


# ------------------------------------------------------------------------------------------------ images
class BagImages:
    """Random access to the frames of one image topic of a bag, in header-stamp order (see the module docstring).

    Args:
        bag: the bag. topic: the image topic (None: the bag's only one). cache: decoded frames kept.

    Attributes:
        topic, msgtype, num_frames, stamps_ns (N,) int64, timestamps (N,) float64 seconds, size (height, width),
        encoding (or the CompressedImage format), frame_id (of the first frame's header).

    Raises:
        DatasetError: no image topic, several and none chosen, a topic that is not an image topic, fewer than 2
            frames; on access: an unknown encoding, a frame of another size, a damaged bag.
    """

    def __init__(self, bag: RosBag, topic: str | None = None, cache: int = 4) -> None:
        self.bag = bag
        self.topic = self._choose(topic)
        self.msgtype = bag.topics[self.topic][0]
        self.cache_size = max(2, int(cache))
        log_ns, stamps = [], []
        first = None
        for _, _, t_ns, msg in bag.messages([self.topic]):
            log_ns.append(t_ns)
            stamps.append(_stamp_ns(msg.header.stamp))
            if first is None:
                first = msg
        if first is None:
            raise DatasetError(f"data.path={bag.given}: topic {self.topic} holds no messages; expected camera frames")
        self.log_ns = np.asarray(log_ns, dtype=np.int64)
        raw = np.asarray(stamps, dtype=np.int64)
        self._stamps_from_log = not raw.any()
        if self._stamps_from_log:
            log.warning("data.path=%s: every header stamp of %s is zero; the frames are timed by the bag's receive "
                        "times instead", bag.given, self.topic)
            raw = self.log_ns.copy()
        self._raw_stamps = raw
        order = np.argsort(raw, kind="stable")
        keep = np.ones(len(order), dtype=bool)
        keep[1:] = raw[order][1:] != raw[order][:-1]
        self.positions = order[keep]  # each frame's position among the topic's messages in receive order
        self.stamps_ns = raw[self.positions]
        self.timestamps = seconds(self.stamps_ns)
        self.num_frames = len(self.positions)
        late = int(np.sum(raw[1:] < np.maximum.accumulate(raw)[:-1])) if len(raw) > 1 else 0
        duplicates = int((~keep).sum())
        if late or duplicates:
            log.warning("data.path=%s, %s: %d messages received out of stamp order (sorted), %d with a stamp "
                        "received before (dropped): %d frames", bag.given, self.topic, late, duplicates,
                        self.num_frames)
        self._sorted_log = bool(np.all(np.diff(self.log_ns) >= 0))
        self.frame_id = str(first.header.frame_id)
        what = f"data.path={bag.given}, {self.topic} frame 0"
        if self.msgtype == IMAGE:
            self.encoding = str(first.encoding)
            image_array(first, what)  # an unknown encoding fails here, before anything runs
            self.size = (int(first.height), int(first.width))
        else:
            self.encoding = str(first.format)
            self.size = tuple(int(v) for v in _frame_tensor(first, self.msgtype, what).shape[-2:])
        self._lock = threading.Lock()
        self._cache: OrderedDict[int, torch.Tensor] = OrderedDict()

    def _choose(self, topic: str | None) -> str:
        images = self.bag.of_types(IMAGE_TYPES)
        where = f"data.path={self.bag.given}"
        if topic is not None:
            if topic not in self.bag.topics:
                raise DatasetError(f"data.topic={topic}: no such topic in {where}; its image topics: "
                                   f"{self.bag.describe(images)}")
            if self.bag.topics[topic][0] not in IMAGE_TYPES:
                raise DatasetError(f"data.topic={topic} in {where} is {self.bag.topics[topic][0]}; expected "
                                   f"sensor_msgs/Image or sensor_msgs/CompressedImage (image topics: "
                                   f"{self.bag.describe(images)})")
            return topic
        if not images:
            raise DatasetError(f"{where} holds no image topic (sensor_msgs/Image or sensor_msgs/CompressedImage); "
                               f"its topics: {self.bag.describe()}")
        if len(images) > 1:
            raise DatasetError(f"{where} holds {len(images)} image topics: {self.bag.describe(images)}; choose one "
                               "with data.topic=TOPIC")
        return images[0]

    def __len__(self) -> int:
        return self.num_frames

    def _cursor(self) -> Any:
        local = self.bag._local
        if getattr(local, "cursors", None) is None:
            local.cursors = {}
        return local.cursors.setdefault(self.topic, [None, None])  # [message iterator, position it yields next]

    def read(self, index: int) -> torch.Tensor:
        """Frame ``index`` as a (3,H,W) float32 RGB tensor in [0,1] at the stored size (cached; do not modify)."""
        if not 0 <= index < self.num_frames:
            raise IndexError(f"{self.topic}: frame {index} out of range 0..{self.num_frames - 1}")
        with self._lock:
            if index in self._cache:
                self._cache.move_to_end(index)
                return self._cache[index]
        pos = int(self.positions[index])
        cursor = self._cursor()
        if cursor[0] is None or not cursor[1] <= pos <= cursor[1] + SEEK_AHEAD:
            if self._sorted_log:
                start = int(self.log_ns[pos])
                cursor[:] = [self.bag.messages([self.topic], start, raw=True),
                             int(np.searchsorted(self.log_ns, start, side="left"))]
            else:  # receive times not in order (a merged bag): read from the start
                cursor[:] = [self.bag.messages([self.topic], raw=True), 0]
        data = None
        while cursor[1] <= pos:
            item = next(cursor[0], None)
            if item is None:
                cursor[0] = None
                raise DatasetError(f"data.path={self.bag.given}, {self.topic}: the bag ended before frame {index} "
                                   "(changed while it was read?)")
            cursor[1] += 1
            data = item[3]
        msg = self.bag.deserialize(data, self.msgtype)
        what = f"data.path={self.bag.given}, {self.topic} frame {index} (t = {self.timestamps[index]:.6f} s)"
        if not self._stamps_from_log and _stamp_ns(msg.header.stamp) != self._raw_stamps[pos]:
            raise DatasetError(f"{what}: read a message stamped {_stamp_ns(msg.header.stamp)} ns where the index "
                               "had another (the bag changed while it was read?)")
        image = _frame_tensor(msg, self.msgtype, what)
        if tuple(image.shape[-2:]) != self.size:
            raise DatasetError(f"{what} is {image.shape[-1]}x{image.shape[-2]}, the first frame "
                               f"{self.size[1]}x{self.size[0]}; expected frames of one size")
        with self._lock:
            self._cache[index] = image
            while len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)
        return image


# ------------------------------------------------------------------------------------------------ calibration
@dataclass
class BagCamera:
    """Intrinsics of a ``sensor_msgs/CameraInfo`` in pixels of the images it describes (binning and ROI applied).

    Attributes:
        topic, frame_id. fx, fy, cx, cy: pixels. dist: OpenCV coefficients (None: none, or all zero). model: the
        ``distortion_model``. size: (height, width) of the images it describes.
    """

    topic: str
    frame_id: str
    fx: float
    fy: float
    cx: float
    cy: float
    dist: list[float] | None
    model: str
    size: tuple[int, int]


def camera_from_info(msg: Any, topic: str) -> BagCamera:
    """:class:`BagCamera` of a CameraInfo message (ROS 1 ``K``/``D`` or ROS 2 ``k``/``d`` fields).

    Raises:
        DatasetError: ``K`` with non-positive focal lengths (an uncalibrated camera), or a distortion model other than
            plumb_bob / rational_polynomial with non-zero coefficients.
    """
    K = np.asarray(getattr(msg, "k", getattr(msg, "K", None)), dtype=np.float64).reshape(-1)
    D = np.asarray(getattr(msg, "d", getattr(msg, "D", ())), dtype=np.float64).reshape(-1)
    if K.size != 9 or K[0] <= 0 or K[4] <= 0:
        raise DatasetError(f"CameraInfo {topic}: K = {K.tolist()} (an uncalibrated camera?); expected fx, fy > 0, "
                           "or give the intrinsics as data.fx= data.fy= data.cx= data.cy=")
    bx, by = max(1, int(msg.binning_x)), max(1, int(msg.binning_y))
    roi = msg.roi
    full_h, full_w = int(msg.height), int(msg.width)
    h = int(roi.height) if int(roi.height) and int(roi.width) else full_h
    w = int(roi.width) if int(roi.height) and int(roi.width) else full_w
    model = str(msg.distortion_model)
    dist: list[float] | None = None
    if D.size and np.any(D != 0):
        want = DISTORTION_COUNTS.get(model)
        if want is None:
            raise DatasetError(f"CameraInfo {topic}: distortion_model {model!r} is not supported; expected plumb_bob "
                               "or rational_polynomial (or give data.dist=[k1,k2,p1,p2,k3] yourself)")
        if D.size < want:
            raise DatasetError(f"CameraInfo {topic}: {model} with {D.size} coefficients in D; expected {want}")
        dist = [float(v) for v in D[:want]]
    return BagCamera(topic, str(msg.header.frame_id), float(K[0]) / bx, float(K[4]) / by,
                     (float(K[2]) - int(roi.x_offset)) / bx, (float(K[5]) - int(roi.y_offset)) / by, dist, model,
                     (h // by, w // bx))


def _camera_info_topic(bag: RosBag, image_topic: str, given: str | None) -> str | None:
    infos = bag.of_types((CAMERA_INFO,))
    if given is not None:
        if bag.topics.get(given, ("", 0))[0] != CAMERA_INFO:
            raise DatasetError(f"data.camera_info_topic={given}: not a sensor_msgs/CameraInfo topic of "
                               f"data.path={bag.given}; its CameraInfo topics: {bag.describe(infos)}")
        return given
    parts = image_topic.rstrip("/").split("/")
    for k in range(len(parts) - 1, 0, -1):  # beside the image topic, then up its namespaces
        candidate = "/".join(parts[:k]) + "/camera_info"
        if candidate in infos:
            return candidate
    if len(infos) == 1:
        return infos[0]
    if infos:
        raise DatasetError(f"data.path={bag.given} holds {len(infos)} CameraInfo topics ({bag.describe(infos)}) and "
                           f"none beside {image_topic}; choose one with data.camera_info_topic=TOPIC")
    return None


def _read_camera(bag: RosBag, topic: str | None) -> BagCamera | None:
    if topic is None:
        return None
    first = None
    changed = False
    for _, _, _, msg in bag.messages([topic]):
        if first is None:
            first = msg
        elif not np.array_equal(np.asarray(getattr(msg, "k", getattr(msg, "K", ()))),
                                np.asarray(getattr(first, "k", getattr(first, "K", ())))):
            changed = True
            break
    if first is None:
        return None
    if changed:
        log.warning("data.path=%s: the CameraInfo on %s changes during the recording; the first one is used",
                    bag.given, topic)
    return camera_from_info(first, topic)


def _intrinsics(camera: BagCamera | None, given: dict[str, Any], size: tuple[int, int], source: str
                ) -> tuple[float, float, float, float, list[float] | None]:
    keys = ("fx", "fy", "cx", "cy")
    if camera is None:
        missing = [k for k in keys if given[k] is None]
        if missing:
            raise DatasetError(f"{source} has no sensor_msgs/CameraInfo for the images; give the intrinsics "
                               f"data.{'= data.'.join(missing)}= (pixels of the stored frames)")
        values = {k: given[k] for k in (*keys, "dist")}
        names = tuple(f"data.{k}" for k in keys)
        return check_intrinsics(*(values[k] for k in keys), size[1], size[0], values["dist"], names=names,
                                source=source)
    if camera.size != tuple(size):
        log.warning("%s: CameraInfo %s describes %dx%d images (binning and ROI applied), the frames are %dx%d",
                    source, camera.topic, camera.size[1], camera.size[0], size[1], size[0])
    values = {k: getattr(camera, k) for k in (*keys, "dist")}
    overridden = []
    for k in (*keys, "dist"):
        if given[k] is None:
            continue
        same = (given[k] == values[k]) if k == "dist" else abs(float(given[k]) - values[k]) <= 1e-9 * abs(values[k])
        if not same:
            overridden.append(f"data.{k}={given[k]} (CameraInfo: {values[k]})")
        values[k] = [float(v) for v in given[k]] if k == "dist" else float(given[k])
    if overridden:
        log.warning("%s: %s replace%s the CameraInfo of %s", source, ", ".join(overridden),
                    "" if len(overridden) > 1 else "s", camera.topic)
    names = tuple(f"data.{k}" if given[k] is not None else f"{k} of CameraInfo {camera.topic}" for k in keys)
    dist_name = "data.dist" if given["dist"] is not None else f"D of CameraInfo {camera.topic}"
    return check_intrinsics(*(values[k] for k in keys), size[1], size[0], values["dist"], names=names,
                            dist_name=dist_name, source=source)


# ------------------------------------------------------------------------------------------------ ground truth
@dataclass
class PoseTrack:
    """Poses of a ground-truth topic: ``stamps_ns`` (M,) int64 header stamps, ``poses`` (M,4,4) ``T_parent_body``,
    ``parent`` and ``body`` frame ids (``body`` None: a PoseStamped with no body named)."""

    stamps_ns: np.ndarray
    poses: np.ndarray
    parent: str
    body: str | None


def read_pose_topic(bag: RosBag, topic: str, parent: str | None = None, child: str | None = None) -> PoseTrack:
    """The poses of ``topic`` (see the module docstring). ``parent`` / ``child`` choose the transform of a TF topic
    (None: the topic's only pair); ``child`` also names the body of a PoseStamped or replaces an Odometry's.

    Raises:
        DatasetError: no such topic, another message type, no pose, or a TF topic whose pairs the settings do not
            single out (the pairs listed).
    """
    where = f"data.gt_topic={topic}"
    if topic not in bag.topics:
        raise DatasetError(f"{where}: no such topic in data.path={bag.given}; its pose topics: "
                           f"{bag.describe(bag.of_types(POSE_TYPES))}")
    msgtype = bag.topics[topic][0]
    if msgtype not in POSE_TYPES:
        raise DatasetError(f"{where} is {msgtype}; expected one of {', '.join(POSE_TYPES)}")
    rows: list[tuple[int, str, str | None, np.ndarray]] = []
    for _, _, _, msg in bag.messages([topic]):
        if msgtype == TF_MESSAGE:
            transforms = list(msg.transforms)
        elif msgtype == TRANSFORM_STAMPED:
            transforms = [msg]
        else:
            pose = msg.pose.pose if msgtype == ODOMETRY else msg.pose
            body = child if child is not None else (str(msg.child_frame_id) or None if msgtype == ODOMETRY else None)
            rows.append((_stamp_ns(msg.header.stamp), str(msg.header.frame_id), body,
                         _pose_matrix(pose.position, pose.orientation, where)))
            continue
        for tr in transforms:
            rows.append((_stamp_ns(tr.header.stamp), str(tr.header.frame_id), str(tr.child_frame_id),
                         _pose_matrix(tr.transform.translation, tr.transform.rotation, where)))
    if msgtype in (TF_MESSAGE, TRANSFORM_STAMPED):
        pairs = Counter((p, c) for _, p, c, _ in rows)
        chosen = [pc for pc in pairs if (parent is None or pc[0] == parent) and (child is None or pc[1] == child)]
        if len(chosen) != 1:
            listed = ", ".join(f"{p} -> {c} ({n})" for (p, c), n in sorted(pairs.items())) or "none"
            how = "no transform matches" if not chosen else f"{len(chosen)} transforms match"
            raise DatasetError(f"{where}: {how} data.gt_parent_frame={parent}, data.gt_child_frame={child}; its "
                               f"transforms: {listed}; choose one with data.gt_parent_frame= data.gt_child_frame=")
        rows = [r for r in rows if (r[1], r[2]) == chosen[0]]
    if not rows:
        raise DatasetError(f"{where} in data.path={bag.given} holds no pose")
    return PoseTrack(np.asarray([r[0] for r in rows], dtype=np.int64), np.stack([r[3] for r in rows]), rows[0][1],
                     rows[0][2])


def static_transforms(bag: RosBag) -> dict[tuple[str, str], np.ndarray]:
    """``{(parent, child): T_parent_child}`` of the bag's ``/tf_static`` (empty without one)."""
    if bag.topics.get(TF_STATIC, ("", 0))[0] != TF_MESSAGE:
        return {}
    out: dict[tuple[str, str], np.ndarray] = {}
    for _, _, _, msg in bag.messages([TF_STATIC]):
        for tr in msg.transforms:
            out[(str(tr.header.frame_id), str(tr.child_frame_id))] = _pose_matrix(
                tr.transform.translation, tr.transform.rotation, f"{TF_STATIC} of data.path={bag.given}")
    return out


def chain_transform(edges: dict[tuple[str, str], np.ndarray], source: str, target: str) -> np.ndarray | None:
    """``T_source_target`` composed along the tree of ``edges`` (``{(parent, child): T_parent_child}``, walked in
    either direction), or None when the two frames are not connected."""
    if source == target:
        return np.eye(4)
    links: dict[str, list[tuple[str, np.ndarray]]] = {}
    for (p, c), T in edges.items():
        links.setdefault(p, []).append((c, T))
        links.setdefault(c, []).append((p, np.linalg.inv(T)))
    seen = {source: np.eye(4)}
    todo = deque([source])
    while todo:
        frame = todo.popleft()
        for nxt, T in links.get(frame, []):
            if nxt not in seen:
                seen[nxt] = seen[frame] @ T
                if nxt == target:
                    return seen[nxt]
                todo.append(nxt)
    return None


def body_to_camera(given: list[float] | None, body: str | None, camera_frame: str,
                   edges: dict[tuple[str, str], np.ndarray], topic: str) -> tuple[np.ndarray, str]:
    """``(T_body_camera, how it was found)`` (see the module docstring).

    Raises:
        ValueError: ``given`` is neither 7 nor 16 numbers. DatasetError: the body and the camera are different frames
            and ``/tf_static`` does not connect them.
    """
    if given is not None:
        values = [float(v) for v in given]
        if len(values) == 7:
            T = np.eye(4)
            T[:3, :3] = quaternion_to_rotation(np.asarray([values[3:]]))[0]
            T[:3, 3] = values[:3]
        elif len(values) == 16:
            T = np.asarray(values, dtype=np.float64).reshape(4, 4)
        else:
            raise ValueError(f"data.gt_camera_transform has {len(values)} numbers; expected [x, y, z, qx, qy, qz, qw] "
                             "(the camera's pose in the ground truth's body frame, metres) or 16 (a 4x4 matrix, row "
                             "by row)")
        return T, "data.gt_camera_transform"
    if body is None:
        return np.eye(4), "the poses are the camera's (a PoseStamped naming no body: data.gt_child_frame)"
    T = chain_transform(edges, body, camera_frame)
    if T is None:
        raise DatasetError(f"data.gt_topic={topic}: poses of frame {body!r}, images in frame {camera_frame!r}, and "
                           f"no {TF_STATIC} chain between them; give data.gt_camera_transform=[x,y,z,qx,qy,qz,qw] "
                           f"(the camera's pose in {body!r})")
    return T, "identity (the camera's frame)" if body == camera_frame else f"{TF_STATIC} {body} -> {camera_frame}"


# ------------------------------------------------------------------------------------------------ the sequence
def open_rosbag(path: str | Path, *, topic: str | None = None, camera_info_topic: str | None = None,
                fx: float | None = None, fy: float | None = None, cx: float | None = None, cy: float | None = None,
                dist: list[float] | None = None, gt_topic: str | None = None, gt_parent_frame: str | None = None,
                gt_child_frame: str | None = None, gt_camera_transform: list[float] | None = None,
                gt_tolerance: float = 0.02, start: int | None = None, end: int | None = None,
                step: int | None = None, cache: int = 4) -> FrameSequence:
    """A bag's camera as a :class:`~dfvo.data.sequence.FrameSequence` at the stored size (see the module docstring).

    Args:
        path: the bag. topic: the image topic (None: the only one). camera_info_topic: None: the CameraInfo beside
            the image topic, else the bag's only one. fx, fy, cx, cy, dist: replace the CameraInfo's (all four needed
            without one). gt_topic, gt_parent_frame, gt_child_frame, gt_camera_transform, gt_tolerance: ground truth
            (None: none). start, end, step: frames in stamp order (Python slice semantics). cache: frames kept.

    Raises:
        ImportError: rosbags missing (one line). DatasetNotFoundError, DatasetError, IntrinsicsError (ValueErrors):
            one line naming the bag, the topic or the setting.
    """
    bag = RosBag(path)
    images = BagImages(bag, topic, cache)
    source = f"data.path={bag.given} ({images.topic})"
    info_topic = _camera_info_topic(bag, images.topic, camera_info_topic)
    camera = _read_camera(bag, info_topic)
    given = {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "dist": dist}
    fx, fy, cx, cy, dist = _intrinsics(camera, given, images.size, source)
    frame_ids = np.arange(len(images))[slice(start, end, step)]
    if len(frame_ids) < 2:
        raise DatasetError(f"{source} has {len(images)} frames; data.start={start}, data.end={end}, data.step={step} "
                           f"select {len(frame_ids)}, expected at least 2")
    prep = FramePrep(intrinsics_matrix(fx, fy, cx, cy, dtype=torch.float64)[0], images.size, None, dist)
    times = images.timestamps[frame_ids]
    name = bag.given.stem if bag.given.suffix in (".bag", ".db3", ".mcap") else bag.given.name
    log.info("%s: %d frames of %s %dx%d (%s), t = %.3f .. %.3f s; intrinsics from %s", source, len(frame_ids),
             images.msgtype, images.size[1], images.size[0], images.encoding, times[0], times[-1],
             "the settings" if camera is None else f"CameraInfo {camera.topic}")
    poses = None
    if gt_topic:
        track = read_pose_topic(bag, gt_topic, gt_parent_frame, gt_child_frame)
        camera_frame = images.frame_id or (camera.frame_id if camera is not None else "")
        T_bc, how = body_to_camera(gt_camera_transform, track.body, camera_frame, static_transforms(bag), gt_topic)
        gt_poses = track.poses @ T_bc
        match = associate_frames(times, seconds(track.stamps_ns), gt_tolerance)
        _, poses, report = attach_ground_truth(times, match, gt_poses, "nan", f"data.gt_topic={gt_topic}",
                                               gt_tolerance)
        log.info("%s (%d poses of %s in %s; camera in the body: %s)", report, len(track.poses), track.body or "the "
                 "camera", track.parent, how)

    def load(i: int) -> torch.Tensor:
        return prep(images.read(int(frame_ids[i])))

    return FrameSequence(name, len(frame_ids), prep.K.clone(), load, poses, timestamps=times, frame_ids=frame_ids)
