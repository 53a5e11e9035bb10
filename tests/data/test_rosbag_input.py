"""ROS bags as input (``data=rosbag``, dfvo.data.rosbag_input): bags written by the test with ``rosbags`` (ROS 1, ROS 2
sqlite3 and MCAP) from the synthetic world's frames, with CameraInfo, a pose topic and /tf_static. The frames equal
the same pixels read from PNG/JPEG files by ``data=folder`` (raw rgb8/bgr8 with row padding, mono16 in both byte
orders, CompressedImage PNG and JPEG), in stamp order (late and repeated messages), with the CameraInfo's intrinsics;
``infer.py data=rosbag`` gives the poses of ``data=folder`` on the same frames and the metrics of the same ground
truth; bad input is one line."""

from __future__ import annotations

import io
import json
import logging
import re
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from dfvo.data.image_folder import ImageFolder
from dfvo.data.image_io import DatasetError
from dfvo.data.intrinsics_check import IntrinsicsError
from dfvo.io.trajectory import rotation_to_quaternion
from dfvo.synthetic import SyntheticWorld

pytest.importorskip("rosbags", reason='data=rosbag needs the ros extra (pip install "dfvo[ros]")')

from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import StoragePlugin  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: E402

from dfvo.data.rosbag_input import ROSBAG_HINT, BagImages, RosBag, debayer, open_rosbag  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
N, H, W = 8, 96, 320
T0 = 1_700_000_000.0  # epoch seconds, as real recordings are stamped
# frame k is stamped T0 + STAMPS[k] (a gap before frame 6) and received 5 ms later, frames 3 and 4 in swapped order,
# frame 5 received twice
STAMPS = [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.8, 0.9]
RECEIVE_ORDER = [0, 1, 2, 4, 3, 5, 5, 6, 7]
SMALL = [f"img_res.width={W}", "num_threads=1", "progress=false", "align=7dof"]
needs_checkpoints = pytest.mark.skipif(not (REPO / "dfvo/checkpoints/flow.safetensors").is_file(),
                                       reason="no shipped checkpoints in dfvo/checkpoints")


def ns(seconds: float) -> int:
    return round(seconds * 1e9)


def stamp_ns(t: float) -> int:
    """A header stamp's nanoseconds as :meth:`Msgs.header` writes ``t`` (whole seconds, then the fraction)."""
    sec = int(np.floor(t))
    return sec * 1_000_000_000 + ns(t - sec)


def rigid(rx: float, ry: float, rz: float, t: tuple[float, float, float]) -> np.ndarray:
    """A (4,4) transform from rotation angles (rad, applied x then y then z) and a translation."""
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = Rz @ Ry @ Rx
    T[:3, 3] = t
    return T


# the camera's optical frame (z forward, x right, y down) on a robot's body (x forward, y left, z up), 1.2 m up
T_BODY_CAMERA = rigid(-np.pi / 2, 0.0, -np.pi / 2, (0.3, 0.05, 1.2)) @ rigid(0.02, -0.01, 0.0, (0, 0, 0))


class Msgs:
    """Messages of one ROS version's typestore (ROS 1 headers carry ``seq``, CameraInfo upper-case ``K``/``D``)."""

    def __init__(self, ros1: bool) -> None:
        self.ros1 = ros1
        self.ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
        if ros1:  # the library's Noetic store lacks tf2_msgs (real ROS 1 bags carry its definition)
            self.ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                                "tf2_msgs/msg/TFMessage"))
        self.T = self.ts.types

    def serialize(self, msg: object, msgtype: str) -> bytes:
        return self.ts.serialize_ros1(msg, msgtype) if self.ros1 else self.ts.serialize_cdr(msg, msgtype)

    def header(self, stamp: float, frame: str) -> object:
        sec = int(np.floor(stamp))
        time = self.T["builtin_interfaces/msg/Time"](sec=sec, nanosec=ns(stamp - sec))
        extra = {"seq": 0} if self.ros1 else {}
        return self.T["std_msgs/msg/Header"](**extra, stamp=time, frame_id=frame)

    def image(self, arr: np.ndarray, encoding: str, stamp: float, pad: int = 0, bigendian: bool = False) -> object:
        h, w = arr.shape[:2]
        arr = arr.astype(arr.dtype.newbyteorder(">" if bigendian else "<"))
        rows = arr.reshape(h, -1).view(np.uint8)
        data = np.concatenate([rows, np.full((h, pad), 7, np.uint8)], axis=1).reshape(-1)
        return self.T["sensor_msgs/msg/Image"](header=self.header(stamp, "camera_optical"), height=h, width=w,
                                               encoding=encoding, is_bigendian=int(bigendian),
                                               step=rows.shape[1] + pad, data=data)

    def compressed(self, data: bytes, fmt: str, stamp: float) -> object:
        return self.T["sensor_msgs/msg/CompressedImage"](header=self.header(stamp, "camera_optical"), format=fmt,
                                                         data=np.frombuffer(data, np.uint8))

    def camera_info(self, K: np.ndarray, h: int, w: int, D: list[float] | None = None, model: str = "plumb_bob",
                    binning: int = 0, roi: tuple[int, int, int, int] = (0, 0, 0, 0)) -> object:
        D = np.asarray(D if D is not None else [0.0] * 5, dtype=np.float64)
        P = np.zeros(12)
        P[[0, 2, 5, 6, 10]] = K[0, 0], K[0, 2], K[1, 1], K[1, 2], 1.0
        region = self.T["sensor_msgs/msg/RegionOfInterest"](x_offset=roi[0], y_offset=roi[1], height=roi[2],
                                                            width=roi[3], do_rectify=False)
        fields = dict(zip(("D", "K", "R", "P") if self.ros1 else ("d", "k", "r", "p"),
                          (D, np.asarray(K, np.float64).reshape(-1), np.eye(3).reshape(-1), P)))
        return self.T["sensor_msgs/msg/CameraInfo"](header=self.header(T0, "camera_optical"), height=h, width=w,
                                                    distortion_model=model, binning_x=binning, binning_y=binning,
                                                    roi=region, **fields)

    def pose(self, T: np.ndarray) -> object:
        x, y, z, w = rotation_to_quaternion(T[None, :3, :3])[0]
        return self.T["geometry_msgs/msg/Pose"](
            position=self.T["geometry_msgs/msg/Point"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
            orientation=self.T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w))

    def transform(self, T: np.ndarray, stamp: float, parent: str, child: str) -> object:
        p = self.pose(T)
        tr = self.T["geometry_msgs/msg/Transform"](
            translation=self.T["geometry_msgs/msg/Vector3"](x=p.position.x, y=p.position.y, z=p.position.z),
            rotation=p.orientation)
        return self.T["geometry_msgs/msg/TransformStamped"](header=self.header(stamp, parent), child_frame_id=child,
                                                            transform=tr)

    def tf(self, transforms: list[object]) -> object:
        return self.T["tf2_msgs/msg/TFMessage"](transforms=transforms)

    def odometry(self, T: np.ndarray, stamp: float, parent: str, child: str) -> object:
        cov = np.zeros(36)
        vec = self.T["geometry_msgs/msg/Vector3"]
        return self.T["nav_msgs/msg/Odometry"](
            header=self.header(stamp, parent), child_frame_id=child,
            pose=self.T["geometry_msgs/msg/PoseWithCovariance"](pose=self.pose(T), covariance=cov),
            twist=self.T["geometry_msgs/msg/TwistWithCovariance"](
                twist=self.T["geometry_msgs/msg/Twist"](linear=vec(x=0, y=0, z=0), angular=vec(x=0, y=0, z=0)),
                covariance=cov))

    def pose_stamped(self, T: np.ndarray, stamp: float, parent: str) -> object:
        return self.T["geometry_msgs/msg/PoseStamped"](header=self.header(stamp, parent), pose=self.pose(T))


def write_bag(path: Path, storage: str, messages: list[tuple[str, str, float, object]], m: Msgs) -> Path:
    """``(topic, message type, receive time s, message)`` into a bag: storage ``ros1`` (``path`` a .bag file),
    ``sqlite3`` or ``mcap`` (``path`` a ROS 2 bag folder)."""
    if storage == "ros1":
        writer = Writer1(path)
    else:
        writer = Writer2(path, version=9,
                         storage_plugin=StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3)
    conns: dict[str, object] = {}
    with writer:
        for topic, msgtype, t, msg in messages:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=m.ts)
            writer.write(conns[topic], ns(t), m.serialize(msg, msgtype))
    return path


def png_bytes(arr: np.ndarray, fmt: str = "PNG", **kw) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(arr).save(buf, format=fmt, **kw)
    return buf.getvalue()


# ------------------------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The synthetic world's 8 frames as PNGs (and 16-bit grey, JPEG twins), their intrinsics, stamps and poses,
    the ground truth as a TUM file and a times file for ``data=folder``."""
    world = SyntheticWorld(seed=0, num_frames=N, height=H, width=W)
    root = tmp_path_factory.mktemp("rosbag")
    images = [world.image(k) for k in range(N)]
    frames = [(img.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8) for img in images]
    grey16 = [(img.mean(0).numpy() * 65535).round().astype(np.uint16) for img in images]
    jpegs = [png_bytes(f, "JPEG", quality=90) for f in frames]
    folders = {name: root / name for name in ("png", "grey16", "jpeg")}
    for folder in folders.values():
        folder.mkdir()
    for k in range(N):
        Image.fromarray(frames[k]).save(folders["png"] / f"{k:06d}.png")
        Image.fromarray(grey16[k]).save(folders["grey16"] / f"{k:06d}.png")
        (folders["jpeg"] / f"{k:06d}.jpg").write_bytes(jpegs[k])
    poses = world.poses().double().numpy()  # T_w_c
    stamps = np.asarray([T0 + s for s in STAMPS])
    (root / "times.txt").write_text("".join(f"{t:.9f}\n" for t in stamps))
    q = rotation_to_quaternion(poses[:, :3, :3])
    (root / "gt.tum").write_text("".join(f"{t:.9f} " + " ".join(f"{v:.17g}" for v in (*poses[k, :3, 3], *q[k]))
                                         + "\n" for k, t in enumerate(stamps)))
    return {"world": world, "root": root, "frames": frames, "grey16": grey16, "jpegs": jpegs, "folders": folders,
            "K": world.intrinsics().double().numpy(), "poses": poses, "stamps": stamps}


def frame_messages(scene: dict, m: Msgs, kind: str) -> list[tuple[str, str, float, object]]:
    """The frames as image messages of ``kind`` (``rgb8`` padded rows, ``bgr8``, ``png``, ``jpeg``, ``mono16``,
    ``mono16be``) in :data:`RECEIVE_ORDER`, received 5 ms after their stamps."""
    out = []
    for j, k in enumerate(RECEIVE_ORDER):
        t = scene["stamps"][k]
        received = scene["stamps"][sorted(RECEIVE_ORDER)[j]] + 0.005 + 1e-4 * j  # the j-th to arrive
        if kind == "rgb8":
            msg, msgtype = m.image(scene["frames"][k], "rgb8", t, pad=4), "sensor_msgs/msg/Image"
        elif kind == "bgr8":
            msg, msgtype = m.image(scene["frames"][k][..., ::-1], "bgr8", t), "sensor_msgs/msg/Image"
        elif kind in ("mono16", "mono16be"):
            msg, msgtype = m.image(scene["grey16"][k], "mono16", t, bigendian=kind == "mono16be"), \
                "sensor_msgs/msg/Image"
        elif kind == "png":
            msg, msgtype = m.compressed(png_bytes(scene["frames"][k]), "rgb8; png compressed rgb8", t), \
                "sensor_msgs/msg/CompressedImage"
        else:
            msg, msgtype = m.compressed(scene["jpegs"][k], "jpeg", t), "sensor_msgs/msg/CompressedImage"
        out.append(("/camera/image_raw", msgtype, received, msg))
    return out


def ground_truth_messages(scene: dict, m: Msgs, how: str) -> list[tuple[str, str, float, object]]:
    """The body's poses ``T_odom_base = T_w_c @ inv(T_BODY_CAMERA)`` at the frames' stamps + 1 ms, with decoys 50 ms
    later (1 m off: a wrong association would show), as ``how``: ``odometry`` (with /tf_static base_link ->
    camera_optical), ``tf`` (on /tf beside another transform, same /tf_static) or ``pose`` (PoseStamped of the
    camera itself)."""
    out = []
    static = m.tf([m.transform(T_BODY_CAMERA, T0, "base_link", "camera_optical"),
                   m.transform(rigid(0, 0, 0.3, (1, 2, 3)), T0, "base_link", "imu")])
    if how != "pose":
        out.append(("/tf_static", "tf2_msgs/msg/TFMessage", T0 - 1.0, static))
    for k, t in enumerate(scene["stamps"]):
        for dt, shift in ((0.001, 0.0), (0.05, 1.0)):
            T_w_c = scene["poses"][k].copy()
            T_w_c[0, 3] += shift
            T_body = T_w_c @ np.linalg.inv(T_BODY_CAMERA)
            stamp = t + dt
            if how == "odometry":
                out.append(("/ground_truth", "nav_msgs/msg/Odometry", stamp, m.odometry(T_body, stamp, "odom",
                                                                                       "base_link")))
            elif how == "tf":
                out.append(("/tf", "tf2_msgs/msg/TFMessage", stamp, m.tf([
                    m.transform(T_body, stamp, "odom", "base_link"),
                    m.transform(rigid(0, 0, 0, (5, 0, 0)), stamp, "map", "odom")])))
            else:
                out.append(("/ground_truth", "geometry_msgs/msg/PoseStamped", stamp, m.pose_stamped(T_w_c, stamp,
                                                                                                   "world")))
    return out


def make_bag(scene: dict, path: Path, storage: str, kind: str, gt: str | None = "odometry",
             info: bool = True, extra: list | None = None) -> Path:
    m = Msgs(storage == "ros1")
    msgs = []
    if info:
        msgs.append(("/camera/camera_info", "sensor_msgs/msg/CameraInfo", T0, m.camera_info(scene["K"], H, W)))
    if gt is not None:
        msgs += ground_truth_messages(scene, m, gt)
    msgs += frame_messages(scene, m, kind)
    msgs += extra or []
    msgs.sort(key=lambda x: x[2])  # a bag holds its messages in receive order
    return write_bag(path, storage, msgs, m)


@pytest.fixture(scope="module")
def bags(scene: dict) -> dict[str, Path]:
    root = scene["root"]
    return {"ros1": make_bag(scene, root / "rec.bag", "ros1", "rgb8", gt="odometry"),
            "sqlite3": make_bag(scene, root / "rec_sqlite", "sqlite3", "bgr8", gt="tf"),
            "mcap": make_bag(scene, root / "rec_mcap", "mcap", "png", gt="pose")}


def folder_frames(folder: Path, K: np.ndarray) -> ImageFolder:
    return ImageFolder(folder, K[0, 0], K[1, 1], K[0, 2], K[1, 2])


# ------------------------------------------------------------------------------------------------ frames
@pytest.mark.parametrize("storage, gt", [("ros1", {}), ("sqlite3", {"gt_child_frame": "base_link"}), ("mcap", {})])
def test_frames_stamps_and_intrinsics_equal_the_folder(scene: dict, bags: dict, storage: str, gt: dict,
                                                       caplog: pytest.LogCaptureFixture) -> None:
    """rgb8 with padded rows (ROS 1), bgr8 (sqlite3), CompressedImage PNG (MCAP): every frame equals the PNG read
    by data=folder, in stamp order (frames 3/4 received swapped, 5 twice), the stamps exact, K the CameraInfo's."""
    topic = "/tf" if storage == "sqlite3" else "/ground_truth"
    with caplog.at_level(logging.WARNING, logger="dfvo.data"):
        seq = open_rosbag(bags[storage], gt_topic=topic, **gt)
    assert "1 messages received out of stamp order (sorted), 1 with a stamp received before (dropped): 8 frames" \
        in caplog.text
    ref = folder_frames(scene["folders"]["png"], scene["K"])
    assert seq.length == N and seq.name == bags[storage].stem
    np.testing.assert_array_equal(seq.timestamps, scene["stamps"])  # header stamps, exact to the nanosecond
    assert torch.equal(seq.K, ref.intrinsics)
    for k in range(N):
        assert torch.equal(seq.load(k), ref[k]["image"]), k
    # the ground truth: the body's poses through /tf_static (Odometry, TF) or the camera's own (PoseStamped);
    # the decoys 50 ms later are not taken
    np.testing.assert_allclose(seq.poses, scene["poses"], atol=1e-9)


def test_mono16_jpeg_ranges_and_random_access(scene: dict) -> None:
    """mono16 in both byte orders equals the 16-bit PNG; CompressedImage JPEG equals the JPEG file read by
    data=folder; data.start/end/step select frames in stamp order; frames read backwards, ahead, and from another
    thread (a reader of its own) are the same."""
    root, K = scene["root"], scene["K"]
    grey = folder_frames(scene["folders"]["grey16"], K)
    for storage, kind in (("sqlite3", "mono16"), ("ros1", "mono16be")):
        path = make_bag(scene, root / f"grey_{storage}{'.bag' if storage == 'ros1' else ''}", storage, kind, gt=None)
        seq = open_rosbag(path)
        for k in (0, 7, 3):
            assert torch.equal(seq.load(k), grey[k]["image"]), (kind, k)
    jpeg = folder_frames(scene["folders"]["jpeg"], K)
    seq = open_rosbag(make_bag(scene, root / "jpeg_mcap", "mcap", "jpeg", gt=None), start=1, end=8, step=2)
    assert seq.length == 4 and seq.frame_ids.tolist() == [1, 3, 5, 7]
    np.testing.assert_array_equal(seq.timestamps, scene["stamps"][[1, 3, 5, 7]])
    for i, k in enumerate([1, 3, 5, 7]):
        assert torch.equal(seq.load(i), jpeg[k]["image"]), k

    bag = RosBag(root / "rec_sqlite")
    images = BagImages(bag, cache=2)
    png = folder_frames(scene["folders"]["png"], K)
    order = [7, 0, 1, 2, 6, 3, 5, 4]  # backwards, in order, ahead, back
    got = {k: images.read(k).clone() for k in order}
    other: dict[int, torch.Tensor] = {}
    thread = threading.Thread(target=lambda: other.update({k: images.read(k).clone() for k in (4, 2)}))
    images._cache.clear()
    thread.start()
    thread.join()
    for k in range(N):
        assert torch.equal(got[k], png[k]["image"]), k
    assert torch.equal(other[4], png[4]["image"]) and torch.equal(other[2], png[2]["image"])


def test_bayer_is_demosaicked(scene: dict) -> None:
    """bayer_rggb8 of a frame: the sampled colour of every pixel exact, the others within a few levels on average
    of the original (the same mosaic read as bggr is far off)."""
    rgb = scene["frames"][2]
    mosaic = np.empty((H, W), np.uint8)
    mosaic[0::2, 0::2] = rgb[0::2, 0::2, 0]
    mosaic[0::2, 1::2] = rgb[0::2, 1::2, 1]
    mosaic[1::2, 0::2] = rgb[1::2, 0::2, 1]
    mosaic[1::2, 1::2] = rgb[1::2, 1::2, 2]
    m = Msgs(False)
    msgs = [("/cam/image_raw", "sensor_msgs/msg/Image", T0 + k, m.image(mosaic, "bayer_rggb8", T0 + k))
            for k in range(2)]
    K = scene["K"]
    seq = open_rosbag(write_bag(scene["root"] / "bayer", "sqlite3", msgs, m), fx=K[0, 0], fy=K[1, 1], cx=K[0, 2],
                      cy=K[1, 2])
    out = (seq.load(0).permute(1, 2, 0).numpy() * 255).round()
    assert np.array_equal(out[0::2, 0::2, 0], rgb[0::2, 0::2, 0]) and np.array_equal(out[1::2, 1::2, 2],
                                                                                      rgb[1::2, 1::2, 2])
    assert np.array_equal(out[0::2, 1::2, 1], rgb[0::2, 1::2, 1])
    err = np.abs(out - rgb).mean()
    wrong = np.abs(debayer(mosaic, "bggr") - rgb).mean()
    assert err < 6 and wrong > 3 * err, (err, wrong)
    from dfvo.data.rosbag_input import image_array

    with pytest.raises(DatasetError, match=r"^odd: a \d+x\d+ bayer_rggb8 mosaic; expected an even width and height"):
        image_array(m.image(np.ascontiguousarray(mosaic[:-1]), "bayer_rggb8", T0), "odd")


def test_camera_info_binning_roi_distortion_and_overrides(scene: dict, caplog: pytest.LogCaptureFixture) -> None:
    """K of the full sensor moved to 2x-binned images of a region of interest as image_geometry does; a
    rational_polynomial D is the 8 OpenCV coefficients (frames undistorted as data=folder with that dist); settings
    replace the CameraInfo with one warning line naming the disagreement; without a CameraInfo the four are needed."""
    m = Msgs(True)
    K_full = np.array([[370.0, 0, 400.0], [0, 368.0, 150.0], [0, 0, 1]])
    D = [-0.1, 0.01, 0.001, -0.002, 0.0, 0.002, 0.0, 0.0]
    info = m.camera_info(K_full, 400, 1000, D=D, model="rational_polynomial", binning=2, roi=(80, 10, 2 * H, 2 * W))
    msgs = [("/camera/camera_info", "sensor_msgs/msg/CameraInfo", T0, info)]
    msgs += frame_messages(scene, m, "rgb8")
    path = write_bag(scene["root"] / "binned.bag", "ros1", msgs, m)
    seq = open_rosbag(path)
    fx, fy, cx, cy = 185.0, 184.0, (400 - 80) / 2, (150 - 10) / 2
    assert torch.allclose(seq.K.double(), torch.tensor([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=torch.float64))
    ref = ImageFolder(scene["folders"]["png"], fx, fy, cx, cy, dist=D)
    assert torch.equal(seq.load(1), ref[1]["image"])
    assert not torch.allclose(seq.load(1), folder_frames(scene["folders"]["png"], scene["K"])[1]["image"], atol=0.05)

    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="dfvo.data"):
        seq = open_rosbag(path, fx=190.0, cy=cy, dist=[0.0, 0.0, 0.0, 0.0])
    lines = [r.getMessage() for r in caplog.records if "replace" in r.getMessage()]
    assert len(lines) == 1 and "data.fx=190.0 (CameraInfo: 185.0)" in lines[0] and "data.dist=" in lines[0]
    assert "data.cy" not in lines[0]  # the same value: no disagreement
    assert seq.K[0, 0].item() == 190.0 and seq.K[1, 1].item() == 184.0

    no_info = make_bag(scene, scene["root"] / "no_info.bag", "ros1", "rgb8", gt=None, info=False)
    with pytest.raises(DatasetError, match=r"has no sensor_msgs/CameraInfo for the images; give the intrinsics "
                                           r"data.fx= data.fy= data.cx= data.cy="):
        open_rosbag(no_info)
    with pytest.raises(IntrinsicsError, match=r"^data.cx=3670 in data.path=.*no_info.bag \(/camera/image_raw\) is "
                                              "outside the 320-px-wide image"):
        open_rosbag(no_info, fx=185, fy=184, cx=3670, cy=40)


def test_ground_truth_topics_and_frames(scene: dict, bags: dict) -> None:
    """A TF topic with several transforms needs parent and child (the message lists them); a PoseStamped of a body
    takes data.gt_child_frame and /tf_static; a given camera transform replaces /tf_static; no chain is one line."""
    with pytest.raises(DatasetError, match=r"data.gt_topic=/tf: 2 transforms match data.gt_parent_frame=None, "
                                           r"data.gt_child_frame=None; its transforms: map -> odom \(16\), odom -> "
                                           r"base_link \(16\); choose one"):
        open_rosbag(bags["sqlite3"], gt_topic="/tf")
    seq = open_rosbag(bags["sqlite3"], gt_topic="/tf", gt_child_frame="base_link")
    np.testing.assert_allclose(seq.poses, scene["poses"], atol=1e-9)
    # the Odometry bag's body poses with the camera transform given (7 numbers) instead of /tf_static
    from dfvo.io.rosbag import rotation_to_quaternion as quat

    given = [*T_BODY_CAMERA[:3, 3], *quat(T_BODY_CAMERA[:3, :3])]
    seq = open_rosbag(bags["ros1"], gt_topic="/ground_truth", gt_camera_transform=given)
    np.testing.assert_allclose(seq.poses, scene["poses"], atol=1e-9)
    seq = open_rosbag(bags["ros1"], gt_topic="/ground_truth", gt_camera_transform=list(np.eye(4).ravel()))
    assert not np.allclose(seq.poses, scene["poses"], atol=1e-3)  # the body's poses, not the camera's
    with pytest.raises(ValueError, match=r"data.gt_camera_transform has 3 numbers; expected \[x, y, z, qx, qy, qz, "
                                         r"qw\]"):
        open_rosbag(bags["ros1"], gt_topic="/ground_truth", gt_camera_transform=[1, 2, 3])
    with pytest.raises(DatasetError, match=r"data.gt_topic=/ground_truth: poses of frame 'base_link', images in frame "
                                           r"'camera_optical', and no /tf_static chain between them; give "
                                           r"data.gt_camera_transform="):
        open_rosbag(bags["mcap"], gt_topic="/ground_truth", gt_child_frame="base_link")
    with pytest.raises(DatasetError, match=r"data.gt_topic=/camera/camera_info is sensor_msgs/msg/CameraInfo; expected "
                                           "one of geometry_msgs/msg/PoseStamped"):
        open_rosbag(bags["mcap"], gt_topic="/camera/camera_info")


# ------------------------------------------------------------------------------------------------ bad input
def test_bad_bags_are_one_line(scene: dict, bags: dict, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    m = Msgs(False)
    info = m.camera_info(scene["K"], H, W)
    no_image = write_bag(tmp_path / "no_image", "sqlite3", [("/camera/camera_info", "sensor_msgs/msg/CameraInfo",
                                                             T0, info)], m)
    with pytest.raises(DatasetError, match=r"^data.path=.*no_image holds no image topic \(sensor_msgs/Image or "
                                           r"sensor_msgs/CompressedImage\); its topics: /camera/camera_info "
                                           r"\(sensor_msgs/msg/CameraInfo, 1 messages\)$"):
        open_rosbag(no_image)
    two = frame_messages(scene, m, "bgr8") + [("/left/image", "sensor_msgs/msg/CompressedImage", T0 + k,
                                               m.compressed(png_bytes(scene["frames"][k]), "png", T0 + k))
                                              for k in range(2)]
    two_path = write_bag(tmp_path / "two", "mcap", two, m)
    with pytest.raises(DatasetError, match=r"holds 2 image topics: /camera/image_raw \(sensor_msgs/msg/Image, 9 "
                                           r"messages\), /left/image \(sensor_msgs/msg/CompressedImage, 2 messages\); "
                                           "choose one with data.topic=TOPIC$"):
        open_rosbag(two_path)
    with pytest.raises(DatasetError, match=r"^data.topic=/right: no such topic in data.path=.*two; its image topics"):
        open_rosbag(two_path, topic="/right")
    assert open_rosbag(two_path, topic="/left/image", fx=185, fy=184, cx=160, cy=48).length == 2
    yuv = [("/cam/image", "sensor_msgs/msg/Image", T0, m.image(scene["frames"][0][..., :2].copy(), "yuv422", T0))]
    with pytest.raises(DatasetError, match=r"^data.path=.*yuv, /cam/image frame 0: image encoding 'yuv422' is not "
                                           r"supported; expected one of mono8, 8UC1, mono16"):
        open_rosbag(write_bag(tmp_path / "yuv", "sqlite3", yuv, m), fx=185, fy=184, cx=160, cy=48)

    expected = r"expected a ROS 1 .bag file, a ROS 2 bag folder \(metadata.yaml\) or a ROS 2 .db3/.mcap file"
    (tmp_path / "notes.bag").write_text("not a bag")
    (tmp_path / "notes.db3").write_text("not a bag" * 100)
    (tmp_path / "empty").mkdir()
    for path in (tmp_path / "notes.bag", tmp_path / "notes.db3", tmp_path / "empty"):
        with pytest.raises(DatasetError, match=rf"^data.path={re.escape(str(path))}: .*{expected}"):
            open_rosbag(path)
    with pytest.raises(FileNotFoundError, match=r"missing.bag: no such file or folder"):
        open_rosbag(tmp_path / "missing.bag")
    # cut short: half of the ROS 1 bag (its index is at the end), of the MCAP file, of the sqlite3 database
    data = bags["ros1"].read_bytes()
    (tmp_path / "cut.bag").write_bytes(data[: len(data) // 2])
    mcap = next(bags["mcap"].glob("*.mcap")).read_bytes()
    (tmp_path / "cut.mcap").write_bytes(mcap[: len(mcap) // 2])
    db = next(bags["sqlite3"].glob("*.db3")).read_bytes()
    (tmp_path / "cut_db").mkdir()
    (tmp_path / "cut_db" / "cut_db.db3").write_bytes(db[: len(db) // 2])  # no metadata.yaml either
    for path in (tmp_path / "cut.bag", tmp_path / "cut.mcap", tmp_path / "cut_db"):
        where = re.escape(str(path))
        with pytest.raises(DatasetError, match=rf"^data.path={where}: cannot read the bag \(.*\); {expected}, "
                                               r"complete \(a recording cut short needs rosbag reindex"):
            open_rosbag(path)
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)  # as if rosbags were not installed
    with pytest.raises(ImportError) as err:
        open_rosbag(bags["ros1"])
    assert str(err.value) == ROSBAG_HINT == 'data=rosbag needs the rosbags library: pip install "dfvo[ros]"'


def test_infer_errors_are_one_line(infer_cli, tmp_path: Path) -> None:
    (tmp_path / "notes.bag").write_text("not a bag")
    for args, line in (
            ((), "data=rosbag needs data.path=BAG"),
            ((f"data.path={tmp_path / 'notes.bag'}",), f"data.path={tmp_path / 'notes.bag'}: cannot read the bag"),
            ((f"data.path={tmp_path / 'notes.bag'}", "data.gt=gt.txt", "data.gt_topic=/gt"),
             "data.gt=gt.txt and data.gt_topic=/gt: give one ground truth")):
        proc = infer_cli("data=rosbag", *args, f"out_dir={tmp_path / 'out'}", "progress=false", check=False)
        assert proc.returncode == 1, proc.stderr
        errors = [ln for ln in proc.stderr.splitlines() if "error:" in ln]
        assert len(errors) == 1 and line in errors[0], proc.stderr


# ------------------------------------------------------------------------------------------------ runs
def read_kitti(path: Path) -> np.ndarray:
    rows = np.loadtxt(path, ndmin=2)
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    T[:, :3, :4] = rows.reshape(-1, 3, 4)
    return T


@needs_checkpoints
def test_infer_on_bags_gives_the_folder_poses_and_metrics(scene: dict, bags: dict, infer_cli,
                                                          tmp_path: Path) -> None:
    """``infer.py data=rosbag`` on the ROS 1, sqlite3 and MCAP bags (intrinsics from CameraInfo, ground truth from
    the bag's pose topic) gives the poses of ``data=folder`` on the same PNGs with the same intrinsics (1e-6) and the
    metrics against the folder's TUM ground truth; the MCAP run also writes its odometry bag as MCAP."""
    K = scene["K"]
    intr = [f"data.fx={K[0, 0]:.17g}", f"data.fy={K[1, 1]:.17g}", f"data.cx={K[0, 2]:.17g}", f"data.cy={K[1, 2]:.17g}"]
    out = tmp_path / "folder"
    infer_cli("data=folder", f"data.root={scene['folders']['png']}", *intr, f"data.gt={scene['root'] / 'gt.tum'}",
              f"data.times={scene['root'] / 'times.txt'}", f"out_dir={out}", *SMALL)
    ref = read_kitti(out / "png.txt")
    ref_metrics = json.loads((out / "metrics.json").read_text())
    for storage, gt in (("ros1", "/ground_truth"), ("sqlite3", "/tf"), ("mcap", "/ground_truth")):
        run = tmp_path / storage
        extra = ["data.gt_child_frame=base_link"] if storage == "sqlite3" else []
        extra += ["output.rosbag=true", "output.rosbag_storage=mcap"] if storage == "mcap" else []
        infer_cli("data=rosbag", f"data.path={bags[storage]}", f"data.gt_topic={gt}", *extra, f"out_dir={run}",
                  *SMALL)
        poses = read_kitti(run / f"{bags[storage].stem}.txt")
        assert poses.shape == ref.shape and np.abs(poses - ref).max() < 1e-6, (storage, np.abs(poses - ref).max())
        metrics = json.loads((run / "metrics.json").read_text())
        assert set(metrics) == set(ref_metrics) and metrics["num_gt_frames"] == N and metrics["gt_missing"] == 0
        for key, value in ref_metrics.items():
            if isinstance(value, float):
                assert metrics[key] == pytest.approx(value, rel=1e-6, abs=1e-9), (storage, key)
            elif key != "sequence":
                assert metrics[key] == value, (storage, key)
    # the odometry bag of the MCAP run, read back as a bag of its own (nav_msgs/Odometry of the camera)
    written = tmp_path / "mcap" / "bag"
    assert [p.name for p in written.glob("*.mcap")] == ["bag.mcap"] and not list(written.glob("*.db3"))
    from dfvo.data.rosbag_input import read_pose_topic

    track = read_pose_topic(RosBag(written), "/dfvo/odometry")
    np.testing.assert_array_equal(track.stamps_ns, [stamp_ns(t) for t in scene["stamps"]])
    np.testing.assert_allclose(track.poses, ref, atol=1e-6)
