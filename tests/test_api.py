"""The Python API (dfvo.api.Odometry): the poses of infer.py on the same frames, the frame types it takes, bad input
in one line, and a light ``import dfvo``."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from dfvo.synthetic import SyntheticWorld

REPO = Path(__file__).resolve().parents[1]
H, W = 96, 320
SMALL = [f"img_res.width={W}", "num_threads=1"]
needs_checkpoints = pytest.mark.skipif(not (REPO / "dfvo/checkpoints/flow.safetensors").is_file(),
                                       reason="no shipped checkpoints in dfvo/checkpoints")


def uint8_frames(world: SyntheticWorld, n: int) -> list[np.ndarray]:
    return [(world.image(k).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8) for k in range(n)]


def read_kitti(path: Path) -> np.ndarray:
    rows = [line.split() for line in path.read_text().splitlines()]
    assert rows and all(len(r) == 12 for r in rows)
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    T[:, :3, :4] = np.asarray(rows, dtype=np.float64).reshape(-1, 3, 4)
    return T


@pytest.fixture(scope="module")
def world() -> SyntheticWorld:
    return SyntheticWorld(seed=0, num_frames=8, height=H, width=W)


@needs_checkpoints
def test_poses_equal_infer_py_on_the_same_frames(world: SyntheticWorld, tmp_path: Path, infer_cli) -> None:
    """Frames written as PNGs, tracked by ``infer.py data=folder`` (batches of 4 pairs) and fed one by one to the API
    (same overrides, same intrinsics): the same trackers, poses equal to 1e-6 m / rad, and frames.csv's covariance
    equals the API's."""
    from PIL import Image

    import dfvo

    n = 8
    frames = uint8_frames(world, n)
    folder = tmp_path / "frames"
    folder.mkdir()
    for k, img in enumerate(frames):
        Image.fromarray(img).save(folder / f"{k:06d}.png")
    K = world.intrinsics().double().numpy()
    out = tmp_path / "out"
    intr = [f"data.fx={K[0, 0]:.17g}", f"data.fy={K[1, 1]:.17g}", f"data.cx={K[0, 2]:.17g}", f"data.cy={K[1, 2]:.17g}"]
    infer_cli("data=folder", f"data.root={folder}", *intr, f"out_dir={out}", "progress=false", *SMALL)
    cli = read_kitti(out / "frames.txt")
    rows = list(csv.DictReader((out / "frames.csv").open()))

    vo = dfvo.Odometry.from_config(SMALL, K=K)
    results = [vo.step(img, 0.1 * k) for k, img in enumerate(frames)]
    api = np.stack([r.T_w_c for r in results])
    assert [r.tracker for r in results] == [row["tracker"] for row in rows]
    assert np.abs(api - cli).max() < 1e-6, np.abs(api - cli).max()
    from dfvo.geometry.pose_covariance import covariance_from_row

    for r, row in zip(results[1:], rows[1:], strict=True):
        C = covariance_from_row(row).numpy()
        assert np.allclose(r.covariance, C, rtol=1e-4, atol=1e-12)  # frames.csv keeps 6 significant digits
    assert np.allclose(results[0].T_w_c, np.eye(4)) and not results[0].covariance.any()
    assert results[3].timestamp == pytest.approx(0.3)


@needs_checkpoints
def test_frame_types_sizes_and_flags(world: SyntheticWorld, caplog: pytest.LogCaptureFixture) -> None:
    """uint8 RGB, gray, float arrays and tensors give the same working frame; a frame of another size is resized
    with one note (logged once) and flagged, or refused in one line with ``size_change="refuse"``."""
    import dfvo

    frames = uint8_frames(world, 4)
    K = world.intrinsics().double().numpy()
    vo = dfvo.Odometry.from_config(SMALL, fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2])
    a, _ = vo._prepare(frames[0])
    b, _ = vo._prepare(torch.from_numpy(frames[0]).permute(2, 0, 1).float() / 255.0)
    c, _ = vo._prepare(frames[0].astype(np.float32) / 255.0)
    assert torch.allclose(a, b, atol=1e-6) and torch.allclose(a, c, atol=1e-6)
    gray, _ = vo._prepare(frames[0][..., 1])
    assert gray.shape == (3, H, W) and torch.equal(gray[0], gray[2])
    assert vo.image_size == (H, W) and vo.K is not None

    r0 = vo.step(frames[0], 0.0)
    assert r0.tracker == "init" and r0.ok
    big = np.kron(frames[1], np.ones((2, 2, 1), dtype=np.uint8))  # the same view at twice the size
    with caplog.at_level("WARNING", logger="dfvo.api"):
        r1 = vo.step(big, 0.1)
        r2 = vo.step(np.kron(frames[2], np.ones((2, 2, 1), dtype=np.uint8)), 0.2)
    assert "resized" in r1.flags and "resized" in r2.flags
    assert sum("resized to the first" in rec.getMessage() for rec in caplog.records) == 1
    assert r1.tracker in ("E", "PnP") and np.isfinite(r1.covariance).all()
    assert np.linalg.eigvalsh(r1.covariance).min() > 0

    strict = dfvo.Odometry.from_config(SMALL, K=K, size_change="refuse")
    strict.step(frames[0])
    with pytest.raises(ValueError, match=r"^frame 1 is 640x192, the first was 320x96 \(size_change=refuse\)$"):
        strict.step(big)


@needs_checkpoints
@pytest.mark.parametrize("bad", [
    lambda f: np.full(f.shape, np.nan, np.float32),  # a dropped camera buffer
    lambda f: np.where(np.arange(f.shape[0])[:, None, None] < 10, np.inf, f / 255.0).astype(np.float32),
])
def test_frame_with_nan_pixels_is_flagged_and_the_next_frame_tracked(world: SyntheticWorld, bad,
                                                                     caplog: pytest.LogCaptureFixture) -> None:
    """Issue 42: a frame with NaN or infinite pixels is not tracked (it raised a RuntimeError deep in the refinement,
    and so did the next good frame): flagged ``bad_frame``, the previous step repeated, and the frames after it are
    tracked against the last good one as when the bad frame was never given (same poses, indices counting it)."""
    import dfvo

    frames = uint8_frames(world, 5)
    K = world.intrinsics().double().numpy()
    ref = dfvo.Odometry.from_config(SMALL, K=K)
    want = [ref.step(f) for f in (frames[0], frames[1], frames[3], frames[4])]
    vo = dfvo.Odometry.from_config(SMALL, K=K)
    got = [vo.step(frames[0]), vo.step(frames[1])]
    with caplog.at_level("WARNING", logger="dfvo.api"):
        coasted = vo.step(bad(frames[2]), 0.2)
    got += [vo.step(frames[3]), vo.step(frames[4])]
    assert coasted.index == 2 and coasted.timestamp == 0.2 and not coasted.ok
    assert coasted.flags == ("constant_motion", "bad_frame") and "NaN or infinite" in coasted.reasons[0]
    assert "frame 2:" in caplog.text and "the next frame is tracked against the last good one" in caplog.text
    np.testing.assert_allclose(coasted.T_prev_cur, got[1].T_prev_cur, atol=1e-12)
    np.testing.assert_allclose(coasted.T_w_c, got[1].T_w_c @ got[1].T_prev_cur, atol=1e-9)
    assert np.linalg.eigvalsh(coasted.covariance).min() > 0
    assert [r.index for r in got] == [0, 1, 3, 4]
    for g, w in zip(got, want, strict=True):
        assert g.tracker == w.tracker and np.abs(g.T_w_c - w.T_w_c).max() < 1e-9


@needs_checkpoints
def test_bad_input_is_one_line(world: SyntheticWorld) -> None:
    import dfvo

    with pytest.raises(ValueError, match="needs the camera intrinsics"):
        dfvo.Odometry.from_config(SMALL)
    with pytest.raises(ValueError, match="oracle"):
        dfvo.Odometry.from_config([*SMALL, "flow=oracle"], fx=100, fy=100, cx=160, cy=48)
    vo = dfvo.Odometry.from_config(SMALL, fx=100, fy=100, cx=160, cy=48)
    with pytest.raises(ValueError, match=r"expected \(H,W\) or \(H,W,3\)"):
        vo.step(np.zeros((4, 96, 320), np.uint8))
    vo = dfvo.Odometry.from_config(SMALL, fx=100, fy=100, cx=900, cy=48)
    with pytest.raises(ValueError, match="data.cx|cx"):  # principal point outside the first frame
        vo.step(uint8_frames(world, 1)[0])
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    with pytest.raises((HydraException, OmegaConfBaseException)):
        dfvo.Odometry.from_config(["tracker.scale.methd=simple"], fx=100, fy=100, cx=160, cy=48)


def test_import_dfvo_is_light() -> None:
    """``import dfvo`` loads neither torch nor Hydra; ``dfvo.Odometry`` is imported on first use."""
    code = ("import sys, dfvo; assert 'torch' not in sys.modules and 'hydra' not in sys.modules; "
            "print(dfvo.__version__); from dfvo import Odometry; assert 'torch' in sys.modules; "
            "assert dfvo.Odometry is Odometry and 'Odometry' in dir(dfvo)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip()
