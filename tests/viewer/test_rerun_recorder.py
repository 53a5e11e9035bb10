"""RerunRecorder: a recording of synthetic frames read back with Rerun's own reader (values, not just presence),
an interrupted recording, the missing-SDK message and the no-display fallback."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from dfvo.synthetic import SyntheticWorld
from dfvo.vis.colour import flow_to_color

REPO = Path(__file__).resolve().parents[2]
N = 5
H, W = 48, 160


def _rerun_cli() -> str:
    exe = Path(sys.executable).parent / "rerun"
    return str(exe) if exe.exists() else "rerun"


def _diag(i: int) -> dict:
    """A frames.csv-like row: frame 0 is the reference (nothing measured), frame 3 falls back to PnP."""
    if i == 0:
        return {"frame": 0, "tracker": "init", "num_inliers": None, "scale": None, "fallback_reason": None}
    return {"frame": i, "tracker": "PnP" if i == 3 else "E", "num_correspondences": 50, "num_inliers": 40 - i,
            "gric_e": 100.0 + 0.5 * i, "gric_h": float("nan") if i == 2 else 130.0, "scale": 0.9 + 0.1 * i,
            "fallback_reason": "low cheirality" if i == 3 else "", "constant_motion": False, "pnp_failed": False}


@pytest.fixture(scope="module")
def world() -> SyntheticWorld:
    return SyntheticWorld(seed=3, num_frames=N + 1, height=H, width=W)


@pytest.fixture(scope="module")
def recording(world: SyntheticWorld, tmp_path_factory: pytest.TempPathFactory):
    pytest.importorskip("rerun")
    from dfvo.viewer import RerunRecorder

    path = tmp_path_factory.mktemp("rrd") / "out" / "run.rrd"
    poses = world.poses().numpy()
    rng = np.random.default_rng(0)
    logged: dict = {"poses": poses, "frames": []}
    with RerunRecorder(path, world.intrinsics(), (H, W), gt_poses=poses, jpeg_quality=None,
                       recording_name="synthetic") as rec:
        for i in range(N):
            d = world.render(i, right=False)
            cur = rng.uniform(0, [W, H], size=(30, 2)).astype(np.float32)
            prev = cur - rng.uniform(-2, 2, size=(30, 2)).astype(np.float32)
            inlier = rng.random(30) > 0.3
            pts = rng.normal(size=(12, 3)) * 5 + [0, 0, 10]
            inc = d["flow_fwd"][:1].abs()  # any (1,H,W) map: it is shown, not interpreted
            rec.log_frame(i, poses[i], image=d["image"], flow_fwd=d["flow_fwd"], inconsistency=inc,
                          depth=d["depth"], pts_prev=prev, pts_cur=cur, inlier=inlier, points_world=pts,
                          diagnostics=_diag(i))
            logged["frames"].append({"image": d["image"], "flow": d["flow_fwd"], "depth": d["depth"], "cur": cur,
                                     "prev": prev, "inlier": inlier, "points": pts})
    from dfvo.viewer import read_rrd

    return path, read_rrd(path), logged


def _raw_image(value_buffer: list, value_format: list) -> np.ndarray:
    fmt = value_format[0]
    return np.asarray(value_buffer[0], dtype=np.uint8).reshape(fmt["height"], fmt["width"], -1)


def test_every_entity_present(recording) -> None:
    from dfvo.viewer import ENTITIES

    path, rec, _ = recording
    expected = {e for e in ENTITIES if e != "diagnostics"}
    assert expected <= rec.entities, expected - rec.entities
    assert {"diagnostics/tracker", "diagnostics/tracker_code", "diagnostics/num_inliers", "diagnostics/scale",
            "diagnostics/gric_e", "diagnostics/fallback_reason"} <= rec.entities
    proc = subprocess.run([_rerun_cli(), "rrd", "verify", str(path)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr


def test_one_pose_per_frame_equal_to_the_poses_logged(recording) -> None:
    _, rec, logged = recording
    assert rec.frames("world/camera", "pose_3x4") == list(range(N))
    assert rec.frames("world/camera", "Transform3D:translation") == list(range(N))
    poses = rec.poses()
    for i in range(N):
        np.testing.assert_array_equal(poses[i], logged["poses"][i])  # float64, exact
        np.testing.assert_allclose(rec.transforms()[i], logged["poses"][i], atol=1e-5)  # float32 transform
    # the path so far: i+1 centres at frame i; the ground truth once, static
    path_now = rec.values("world/path", "LineStrips3D:strips")
    for i in range(N):
        np.testing.assert_allclose(np.asarray(path_now[i][0]), logged["poses"][: i + 1, :3, 3], atol=1e-5)
    gt = np.asarray(rec.static["world/ground_truth"]["LineStrips3D:strips"][0])
    np.testing.assert_allclose(gt, logged["poses"][:, :3, 3], atol=1e-5)
    K = np.asarray(rec.static["world/camera/image"]["Pinhole:image_from_camera"][0]).reshape(3, 3).T
    np.testing.assert_allclose(K, SyntheticWorld(seed=3, num_frames=2, height=H, width=W).intrinsics(), rtol=1e-6)
    assert rec.static["world/camera/image"]["Pinhole:resolution"][0] == [W, H]


def test_scalars_equal_the_diagnostics_logged(recording) -> None:
    _, rec, _ = recording
    for key in ("num_inliers", "gric_e", "gric_h", "scale", "num_correspondences", "constant_motion"):
        want = {}
        for i in range(N):
            v = _diag(i).get(key)
            if v is not None and not (isinstance(v, float) and np.isnan(v)):
                want[i] = float(v)
        assert rec.scalars(key) == pytest.approx(want), key
    assert 2 not in rec.scalars("gric_h") and 0 not in rec.scalars("scale")  # NaN / None: not logged
    assert rec.texts("diagnostics/tracker") == {i: _diag(i)["tracker"] for i in range(N)}
    assert rec.scalars("tracker_code") == {0: 0.0, 1: 1.0, 2: 1.0, 3: 2.0, 4: 1.0}
    assert rec.texts("diagnostics/fallback_reason") == {3: "low cheirality"}
    levels = {f: v[0] for f, v in rec.values("log", "TextLog:level").items()}
    assert levels[3] == "WARN" and levels[1] == "INFO" and "tracker=PnP" in rec.texts("log")[3]


def test_images_depth_points_and_correspondences(recording) -> None:
    _, rec, logged = recording
    rgb_buf, rgb_fmt = (rec.values("world/camera/image/rgb", c) for c in ("Image:buffer", "Image:format"))
    flow_buf, flow_fmt = (rec.values("flow", c) for c in ("Image:buffer", "Image:format"))
    depth_buf = rec.values("world/camera/image/depth", "DepthImage:buffer")
    pts2 = rec.values("world/camera/image/correspondences", "Points2D:positions")
    cols2 = rec.values("world/camera/image/correspondences", "Points2D:colors")
    tracks = rec.values("world/camera/image/tracks", "LineStrips2D:strips")
    pts3 = rec.values("world/points", "Points3D:positions")
    for i, f in enumerate(logged["frames"]):
        img = _raw_image(rgb_buf[i], rgb_fmt[i])
        np.testing.assert_allclose(img / 255.0, f["image"].permute(1, 2, 0).numpy(), atol=0.5 / 255 + 1e-6)
        want_flow = flow_to_color(f["flow"][None])[0].permute(1, 2, 0).numpy()
        np.testing.assert_allclose(_raw_image(flow_buf[i], flow_fmt[i]) / 255.0, want_flow, atol=0.5 / 255 + 1e-6)
        depth = np.frombuffer(np.asarray(depth_buf[i][0], dtype=np.uint8).tobytes(), dtype=np.float16)
        np.testing.assert_allclose(depth.reshape(H, W), f["depth"][0].numpy(), rtol=1e-3)  # float16
        np.testing.assert_allclose(np.asarray(pts2[i]), f["cur"], atol=1e-6)
        # colours packed RGBA u32: green inliers, red outliers
        red = (np.asarray(cols2[i], dtype=np.uint64) >> 24) & 0xFF
        assert ((red < 100) == f["inlier"]).all()
        strips = np.asarray(tracks[i])
        np.testing.assert_allclose(strips[:, 0], f["prev"], atol=1e-6)
        np.testing.assert_allclose(strips[:, 1], f["cur"], atol=1e-6)
        np.testing.assert_allclose(np.asarray(pts3[i]), f["points"], rtol=1e-6, atol=1e-5)


def test_interrupted_recording_keeps_the_frames_logged(tmp_path: Path) -> None:
    pytest.importorskip("rerun")
    from dfvo.viewer import read_rrd

    path = tmp_path / "run.rrd"
    script = textwrap.dedent(f"""
        import os
        import numpy as np
        from dfvo.viewer import RerunRecorder
        rec = RerunRecorder({str(path)!r}, np.diag([50.0, 50.0, 1.0]), (24, 32))
        for i in range(3):
            T = np.eye(4)
            T[:3, 3] = [0.1 * i, 0.0, 1.0 * i]
            rec.log_frame(i, T, image=np.full((3, 24, 32), 0.5), diagnostics={{"num_inliers": 10 + i}})
        os._exit(1)  # killed: no close(), no interpreter shutdown
        """)
    proc = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1, proc.stderr
    rec = read_rrd(path)
    assert rec.frames("world/camera", "pose_3x4") == [0, 1, 2]
    assert [T[2, 3] for _, T in sorted(rec.poses().items())] == [0.0, 1.0, 2.0]
    assert rec.scalars("num_inliers") == {0: 10.0, 1: 11.0, 2: 12.0}
    printed = subprocess.run([_rerun_cli(), "rrd", "print", str(path)], capture_output=True, text=True, timeout=120)
    assert printed.returncode == 0 and "/world/camera" in printed.stdout + printed.stderr


def test_images_every_and_jpeg(tmp_path: Path) -> None:
    pytest.importorskip("rerun")
    from dfvo.viewer import RerunRecorder, read_rrd

    with RerunRecorder(tmp_path / "r.rrd", np.diag([50.0, 50.0, 1.0]), (24, 32), images_every=2) as rec:
        for i in range(5):
            rec.log_frame(i, np.eye(4), image=torch.rand(1, 3, 24, 32), flow_fwd=torch.zeros(2, 24, 32))
    out = read_rrd(tmp_path / "r.rrd")
    assert out.frames("world/camera/image/rgb", "EncodedImage:media_type") == [0, 2, 4]
    assert out.values("flow", "EncodedImage:media_type")[2] == ["image/jpeg"]
    assert out.frames("world/camera", "pose_3x4") == [0, 1, 2, 3, 4]


def test_bad_input_names_the_argument(tmp_path: Path) -> None:
    pytest.importorskip("rerun")
    from dfvo.viewer import RerunRecorder

    rec = RerunRecorder(tmp_path / "r.rrd", np.eye(3), (24, 32))
    with pytest.raises(ValueError, match=r"image has shape \(3, 20, 32\); expected \(3,24,32\)"):
        rec.log_frame(0, np.eye(4), image=np.zeros((3, 20, 32)))
    with pytest.raises(ValueError, match="T_w_c"):
        rec.log_frame(0, np.full((4, 4), np.nan))
    rec.close()
    rec.close()
    with pytest.raises(RuntimeError, match="after close"):
        rec.log_frame(1, np.eye(4))
    with pytest.raises(ValueError, match="image_hw"):
        RerunRecorder(tmp_path / "s.rrd", np.eye(3), (0, 32))


def test_without_the_sdk_one_line(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from dfvo.viewer import MISSING_SDK_MESSAGE, RerunRecorder

    monkeypatch.setitem(sys.modules, "rerun", None)  # import rerun -> ImportError
    with pytest.raises(ImportError) as err:
        RerunRecorder(tmp_path / "r.rrd", np.eye(3), (24, 32))
    assert str(err.value) == MISSING_SDK_MESSAGE == 'viewer=rerun needs the Rerun SDK: pip install "dfvo[viewer]"'
    assert err.value.__cause__ is None and err.value.__suppress_context__
    assert not (tmp_path / "r.rrd").exists()


def test_spawn_without_display_warns_once_and_writes_the_file(monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
                                                              caplog: pytest.LogCaptureFixture) -> None:
    pytest.importorskip("rerun")
    import dfvo.viewer.rerun_recorder as mod

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(mod, "_warned_no_display", False)
    monkeypatch.setattr(mod.sys, "platform", "linux")
    with caplog.at_level(logging.WARNING, logger=mod.__name__):
        for name in ("a.rrd", "b.rrd"):
            with mod.RerunRecorder(tmp_path / name, np.eye(3), (24, 32), spawn=True) as rec:
                rec.log_frame(0, np.eye(4))
            assert not rec.spawned
    warnings = [r for r in caplog.records if "no display" in r.getMessage()]
    assert len(warnings) == 1 and "a.rrd" in warnings[0].getMessage()
    assert os.path.getsize(tmp_path / "b.rrd") > 0


def test_diagnostics_given_as_frames_csv_strings(tmp_path: Path) -> None:
    pytest.importorskip("rerun")
    from dfvo.viewer import RerunRecorder, read_rrd

    row = {"frame": "1", "tracker": "constant_motion", "num_inliers": "12", "scale": "1.25", "gric_h": "nan",
           "fallback_reason": "", "constant_motion": "1", "pnp_failed": "False"}
    with RerunRecorder(tmp_path / "r.rrd", np.eye(3), (24, 32)) as rec:
        rec.log_frame(1, np.eye(4), diagnostics=row)
    out = read_rrd(tmp_path / "r.rrd")
    assert out.scalars("num_inliers") == {1: 12.0} and out.scalars("scale") == {1: 1.25}
    assert out.scalars("constant_motion") == {1: 1.0} and out.scalars("tracker_code") == {1: 3.0}
    assert out.scalars("pnp_failed") == {1: 0.0}
    assert out.texts("diagnostics/tracker") == {1: "constant_motion"}
    assert "diagnostics/gric_h" not in out.entities and "diagnostics/fallback_reason" not in out.entities
    assert out.values("log", "TextLog:level")[1] == ["WARN"]
