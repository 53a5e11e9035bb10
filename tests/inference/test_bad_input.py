"""Issue 16, one test per row: what ``infer.py`` (and ``dfvo.evaluate``) do with bad input and interrupted runs, as a
user sees it: the exit status, the one line on stderr, and the files in ``out_dir`` (docs/bad_input.md is the table).

Every run starts from an empty working folder of the test (``infer_cli``), so a stray ``outputs/`` would show."""

from __future__ import annotations

import csv
import json
import re
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from dfvo.eval.ablation import load_runs, table
from dfvo.synthetic import SyntheticWorld

REPO = Path(__file__).resolve().parents[2]
H, W = 96, 320
SMALL = [f"img_res.height={H}", f"img_res.width={W}", "progress=false", "num_threads=1"]
ORACLE = ["flow=oracle", "depth=oracle"]
POSES = "synthetic_drive_s0.txt"
needs_checkpoints = pytest.mark.skipif(not (REPO / "dfvo/checkpoints/flow.safetensors").is_file(),
                                       reason="no shipped checkpoints in dfvo/checkpoints")


def error_line(proc: subprocess.CompletedProcess) -> str:
    """The single line an expected error leaves on stderr (asserted to be the only one, without a traceback)."""
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in proc.stderr, f"expected one line on stderr, got:\n{proc.stderr}"
    return lines[0]


def assert_logged(log: Path, message: str) -> None:
    """``log`` exists and holds the error's message and its traceback."""
    assert log.is_file(), f"{log} was not written"
    text = log.read_text()
    assert message in text and "Traceback (most recent call last)" in text, text[-2000:]


# ------------------------------------------------------------------------------------------------ multirun out_dir
def test_multirun_jobs_each_write_a_complete_folder(infer_cli, frames_io, tmp_path: Path) -> None:
    """``-m tracker=hybrid,pnp out_dir=X``: each job writes its own subfolder of X, named by its overrides, with
    complete files (one 12-number line per frame, one frames.csv row per frame, its own infer.log, the sweep's
    overrides in summary.json); nothing is written into X itself or the working folder; the ablation table of the
    sweep has one row per tracker."""
    n, sweep = 4, tmp_path / "X"
    infer_cli("-m", "tracker=hybrid,pnp", f"out_dir={sweep}", f"data.num_frames={n}", *SMALL, *ORACLE, timeout=600)
    jobs = sorted(p for p in sweep.iterdir() if p.is_dir())
    assert [p.name.endswith(t) for p, t in zip(jobs, ("tracker=hybrid", "tracker=pnp"))] == [True, True], jobs
    assert not list(sweep.glob("*.txt")) and not (sweep / "frames.csv").exists()
    gt = SyntheticWorld(seed=0, num_frames=n, height=H, width=W).poses().double().numpy()
    gt = np.linalg.inv(gt[0]) @ gt  # the run's trajectory starts at the identity
    for job, tracker in zip(jobs, ("hybrid", "pnp")):
        pred = frames_io.read_kitti(job / POSES)
        assert pred.shape == (n, 4, 4)
        np.testing.assert_allclose(pred[:, :3, 3], gt[:, :3, 3], atol=0.01)  # oracle sources: the true path
        rows = list(csv.DictReader((job / "frames.csv").open()))
        assert [int(r["frame"]) for r in rows] == list(range(n))
        summary = json.loads((job / "summary.json").read_text())
        assert summary["choices"]["tracker"] == tracker and summary["frames_written"] == n
        assert (job / "infer.log").is_file() and (job / "trajectory.png").is_file()
        recorded = summary["overrides"]  # the sweep's non-group overrides, as Hydra saw them
        assert recorded["data.num_frames"] == str(n) and recorded["img_res.height"] == str(H)
        assert not {"progress", "num_threads", "out_dir", "tracker", "flow", "depth"} & set(recorded)
    assert not (infer_cli.cwd / "outputs").exists()
    lines = [line for line in table(load_runs([sweep])).splitlines() if line.startswith("| ")]
    assert lines[0] == "| tracker | synthetic_drive_s0 |"
    assert {line.split("|")[1].strip() for line in lines[1:]} == {"hybrid", "pnp"}


# ------------------------------------------------------------------------------------------------ intrinsics
@pytest.fixture
def euroc_like_folder(tmp_path: Path) -> Path:
    """Three 752x480 frames (EuRoC's size) of a textured pattern."""
    from PIL import Image

    folder = tmp_path / "frames"
    folder.mkdir()
    y, x = np.mgrid[0:480, 0:752]
    for k in range(3):
        img = 127.5 + 100 * np.sin((x + 7 * k) / 9.0) * np.cos(y / 13.0)
        Image.fromarray(img.round().astype(np.uint8)).save(folder / f"{k:06d}.png")
    return folder


@pytest.mark.parametrize("overrides, message", [
    (["data.cx=3670"], r"data\.cx=3670 in frames of .* is outside the 752-px-wide image \(expected 0 < cx < 752"),
    (["data.fx=4.5", "data.fy=4.5"],
     r"data\.fx=4\.5 in frames of .* gives a 178\.6-degree horizontal field of view .* not millimetres"),
], ids=["principal point", "focal length in mm"])
def test_implausible_intrinsics_are_one_clear_error(infer_cli, euroc_like_folder: Path, tmp_path: Path,
                                                    overrides: list[str], message: str) -> None:
    """``data=folder data.cx=3670`` on a 752-px-wide image (and focal lengths in millimetres) stop before any frame
    is tracked, with one line naming the setting, its value and what was expected, and the log in OUT. (Every
    check of :mod:`dfvo.data.intrinsics_check` has its unit test in tests/data/test_intrinsics_check.py.)"""
    intrinsics = {"data.fx": "458.654", "data.fy": "457.296", "data.cx": "367.215", "data.cy": "248.375"}
    intrinsics.update(o.split("=") for o in overrides)
    out = tmp_path / "out"
    proc = infer_cli("data=folder", f"data.root={euroc_like_folder}", *(f"{k}={v}" for k, v in intrinsics.items()),
                     f"out_dir={out}", *SMALL, check=False)
    assert proc.returncode == 1
    line = error_line(proc)
    assert line.startswith("dfvo-infer: error: ") and line.endswith(f"[log: {out / 'infer.log'}]")
    assert re.search(message, line), line
    assert_logged(out / "infer.log", line.removeprefix("dfvo-infer: error: ").split(" [log:")[0])
    assert not (out / "frames.csv").exists() and not (infer_cli.cwd / "outputs").exists()


# ------------------------------------------------------------------------------------------------ calib.txt
def kitti_copy(kitti_odom_root: Path, dest: Path, calib: str) -> Path:
    """ROOT/sequences/06 of the shared snippet with its frames linked and ``calib`` as calib.txt."""
    seq = dest / "sequences" / "06"
    seq.mkdir(parents=True)
    (seq / "image_0").symlink_to(kitti_odom_root / "sequences" / "06" / "image_0", target_is_directory=True)
    (seq / "calib.txt").write_text(calib)
    return dest


def test_calib_line_that_is_not_numbers_is_named(infer_cli, kitti_odom_root: Path, tmp_path: Path) -> None:
    """``P0: abc ...`` in calib.txt: the error names the file, the line number, and that it is not 12 numbers."""
    good = (kitti_odom_root / "sequences" / "06" / "calib.txt").read_text().splitlines()
    p0 = next(i for i, line in enumerate(good) if line.startswith("P0:"))
    bad = list(good)
    bad[p0] = "P0: abc " + " ".join(good[p0].split()[2:])
    root = kitti_copy(kitti_odom_root, tmp_path / "kitti", "\n".join(bad) + "\n")
    proc = infer_cli("data=kitti_odom", f"data.root={root}", "seq=06", f"out_dir={tmp_path / 'out'}", *SMALL,
                     check=False)
    assert proc.returncode == 1
    line = error_line(proc)
    calib = root / "sequences" / "06" / "calib.txt"
    assert f"calibration file {calib} line {p0 + 1}: 'P0:' is not 12 numbers (3x4 matrix): 'abc" in line, line


# ------------------------------------------------------------------------------------------------ one line + log
@pytest.fixture
def garbage_checkpoint(tmp_path: Path) -> Path:
    path = tmp_path / "flow.safetensors"
    path.write_bytes(b"this is not a checkpoint" * 10)
    return path


EXPECTED_ERRORS = {
    "missing data": (["data=kitti_odom", "data.root=/nonexistent/kitti", "seq=06"],
                     "KITTI odometry sequence 06: folder /nonexistent/kitti/sequences/06 does not exist"),
    "bad checkpoint": (["flow=network", "flow.checkpoint={ckpt}", "data.num_frames=3"], "flow.checkpoint={ckpt}"),
    "unknown key": (["tracker.scale.methd=simple"], "Could not override 'tracker.scale.methd'; Key 'methd' not in"),
    "wrong type": (["batch_size=four"], "Error merging override batch_size=four; Value 'four' of type 'str' could "
                                        "not be converted to Integer"),
    "unknown option": (["tracker=bogus"], "Could not find 'tracker/bogus'; available options in 'tracker': e, hybrid"),
}


@pytest.mark.parametrize("case", list(EXPECTED_ERRORS))
def test_expected_errors_end_with_one_line_and_the_traceback_in_the_log(infer_cli, garbage_checkpoint: Path,
                                                                         tmp_path: Path, case: str) -> None:
    """Missing data, a bad checkpoint, a bad config: exit status 1, one line on stderr naming the log file, the
    traceback in ``OUT/infer.log`` (so a failed run says in OUT what failed), no stray ``outputs/`` folder."""
    args, expected = EXPECTED_ERRORS[case]
    args = [a.format(ckpt=garbage_checkpoint) for a in args]
    expected = expected.format(ckpt=garbage_checkpoint)
    out = tmp_path / "out"
    proc = infer_cli(*args, f"out_dir={out}", *SMALL, check=False)
    assert proc.returncode == 1, proc.stderr
    line = error_line(proc)
    assert line.startswith("dfvo-infer: error: ") and expected in line, line
    assert line.endswith(f" [log: {out / 'infer.log'}]"), line
    assert_logged(out / "infer.log", expected)
    assert not (infer_cli.cwd / "outputs").exists()


@pytest.mark.parametrize("case", ["missing data", "unknown key"])
def test_verbose_shows_the_traceback(infer_cli, tmp_path: Path, case: str) -> None:
    args, expected = EXPECTED_ERRORS[case]
    proc = infer_cli(*args, f"out_dir={tmp_path / 'out'}", "verbose=true", *SMALL, check=False)
    assert proc.returncode == 1
    assert "Traceback (most recent call last)" in proc.stderr and expected.split(";")[0] in proc.stderr


# ------------------------------------------------------------------------------------------------ Ctrl-C, SIGTERM
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_interrupted_run_writes_partial_results(infer_cli, frames_io, tmp_path: Path, sig: signal.Signals) -> None:
    """Ctrl-C (SIGINT) or SIGTERM after a few poses: one line, exit 128 + signal (130, 143), and OUT holds the poses
    so far, ``summary.json`` marked partial, ``metrics.json`` of those poses, the trajectory and frames plots."""
    n, out = 60, tmp_path / "out"
    proc = infer_cli.popen(f"out_dir={out}", f"data.num_frames={n}", "batch_size=1", *SMALL, *ORACLE)
    pose_file = out / POSES
    deadline = time.time() + 240
    try:
        while time.time() < deadline and proc.poll() is None:
            if pose_file.exists() and len(pose_file.read_text().splitlines()) >= 4:
                break
            time.sleep(0.05)
        assert proc.poll() is None, f"the run ended before it could be interrupted:\n{proc.stderr.read()}"
        proc.send_signal(sig)
        _, stderr = proc.communicate(timeout=240)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 128 + sig, (proc.returncode, stderr)
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert lines == [f"dfvo-infer: interrupted by {sig.name}; the poses so far, their metrics and plots are written "
                     f"[log: {out / 'infer.log'}]"], stderr
    pred = frames_io.read_kitti(pose_file)
    assert 4 <= len(pred) < n
    summary = json.loads((out / "summary.json").read_text())
    assert summary["partial"] is True and summary["stopped_by"] == sig.name
    assert summary["frames"] == n and summary["frames_written"] == len(pred)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["num_frames"] == len(pred) and metrics["partial"] == f"first {len(pred)} of {n} frames ({sig.name})"
    gt = SyntheticWorld(seed=0, num_frames=len(pred), height=H, width=W).poses().double().numpy()
    gt = np.linalg.inv(gt[0]) @ gt  # the run's trajectory starts at the identity
    assert metrics["ate_m"] < 0.01 and np.abs(pred[:, :3, 3] - gt[:, :3, 3]).max() < 0.01  # the oracle's true path
    assert len(list(csv.DictReader((out / "frames.csv").open()))) >= len(pred)
    for png in ("trajectory.png", "frames.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "interrupted by " + sig.name in (out / "infer.log").read_text()


# ------------------------------------------------------------------------------------------------ segment plot
def test_segment_plot_of_a_short_sequence_is_not_an_empty_plot(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """``dfvo.evaluate ... plot_dir=P`` on a path shorter than 100 m writes no (empty) segment-error plot, removes a
    stale one, and says why in its table; a path of 100 m or more gets the plot (the command's work, in this process:
    :func:`dfvo.cli.evaluate.run` on the composed command line)."""
    from hydra import compose, initialize_config_module

    from dfvo.cli.evaluate import run
    from dfvo.io.trajectory import write_kitti_poses

    for n in (40, 160):  # 1 m per frame: 39 m and 159 m
        T = np.tile(np.eye(4), (n, 1, 1))
        T[:, 2, 3] = np.arange(n, dtype=float)
        P = T.copy()
        P[:, 0, 3] += 0.05 * np.sin(np.arange(n))
        write_kitti_poses(tmp_path / f"gt{n}" / "06.txt", T)
        write_kitti_poses(tmp_path / f"pred{n}" / "06.txt", P)
    plots = tmp_path / "plots"
    plots.mkdir()
    (plots / "06_segment_errors.png").write_text("stale")
    with initialize_config_module(config_module="dfvo.conf.evaluate", version_base="1.3"):
        for n in (40, 160):
            run(compose(config_name="evaluate", overrides=["align=6dof", f"plot_dir={plots}",
                                                          f"gt_dir={tmp_path / f'gt{n}'}",
                                                          f"pred_dir={tmp_path / f'pred{n}'}"]))
            if n == 40:
                assert not (plots / "06_segment_errors.png").exists()
                assert (plots / "06_trajectory.png").is_file() and "no 100 m segment" in capsys.readouterr().out
    assert (plots / "06_segment_errors.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# ------------------------------------------------------------------------------------------------ own video, no GT
@needs_checkpoints
def test_own_video_without_ground_truth_plot(infer_cli, tmp_path: Path) -> None:
    """``data=video`` without ground truth (the shipped networks): the run writes its log into OUT (and nothing into
    the working folder); ``trajectory.png`` shows the path with a start marker, equal axes and a scale bar."""
    av = pytest.importorskip("av", reason='PyAV not installed (pip install "dfvo[video]")')
    import matplotlib.pyplot as plt

    from dfvo.eval.plots import trajectory_figure

    n = 6
    world = SyntheticWorld(seed=3, num_frames=n, height=H, width=W, scenario="straight")
    video = tmp_path / "drive.mkv"
    with av.open(str(video), "w") as container:
        stream = container.add_stream("ffv1", rate=10)
        stream.width, stream.height, stream.pix_fmt = W, H, "bgr0"
        for i in range(n):
            rgb = (world.image(i).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
            for packet in stream.encode(av.VideoFrame.from_ndarray(rgb, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    K = world.intrinsics()
    out = tmp_path / "out"
    infer_cli("data=video", f"data.path={video}", f"data.fx={float(K[0, 0])}", f"data.fy={float(K[1, 1])}",
              f"data.cx={float(K[0, 2])}", f"data.cy={float(K[1, 2])}", f"out_dir={out}", *SMALL)
    assert (out / "infer.log").is_file() and not (infer_cli.cwd / "outputs").exists()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["metrics"] is None and summary["frames_written"] == n
    png = np.asarray(plt.imread(out / "trajectory.png"))[..., :3]
    green = np.all(np.abs(png - np.array([44, 160, 44]) / 255) < 0.03, axis=-1)  # tab:green, the start marker
    assert green.sum() > 20
    pred = np.loadtxt(out / "drive.txt").reshape(-1, 3, 4)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3] = pred
    fig = trajectory_figure(None, poses)  # the figure the run drew (no ground truth): rebuilt to read its parts
    ax = fig.axes[0]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert "start" in labels and "end (prediction)" in labels
    assert ax.get_aspect() == 1.0
    bars = [a for a in ax.artists if a.get_gid() == "scale_bar"]
    assert len(bars) == 1
    caption = next(t.get_text() for t in fig.texts if t.get_gid() == "caption")
    assert "no ground truth" in caption and "scale bar" in caption
    plt.close(fig)


# ------------------------------------------------------------------------------------------------ other bad input
def _frames(folder: Path, sizes: list[tuple[int, int]], truncate_last: bool = False) -> Path:
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    for k, (h, w) in enumerate(sizes):
        Image.fromarray(rng.integers(0, 256, (h, w), dtype=np.uint8)).save(folder / f"{k:06d}.png")
    if truncate_last:
        last = folder / f"{len(sizes) - 1:06d}.png"
        last.write_bytes(last.read_bytes()[: last.stat().st_size // 2])
    return folder


INTRINSICS = ["data.fx=200", "data.fy=200", "data.cx=160", "data.cy=48"]
OTHER_BAD_INPUT = {
    "empty folder": (lambda d: ["data=folder", f"data.root={_frames(d, [])}", *INTRINSICS],
                     r"image folder: folder .*frames contains no images \(expected files ending in \.png"),
    "frames of two sizes": (lambda d: ["data=folder", f"data.root={_frames(d, [(96, 320), (100, 320)])}",
                                       *INTRINSICS], r"image .*000001\.png is 100x320, expected 96x320"),
    "truncated frame": (lambda d: ["data=folder", f"data.root={_frames(d, [(96, 320)] * 3, True)}", *INTRINSICS],
                        r"cannot read image .*000002\.png: expected a complete PNG or JPEG file"),
    "not a video": (lambda d: ["data=video", f"data.path={d.parent / 'clip.mp4'}", *INTRINSICS],
                    r"cannot open video .*clip\.mp4: expected a video file"),
    "no intrinsics": (lambda d: ["data=folder", f"data.root={_frames(d, [(96, 320)] * 2)}"],
                      r"data=folder needs data\.fx= \(intrinsics in pixels of the stored frames\)"),
    "KITTI number without root": (lambda d: ["seq=10"], r"KITTI odometry sequence 10 needs the dataset folder: set "
                                                        r"the environment variable DFVO_KITTI_ODOM_ROOT=ROOT once or "
                                                        r"pass data\.root=ROOT"),
}


@pytest.mark.parametrize("case", list(OTHER_BAD_INPUT))
def test_other_bad_input_is_one_line(infer_cli, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, case: str) -> None:
    """More of what a new user gets wrong: each ends with exit status 1 and one line naming the file or setting."""
    monkeypatch.delenv("DFVO_KITTI_ODOM_ROOT", raising=False)
    (tmp_path / "clip.mp4").write_text("not a video")
    make_args, pattern = OTHER_BAD_INPUT[case]
    out = tmp_path / "out"
    proc = infer_cli(*make_args(tmp_path / "frames"), f"out_dir={out}", *SMALL, check=False)
    assert proc.returncode == 1, proc.stderr
    line = error_line(proc)
    assert re.search(pattern, line) and line.endswith(f"[log: {out / 'infer.log'}]"), line
    assert "Traceback (most recent call last)" in (out / "infer.log").read_text()
