"""KITTI odometry as a ROS 2 bag, and the check that ``data=rosbag`` on it gives what ``data=kitti_odom`` gives.

    python scripts/kitti_to_rosbag.py --root ../shared/data/kitti_odom --seq 07 --out runs/kitti07_bag
    python scripts/kitti_to_rosbag.py --root ... --seq 07 --out runs/kitti07_bag --storage mcap --no-run

Writes ``OUT/kitti_SEQ`` (a ROS 2 bag, sqlite3 or MCAP) with the sequence's left frames (``image_2`` as ``rgb8``,
else ``image_0`` as ``mono8``) on ``/kitti/camera/image_raw``, their ``sensor_msgs/CameraInfo`` (``K = P[:3,:3]``
of ``calib.txt``, no distortion: the frames are rectified) on ``/kitti/camera/camera_info`` and the ground-truth
poses of the camera (``poses/SEQ.txt``) as ``geometry_msgs/PoseStamped`` on ``/kitti/ground_truth``, all stamped
with ``times.txt`` (+ ``--t0`` seconds). Then (unless ``--no-run``) it runs ``infer.py`` twice with the same
overrides, ``data=kitti_odom`` and ``data=rosbag data.gt_topic=/kitti/ground_truth data.camera_height=1.65`` (the
height the KITTI reader sets), and prints one JSON object: both runs' metrics (RPE, ATE, KITTI errors) and the
largest difference between their poses. Not run by the tests (a few minutes on a CPU); the tests write small bags
of the synthetic world (tests/data/test_rosbag_input.py).
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
from PIL import Image

from dfvo.data.calibration import read_calib_file
from dfvo.data.image_io import list_images
from dfvo.io.trajectory import rotation_to_quaternion

REPO = Path(__file__).resolve().parents[1]
TOPIC_IMAGE = "/kitti/camera/image_raw"
TOPIC_INFO = "/kitti/camera/camera_info"
TOPIC_GT = "/kitti/ground_truth"


def write_bag(root: Path, seq: str, path: Path, storage: str, t0: float) -> int:
    """The sequence as a ROS 2 bag at ``path`` (see the module docstring); returns the number of frames."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    folder = root / "sequences" / seq
    camera = "image_2" if (folder / "image_2").is_dir() else "image_0"
    files = list_images(folder / camera, f"KITTI {camera}")
    times = np.loadtxt(folder / "times.txt", ndmin=1)[: len(files)] + t0
    gt_file = root / "poses" / f"{seq}.txt"
    poses = np.loadtxt(gt_file, ndmin=2).reshape(-1, 3, 4) if gt_file.is_file() else None
    P = read_calib_file(folder / "calib.txt")["P2" if camera == "image_2" else "P0"].reshape(3, 4)
    K = P[:, :3]

    def header(t: float, frame: str) -> object:
        sec = math.floor(t)
        return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
            sec=int(sec), nanosec=min(int(round((t - sec) * 1e9)), 999_999_999)), frame_id=frame)

    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as writer:
        c_img = writer.add_connection(TOPIC_IMAGE, "sensor_msgs/msg/Image", typestore=ts)
        c_info = writer.add_connection(TOPIC_INFO, "sensor_msgs/msg/CameraInfo", typestore=ts)
        c_gt = writer.add_connection(TOPIC_GT, "geometry_msgs/msg/PoseStamped", typestore=ts) \
            if poses is not None else None
        quats = rotation_to_quaternion(poses[:, :3, :3]) if poses is not None else None
        for k, (file, t) in enumerate(zip(files, times, strict=True)):
            with Image.open(file) as im:
                arr = np.asarray(im.convert("RGB" if camera == "image_2" else "L"), dtype=np.uint8)
            h, w = arr.shape[:2]
            enc, step = ("rgb8", 3 * w) if arr.ndim == 3 else ("mono8", w)
            stamp = int(round(t * 1e9))
            img = T["sensor_msgs/msg/Image"](header=header(t, "camera_left"), height=h, width=w, encoding=enc,
                                             is_bigendian=0, step=step, data=arr.reshape(-1))
            writer.write(c_img, stamp, ts.serialize_cdr(img, "sensor_msgs/msg/Image"))
            if k == 0:
                roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                            do_rectify=False)
                info = T["sensor_msgs/msg/CameraInfo"](
                    header=header(t, "camera_left"), height=h, width=w, distortion_model="plumb_bob",
                    d=np.zeros(5), k=K.reshape(-1).astype(np.float64), r=np.eye(3).reshape(-1),
                    p=P.reshape(-1).astype(np.float64), binning_x=0, binning_y=0, roi=roi)
                writer.write(c_info, stamp, ts.serialize_cdr(info, "sensor_msgs/msg/CameraInfo"))
            if c_gt is not None and k < len(poses):
                x, y, z, qw = quats[k]
                pose = T["geometry_msgs/msg/Pose"](
                    position=T["geometry_msgs/msg/Point"](x=poses[k, 0, 3], y=poses[k, 1, 3], z=poses[k, 2, 3]),
                    orientation=T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=qw))
                msg = T["geometry_msgs/msg/PoseStamped"](header=header(t, "world"), pose=pose)
                writer.write(c_gt, stamp, ts.serialize_cdr(msg, "geometry_msgs/msg/PoseStamped"))
    return len(files)


def read_kitti(path: Path) -> np.ndarray:
    return np.loadtxt(path, ndmin=2).reshape(-1, 3, 4)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--root", type=Path, default=REPO.parent / "shared" / "data" / "kitti_odom")
    ap.add_argument("--seq", default="07")
    ap.add_argument("--out", type=Path, default=REPO / "runs" / "kitti_bag")
    ap.add_argument("--storage", choices=("sqlite3", "mcap"), default="sqlite3")
    ap.add_argument("--t0", type=float, default=0.0, help="seconds added to times.txt (e.g. 1.7e9 for epoch stamps)")
    ap.add_argument("--no-run", action="store_true", help="write the bag only")
    ap.add_argument("overrides", nargs="*", help="infer.py overrides for both runs (e.g. num_threads=1)")
    args = ap.parse_args()
    seq = args.seq.zfill(2)
    bag = args.out / f"kitti_{seq}"
    if bag.exists():
        sys.exit(f"{bag} exists; remove it or choose another --out")
    args.out.mkdir(parents=True, exist_ok=True)
    n = write_bag(args.root, seq, bag, args.storage, args.t0)
    report: dict = {"bag": str(bag), "storage": args.storage, "frames": n}
    if not args.no_run:
        runs = {"kitti_odom": ["data=kitti_odom", f"data.root={args.root}", f"seq={seq}"],
                "rosbag": ["data=rosbag", f"data.path={bag}", f"data.gt_topic={TOPIC_GT}", "data.camera_height=1.65"]}
        for name, data in runs.items():
            out = args.out / name
            subprocess.run([sys.executable, str(REPO / "infer.py"), *data, f"out_dir={out}", "progress=false",
                            *args.overrides], check=True)
            metrics = json.loads((out / "metrics.json").read_text())
            report[name] = {k: v for k, v in metrics.items() if not isinstance(v, dict | list)}
        a, b = read_kitti(args.out / "kitti_odom" / f"{seq}.txt"), read_kitti(args.out / "rosbag" / f"kitti_{seq}.txt")
        report["max_pose_difference"] = float(np.abs(a - b).max()) if a.shape == b.shape else None
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
