"""EuRoC reader on a tiny ASL layout made from the synthetic world: poses through a non-identity T_BS, nearest-time
association, timestamps, sensor.yaml intrinsics, frame ranges, undistortion and the error messages."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from dfvo.data.euroc import EurocSequence, open_euroc, read_sensor_yaml
from dfvo.data.image_io import DatasetError, DatasetNotFoundError
from dfvo.data.intrinsics_check import IntrinsicsError
from dfvo.geometry.camera import resize_intrinsics
from dfvo.synthetic import SyntheticWorld

Rotation = pytest.importorskip("scipy.spatial.transform", reason="SciPy (test-only reference) not installed").Rotation
cv2 = pytest.importorskip("cv2", reason="OpenCV (test-only reference) not installed")

N, H, W = 8, 64, 208
T0_NS = 1403636579763555584  # first frame of MH_01_easy
DT_NS = 50_000_000  # 20 Hz
# cam0 T_BS of the EuRoC MAV dataset (camera -> body/IMU), a real, non-identity extrinsic
T_BS = np.array([[0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
                 [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
                 [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
                 [0.0, 0.0, 0.0, 1.0]])


class Scene:
    """The synthetic world's frames (8-bit gray, like EuRoC's), true camera poses and intrinsics, rendered once."""

    def __init__(self) -> None:
        world = SyntheticWorld(seed=5, num_frames=N, height=H, width=W)
        self.frames = [(world.image(i).mean(0).numpy() * 255).round().astype(np.uint8) for i in range(N)]
        self.poses = world.poses().double().numpy()
        self.K = world.intrinsics().double().numpy()


@pytest.fixture(scope="module")
def world() -> Scene:
    return Scene()


def sensor_yaml(K: np.ndarray, dist: list[float], w: int, h: int, header: str = "", model: str = "radial-tangential"
                ) -> str:
    T = ", ".join(f"{v:.17g}" for v in T_BS.ravel())
    return (f"{header}# General sensor definitions.\nsensor_type: camera\ncomment: VI-Sensor cam0 (MT9M034)\n\n"
            f"T_BS:\n  cols: 4\n  rows: 4\n  data: [{T}]\n\nrate_hz: 20\nresolution: [{w}, {h}]\n"
            f"camera_model: pinhole\nintrinsics: [{K[0, 0]:.17g}, {K[1, 1]:.17g}, {K[0, 2]:.17g}, {K[1, 2]:.17g}] "
            f"#fu, fv, cu, cv\ndistortion_model: {model}\n"
            f"distortion_coefficients: [{', '.join(f'{float(d):.17g}' for d in dist)}]\n")


def gt_row(t_ns: int, T_w_b: np.ndarray) -> str:
    qx, qy, qz, qw = Rotation.from_matrix(T_w_b[:3, :3]).as_quat()  # independent quaternion reference
    vals = [*T_w_b[:3, 3], qw, qx, qy, qz] + [0.0] * 9
    return f"{t_ns}," + ",".join(f"{v:.17g}" for v in vals)


def build_euroc(root: Path, world: Scene, frames: list[np.ndarray] | None = None, dist: list[float] = (),
                gt_from: int = 2, gt_gap: int | None = None, header: str = "", model: str = "radial-tangential",
                K: np.ndarray | None = None) -> list[int]:
    """Write ROOT/mav0/{cam0, state_groundtruth_estimate0}; ground truth starts at frame ``gt_from``."""
    cam = root / "mav0" / "cam0"
    (cam / "data").mkdir(parents=True)
    stamps = [T0_NS + i * DT_NS for i in range(N)]
    frames = frames if frames is not None else world.frames
    lines = ["#timestamp [ns],filename"]
    for img, t in zip(frames, stamps):
        Image.fromarray(img).save(cam / "data" / f"{t}.png")
        lines.append(f"{t},{t}.png")
    (cam / "data.csv").write_text("\n".join(lines) + "\n")
    K = world.K if K is None else K
    h, w = frames[0].shape
    (cam / "sensor.yaml").write_text(sensor_yaml(K, list(dist), w, h, header, model))
    # 200 Hz ground truth of the BODY: the true sample 0.4 ms after each frame, decoys 4.6 ms before/5.4 ms after
    poses_c = world.poses
    rows = ["#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], ..."]
    decoy = np.eye(4)
    decoy[:3, 3] = (1.0, -2.0, 0.5)
    for i in range(gt_from, N):
        if i == gt_gap:
            continue
        T_w_b = poses_c[i] @ np.linalg.inv(T_BS)
        rows += [gt_row(stamps[i] - 4_600_000, decoy @ T_w_b), gt_row(stamps[i] + 400_000, T_w_b),
                 gt_row(stamps[i] + 5_400_000, T_w_b @ decoy)]
    gt = root / "mav0" / "state_groundtruth_estimate0"
    gt.mkdir()
    (gt / "data.csv").write_text("\n".join(rows) + "\n")
    return stamps


def test_poses_timestamps_intrinsics(tmp_path: Path, world: Scene) -> None:
    stamps = build_euroc(tmp_path / "MH_01_easy", world, gt_from=2, header="%YAML:1.0\n")
    seq = open_euroc(tmp_path / "MH_01_easy")
    assert seq.name == "MH_01_easy" and seq.length == N - 2  # the 2 frames before the ground truth are dropped
    truth = world.poses[2:]
    np.testing.assert_allclose(seq.poses, truth, atol=1e-9)
    np.testing.assert_array_equal(seq.timestamps, np.array(stamps[2:]) * 1e-9)
    assert torch.allclose(seq.K, torch.from_numpy(world.K).float())
    img = seq.load(0)
    assert img.shape == (3, H, W) and torch.equal(img[0], img[2])
    assert torch.allclose(img[0], torch.from_numpy(world.frames[2]).float() / 255, atol=1e-6)
    # the extrinsic matters: the body poses are centimetres and a rotation of ~90 degrees away from the camera's
    body = EurocSequence(tmp_path / "MH_01_easy").poses @ np.linalg.inv(T_BS)
    assert np.abs(body[:, :3, 3] - truth[:, :3, 3]).max() > 0.02
    # and mav0/ itself is accepted as the root
    assert open_euroc(tmp_path / "MH_01_easy" / "mav0").length == N - 2


def test_unmatched_policies_and_report(tmp_path: Path, world: Scene) -> None:
    build_euroc(tmp_path / "V1_01", world, gt_from=3)
    seq = EurocSequence(tmp_path / "V1_01")
    assert "5 of 8 frames matched" in seq.report and "dropped 3 frames before and 0 after" in seq.report
    assert list(seq.frame_ids) == [3, 4, 5, 6, 7]
    nan = open_euroc(tmp_path / "V1_01", unmatched="nan")
    assert nan.length == N and np.isnan(nan.poses[:3]).all()
    np.testing.assert_allclose(nan.poses[3:], world.poses[3:], atol=1e-9)
    none = open_euroc(tmp_path / "V1_01", unmatched="none")
    assert none.length == N and none.poses is None
    # a tolerance below the 0.4 ms offset matches nothing: one line says what to check
    with pytest.raises(DatasetError, match=r"none of the 8 frames .* within 0.0001 s"):
        open_euroc(tmp_path / "V1_01", gt_tolerance=1e-4)


def test_frame_range_then_trim(tmp_path: Path, world: Scene) -> None:
    stamps = build_euroc(tmp_path / "seq", world, gt_from=2)
    seq = EurocSequence(tmp_path / "seq", frames=slice(1, 8, 2))  # rows 1, 3, 5, 7; row 1 has no ground truth
    assert list(seq.frame_ids) == [3, 5, 7]
    np.testing.assert_array_equal(seq.timestamps_ns, np.array(stamps)[[3, 5, 7]])
    np.testing.assert_allclose(seq.poses, world.poses[[3, 5, 7]], atol=1e-9)
    fs = open_euroc(tmp_path / "seq", start=3, end=6)
    assert fs.length == 3 and fs.timestamps[0] == stamps[3] * 1e-9


def test_gap_inside_ground_truth(tmp_path: Path, world: Scene) -> None:
    build_euroc(tmp_path / "seq", world, gt_from=1, gt_gap=4)
    with pytest.raises(DatasetError, match=r"1 frames inside the ground-truth span have no pose .* frame 4"):
        open_euroc(tmp_path / "seq")
    seq = open_euroc(tmp_path / "seq", unmatched="nan")
    assert np.isnan(seq.poses[[0, 4]]).all() and np.isfinite(seq.poses[[1, 2, 3, 5, 6, 7]]).all()


def test_resize(tmp_path: Path, world: Scene) -> None:
    build_euroc(tmp_path / "seq", world)
    seq = open_euroc(tmp_path / "seq", height=32, width=96)
    assert seq.load(0).shape == (3, 32, 96)
    expected = resize_intrinsics(torch.from_numpy(world.K), (H, W), (32, 96))
    assert torch.allclose(seq.K.double(), expected, atol=1e-5)


def distort(ideal: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """The image a lens with ``dist`` would record: each distorted pixel samples the ideal image (OpenCV)."""
    h, w = ideal.shape[:2]
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    pts = np.stack([u.ravel(), v.ravel()], -1)[:, None]
    und = cv2.undistortPoints(pts, K, dist, None, None, K, (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-9))
    maps = und.reshape(h, w, 2).astype(np.float32)
    return cv2.remap(ideal, maps[..., 0], maps[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def test_undistortion_recovers_the_pinhole_frame(tmp_path: Path, world: Scene) -> None:
    h, w = 2 * H, 2 * W
    K = np.array([[0.6 * w, 0, 0.5 * w + 3.2], [0, 0.6 * w, 0.5 * h - 2.1], [0, 0, 1.0]])
    dist = np.array([-0.28, 0.07, 0.0008, -0.0004])  # EuRoC-like barrel distortion
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    ideal = [(127.5 + 110 * np.sin(x / (6 + k) + y / 9) * np.cos(y / (7 + k) - x / 17)).astype(np.float32)
             for k in range(N)]
    frames = [np.clip(distort(im, K, dist), 0, 255).round().astype(np.uint8) for im in ideal]
    build_euroc(tmp_path / "seq", world, frames=frames, dist=list(dist), K=K)
    seq = open_euroc(tmp_path / "seq", unmatched="none")
    raw = open_euroc(tmp_path / "seq", unmatched="none", undistort=False)
    inner = np.s_[16:-16, 24:-24]
    err = np.abs(seq.load(4)[0].numpy() * 255 - ideal[4])[inner].mean()
    err_raw = np.abs(raw.load(4)[0].numpy() * 255 - ideal[4])[inner].mean()
    assert err < 1.0 and err_raw > 20 * err, (err, err_raw)


def test_sensor_yaml_and_layout_errors(tmp_path: Path, world: Scene) -> None:
    with pytest.raises(DatasetNotFoundError, match="holds no mav0/"):
        open_euroc(tmp_path)
    build_euroc(tmp_path / "seq", world)
    cam = read_sensor_yaml(tmp_path / "seq/mav0/cam0/sensor.yaml")
    np.testing.assert_array_equal(cam.T_BS, T_BS)
    np.testing.assert_allclose(cam.K, world.K, rtol=1e-15)
    assert cam.resolution == (W, H) and cam.rate_hz == 20.0
    yaml_path = tmp_path / "seq/mav0/cam0/sensor.yaml"
    K_bad = world.K
    K_bad[0, 2] = 3670.0
    yaml_path.write_text(sensor_yaml(K_bad, [], W, H))
    with pytest.raises(IntrinsicsError, match=r"^cu=3670 in .*sensor.yaml is outside the 208-px-wide image"):
        open_euroc(tmp_path / "seq")
    yaml_path.write_text(sensor_yaml(world.K, [0.1, 0.0, 0.0, 0.0], W + 1, H))
    with pytest.raises(DatasetError, match=r"is 208x64, .*sensor.yaml says resolution 209x64"):
        open_euroc(tmp_path / "seq")
    yaml_path.write_text(sensor_yaml(world.K, [0.1, 0.0, 0.0, 0.0], W, H,
                                     model="equidistant"))
    with pytest.raises(DatasetError, match="'equidistant' cannot be undone here"):
        open_euroc(tmp_path / "seq")
    yaml_path.write_text(yaml_path.read_text().replace("intrinsics:", "intrinsix:"))
    with pytest.raises(DatasetError, match=r"sensor.yaml has no 'intrinsics:' entry"):
        open_euroc(tmp_path / "seq")
    yaml_path.write_text(sensor_yaml(world.K, [], W, H))
    (tmp_path / "seq/mav0/cam0/data.csv").write_text("#timestamp [ns],filename\n1403636579763555584,nope.png\n")
    with pytest.raises(DatasetNotFoundError, match=r"names 1 missing files, first .*nope.png"):
        open_euroc(tmp_path / "seq")


MH01_CAM0_YAML = """# General sensor definitions.
sensor_type: camera
comment: VI-Sensor cam0 (MT9M034)

# Sensor extrinsics wrt. the body-frame.
T_BS:
  cols: 4
  rows: 4
  data: [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
         0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
        -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,
         0.0, 0.0, 0.0, 1.0]

# Camera specific definitions.
rate_hz: 20
resolution: [752, 480]
camera_model: pinhole
intrinsics: [458.654, 457.296, 367.215, 248.375] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
"""


def test_the_datasets_own_sensor_yaml(tmp_path: Path) -> None:
    path = tmp_path / "sensor.yaml"
    path.write_text(MH01_CAM0_YAML)  # the layout of EuRoC's cam0/sensor.yaml (multi-line T_BS, comments)
    cam = read_sensor_yaml(path)
    np.testing.assert_array_equal(cam.T_BS, T_BS)
    np.testing.assert_array_equal(cam.K, [[458.654, 0, 367.215], [0, 457.296, 248.375], [0, 0, 1]])
    assert cam.dist == [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
    assert cam.resolution == (752, 480) and cam.distortion_model == "radial-tangential" and cam.rate_hz == 20
