"""Issue 28, bad input and faults round 2: one test (or one parametrised case) per row of the issue's table, run as a
user runs the commands (the exit status, the one line on stderr, the files in ``out_dir``); docs/bad_input.md is the
table. Training rows (SIGTERM during training, ``trainer=smoke`` noise) are tested with the training code.

Every ``infer.py`` run starts from an empty working folder of the test (``infer_cli``), so a stray ``outputs/``
would show. Modified KITTI data is a copy in ``tmp_path`` with the shared frames linked, never ../shared itself."""

from __future__ import annotations

import csv
import json
import os
import re
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

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


def kitti_copy(kitti_odom_root: Path, dest: Path, calib: str | None = None, half_frames: int = 0) -> Path:
    """ROOT/sequences/06 of the shared snippet: frames linked (or the first ``half_frames`` written at half size),
    ``calib`` (default: the original) as calib.txt."""
    src = kitti_odom_root / "sequences" / "06"
    seq = dest / "sequences" / "06"
    seq.mkdir(parents=True)
    if half_frames:
        from PIL import Image

        (seq / "image_0").mkdir()
        for path in sorted((src / "image_0").iterdir())[:half_frames]:
            with Image.open(path) as im:
                im.resize((im.width // 2, im.height // 2), Image.BILINEAR).save(seq / "image_0" / path.name)
    else:
        (seq / "image_0").symlink_to(src / "image_0", target_is_directory=True)
    (seq / "calib.txt").write_text(calib if calib is not None else (src / "calib.txt").read_text())
    return dest


def calib_with_p0(kitti_odom_root: Path, **entries: str) -> tuple[str, int]:
    """The shared calib.txt with entries of its ``P0:`` line replaced (``fx``: index 0, ``fy``: index 5), and the
    line number of ``P0:``."""
    lines = (kitti_odom_root / "sequences" / "06" / "calib.txt").read_text().splitlines()
    k = next(i for i, line in enumerate(lines) if line.startswith("P0:"))
    values = lines[k].split()[1:]
    for name, value in entries.items():
        values[{"fx": 0, "fy": 5}[name]] = value
    lines[k] = "P0: " + " ".join(values)
    return "\n".join(lines) + "\n", k + 1


# ------------------------------------------------------------------------------------------------ KITTI calib.txt
@pytest.mark.parametrize("entries, message", [
    ({"fx": "nan"}, r"fx=nan in calibration file .*calib\.txt line {line} \('P0:'\) is not finite"),
    ({"fx": "0", "fy": "0"}, r"fx=0 in calibration file .*calib\.txt line {line} \('P0:'\) must be positive"),
    ({"fx": "7.070912000000e+03", "fy": "7.070912000000e+03"},
     r"fx=7070\.91 in calibration file .*calib\.txt line {line} \('P0:'\) gives a 9\.9-degree horizontal field of "
     r"view on the 1226-px-wide image; expected 10\.\.170 degrees"),
], ids=["fx nan", "fx fy zero", "focal length x10"])
def test_kitti_calib_with_implausible_intrinsics_is_one_line(infer_cli, kitti_odom_root: Path, tmp_path: Path,
                                                             entries: dict[str, str], message: str) -> None:
    """KITTI calib.txt with fx = nan, fx = fy = 0, or the focal length x10 (a 10-degree lens; ``data=folder`` refuses
    the same): the checks of :mod:`dfvo.data.intrinsics_check` name calib.txt, its line and the value; nothing is
    tracked."""
    calib, line = calib_with_p0(kitti_odom_root, **entries)
    root = kitti_copy(kitti_odom_root, tmp_path / "kitti", calib)
    out = tmp_path / "out"
    proc = infer_cli("data=kitti_odom", f"data.root={root}", "seq=06", f"out_dir={out}", *SMALL, check=False)
    assert proc.returncode == 1
    text = error_line(proc)
    assert re.search(message.format(line=line), text), text
    assert str(root / "sequences" / "06" / "calib.txt") in text
    assert not (out / "06.txt").exists() and not (out / "frames.csv").exists()


def test_frames_downscaled_with_full_resolution_intrinsics_warn(kitti_odom_root: Path, tmp_path: Path,
                                                                caplog: pytest.LogCaptureFixture) -> None:
    """Frames downscaled by 2 beside the full-resolution calib.txt: the principal point (601.9, 183.1) sits at the
    right and bottom edges of the 613x185 frames: a warning names its offset from the image centre (+296 px, +91 px);
    the original frames give none. (Every reader goes through :func:`dfvo.data.intrinsics_check.check_intrinsics`;
    the folder, EuRoC, TUM and video readers: ``tests/data/test_intrinsics_check.py``.)"""
    from dfvo.data.kitti_odometry import KittiOdometry

    with caplog.at_level("WARNING", logger="dfvo.data"):
        KittiOdometry(kitti_copy(kitti_odom_root, tmp_path / "full"), "06", stereo=False)
    assert not [r for r in caplog.records if "principal point" in r.getMessage()]
    with caplog.at_level("WARNING", logger="dfvo.data"):
        ds = KittiOdometry(kitti_copy(kitti_odom_root, tmp_path / "half", half_frames=3), "06", stereo=False)
    assert ds.native_size == (185, 613)
    warned = [r.getMessage() for r in caplog.records if "principal point" in r.getMessage()]
    assert len(warned) == 1, warned
    dx, dy = 601.8873 - 306.0, 183.1104 - 92.0
    assert f"is {dx:+.0f} px, {dy:+.0f} px from the centre of the 613x185 image" in warned[0], warned[0]
    assert "calib.txt line 1 ('P0:')" in warned[0] and "another resolution" in warned[0]


# ------------------------------------------------------------------------------------------------ out_dir
def _wait_for_poses(proc: subprocess.Popen, pose_file: Path, count: int, timeout: float = 240) -> None:
    deadline = time.time() + timeout
    while time.time() < deadline and proc.poll() is None:
        if pose_file.exists() and len(pose_file.read_text().splitlines()) >= count:
            return
        time.sleep(0.05)
    raise AssertionError(f"no {count} poses in {pose_file} (exit {proc.poll()})")


def test_second_run_into_a_busy_out_dir_refuses(infer_cli, frames_io, tmp_path: Path) -> None:
    """Two runs into one out_dir at once: the second refuses with one line naming the folder and the first run's
    pid and writes nothing there (not even Hydra's files); the first run's files are complete and its own."""
    n, out = 40, tmp_path / "out"
    first = infer_cli.popen(f"out_dir={out}", f"data.num_frames={n}", "batch_size=1", *SMALL, *ORACLE)
    try:
        _wait_for_poses(first, out / POSES, 3)
        hydra_config = (out / ".hydra" / "config.yaml").read_text()
        second = infer_cli(f"out_dir={out}", "data.num_frames=5", "tracker=pnp", *SMALL, *ORACLE, check=False)
        assert first.poll() is None, "the first run ended before the second one started: nothing was tested"
        _, stderr = first.communicate(timeout=300)
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    assert second.returncode == 1
    line = error_line(second)
    assert line == (f"dfvo-infer: error: out_dir={out} is in use by another dfvo run (pid {first.pid} on "
                    f"{os.uname().nodename}, since " + line.split(", since ")[1]), line
    assert line.endswith("wait for it to finish or pass another out_dir="), line
    assert first.returncode == 0, stderr
    assert frames_io.read_kitti(out / POSES).shape == (n, 4, 4)  # 12 numbers on every line
    assert [int(r["frame"]) for r in csv.DictReader((out / "frames.csv").open())] == list(range(n))
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames_written"] == n and summary["choices"]["tracker"] == "hybrid"
    assert (out / ".hydra" / "config.yaml").read_text() == hydra_config  # the refused run wrote nothing here
    assert not (out / ".dfvo.lock").exists()  # released at the end


def test_lock_of_a_dead_run_does_not_block(tmp_path: Path) -> None:
    """The lock is ``flock``: a process killed with SIGKILL while holding it leaves its lock file behind, and the
    next run takes the folder at once; a live holder refuses the folder with its pid."""
    from dfvo.inference.outputs import OutDirBusy, lock_out_dir

    out = tmp_path / "out"
    hold = ("import sys, time; from dfvo.inference.outputs import lock_out_dir; lock_out_dir(sys.argv[1]); "
            "print('locked', flush=True); time.sleep(60)")
    holder = subprocess.Popen([sys.executable, "-c", hold, str(out)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(OutDirBusy, match=rf"out_dir={re.escape(str(out))} is in use by another dfvo run "
                                             rf"\(pid {holder.pid} on "):
            lock_out_dir(out)
        holder.send_signal(signal.SIGKILL)
        holder.wait(timeout=30)
    finally:
        if holder.poll() is None:
            holder.kill()
            holder.wait()
    assert (out / ".dfvo.lock").exists()  # the killed run's file stays ...
    lock = lock_out_dir(out)  # ... and does not block
    assert json.loads((out / ".dfvo.lock").read_text())["pid"] == os.getpid()
    lock.release()
    assert not (out / ".dfvo.lock").exists()


def test_rerun_into_an_out_dir_replaces_the_earlier_outputs(infer_cli, frames_io, tmp_path: Path) -> None:
    """A rerun into an existing out_dir: the same command twice gives the second run's complete files, and a run
    of another sequence leaves no pose file of the earlier one beside its own (removed first, logged)."""
    n, out = 5, tmp_path / "out"
    for _ in range(2):
        infer_cli(f"out_dir={out}", f"data.num_frames={n}", *SMALL, *ORACLE)
        assert frames_io.read_kitti(out / POSES).shape == (n, 4, 4)
        assert [int(r["frame"]) for r in csv.DictReader((out / "frames.csv").open())] == list(range(n))
    assert json.loads((out / "metrics.json").read_text())["num_frames"] == n
    infer_cli(f"out_dir={out}", "data.seq=straight", "data.num_frames=3", *SMALL, *ORACLE)
    names = sorted(p.name for p in out.iterdir())
    assert names == [".hydra", "frames.csv", "frames.png", "infer.log", "metrics.json", "summary.json",
                     "synthetic_straight_s0.txt", "trajectory.png"], names
    assert json.loads((out / "metrics.json").read_text())["sequence"] == "synthetic_straight_s0"
    assert json.loads((out / "summary.json").read_text())["frames_written"] == 3
    log = (out / "infer.log").read_text()
    assert log.count(f"out_dir {out} held an earlier run's outputs; removed summary.json, metrics.json, frames.csv, "
                     f"trajectory.png, frames.png, {POSES}") == 2, log[-3000:]


def test_clear_previous_outputs_removes_the_runs_files_only(tmp_path: Path) -> None:
    """What a rerun removes: the run's own outputs and the pose file the earlier summary.json names (here a stale
    metrics.json of a run with ground truth); Hydra's infer.log, other files and pose files outside OUT stay."""
    from dfvo.inference.outputs import clear_previous_outputs

    out = tmp_path / "out"
    (out / "tensorboard").mkdir(parents=True)
    (out / "tensorboard" / "events").write_text("x")
    for name in ("metrics.json", "frames.csv", "trajectory.png", "frames.png", "06.txt", "07.txt", "infer.log",
                 "notes.md"):
        (out / name).write_text("earlier run")
    (tmp_path / "elsewhere.txt").write_text("not this run's folder")
    (out / "summary.json").write_text(json.dumps({"pose_file": str(out / "06.txt")}))
    removed = clear_previous_outputs(out)
    assert removed == ["summary.json", "metrics.json", "frames.csv", "trajectory.png", "frames.png", "tensorboard",
                       "06.txt"]
    assert sorted(p.name for p in out.iterdir()) == ["07.txt", "infer.log", "notes.md"]
    (out / "summary.json").write_text(json.dumps({"pose_file": str(tmp_path / "elsewhere.txt")}))
    assert clear_previous_outputs(out) == ["summary.json"] and (tmp_path / "elsewhere.txt").is_file()
    assert clear_previous_outputs(out) == []


@pytest.mark.slow
@needs_checkpoints
def test_rerun_without_ground_truth_leaves_no_stale_metrics(infer_cli, frames_io, tmp_path: Path) -> None:
    """The issue's case end to end: a run with ground truth, then a run without it (own frames, the shipped
    networks) into the same out_dir: no metrics.json of the first run stays beside the new trajectory."""
    out = tmp_path / "out"
    infer_cli(f"out_dir={out}", "data.num_frames=3", *SMALL, *ORACLE)
    assert (out / "metrics.json").is_file()
    world = SyntheticWorld(seed=3, num_frames=3, height=H, width=W, scenario="straight")
    frames = frames_io.write_frames(tmp_path / "own", [world.image(i) for i in range(3)])
    infer_cli("data=folder", f"data.root={frames}", *frames_io.intrinsics_overrides(world.intrinsics()),
              f"out_dir={out}", *SMALL)
    names = sorted(p.name for p in out.iterdir())
    assert names == [".hydra", "frames.csv", "frames.png", "infer.log", "own.txt", "summary.json",
                     "trajectory.png"], names
    summary = json.loads((out / "summary.json").read_text())
    assert summary["sequence"] == "own" and summary["metrics"] is None and summary["frames_written"] == 3


FULL_DISK = textwrap.dedent('''
    """infer.py on a simulated disk that fills up: files under OUT get BUDGET bytes in all, then every write (and the
    flush of a buffered write) fails with ENOSPC, as on a real full disk; Hydra's .hydra/ files are not counted."""
    import builtins, errno, io, sys
    from pathlib import Path

    out, budget = Path(sys.argv[1]).resolve(), int(sys.argv[2])
    used = [0]
    real_open = io.open

    class FullDisk:
        def __init__(self, f):
            self._f = f
        def write(self, data):
            used[0] += len(data)
            if used[0] > budget:
                raise OSError(errno.ENOSPC, "No space left on device")
            return self._f.write(data)
        def __getattr__(self, name):
            return getattr(self._f, name)
        def __enter__(self):
            return self
        def __exit__(self, *exc):
            self._f.close()
        def __iter__(self):
            return iter(self._f)

    def guarded_open(file, mode="r", *args, **kwargs):
        f = real_open(file, mode, *args, **kwargs)
        path = Path(file).resolve() if isinstance(file, (str, Path)) else None
        if path is not None and out in path.parents and ".hydra" not in path.parts and set(mode) & set("wa+"):
            return FullDisk(f)
        return f

    io.open = builtins.open = guarded_open
    sys.argv = ["infer.py", f"out_dir={out}", *sys.argv[3:]]
    from dfvo.cli.infer import main
    main()
''')


@pytest.mark.parametrize("budget", [0, 2500], ids=["full at start", "fills mid-run"])
def test_out_dir_on_a_full_disk_is_one_line(tmp_path: Path, budget: int) -> None:
    """out_dir on a disk that is full (or fills during the run): one line naming the file that could not be written
    and that the log could not be written either, exit status 1; no ``--- Logging error ---`` wall."""
    script = tmp_path / "full_disk.py"
    script.write_text(FULL_DISK)
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, str(script), str(out), str(budget), "data.num_frames=30", *SMALL,
                           *ORACLE], cwd=tmp_path, capture_output=True, text=True, timeout=300,
                          env=dict(os.environ, OMP_NUM_THREADS="1"))
    assert proc.returncode == 1, proc.stderr[-3000:]
    line = error_line(proc)
    assert "Logging error" not in proc.stderr + proc.stdout
    m = re.fullmatch(r"dfvo-infer: error: cannot write (\S+): No space left on device; free space on its disk or pass "
                     r"another out_dir=.*\[log: (\S+) could not be written: No space left on device\]", line)
    assert m, line
    assert Path(m.group(1)).parent == out.resolve() and Path(m.group(2)) == out.resolve() / "infer.log"


# ------------------------------------------------------------------------------------------------ settings
def test_img_res_scale_alone_wins_over_the_default_width() -> None:
    """``img_res.scale=0.5`` as README and docs/running.md write it: the group's default width gives way (KITTI's
    1241x376 -> 608x192, not 640x192); a width given on the command line with a scale is still a contradiction."""
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    from dfvo.inference.config import typed
    from dfvo.inference.frames import working_hw

    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="dfvo.conf.infer", version_base="1.3"):
        scaled = typed(compose(config_name="infer", overrides=["img_res.scale=0.5"]).img_res)
        default = typed(compose(config_name="infer").img_res)
        both = typed(compose(config_name="infer", overrides=["img_res.scale=0.5", "img_res.width=320"]).img_res)
    GlobalHydra.instance().clear()
    assert (scaled.height, scaled.width, scaled.scale) == (None, None, 0.5)
    assert working_hw(scaled, (376, 1241)) == (192, 608)  # 188 -> 192, 620.5 -> 608 (multiples of 32)
    assert working_hw(default, (376, 1241)) == (192, 640)
    with pytest.raises(ValueError, match=r"give scale=0\.5 alone \(height=None, width=320 must be null\)"):
        working_hw(both, (376, 1241))


def test_img_res_scale_runs(infer_cli, tmp_path: Path) -> None:
    """The command of the docs runs: ``img_res.scale=0.25`` renders the synthetic drive at 96x320."""
    out = tmp_path / "out"
    infer_cli("img_res.scale=0.25", "data.num_frames=3", "progress=false", "num_threads=1", *ORACLE,
              f"out_dir={out}")
    assert json.loads((out / "summary.json").read_text())["frames_written"] == 3


@pytest.mark.parametrize("args, hint", [
    (["data=folder", "data.root=/data/my", "frames"],
     "cannot parse the command line: 'frames' is not key=value: a value with spaces split by the shell? Quote the "
     "override for the shell and the value for Hydra: \"data.root='/data/my frames'\""),
    (["data=folder", "data.root=/data/fahrt_müller"],
     "cannot parse the command line: data.root=/data/fahrt_müller: a value with spaces or non-ASCII letters must be "
     "quoted for Hydra, inside the shell's quotes: \"data.root='/data/fahrt_müller'\""),
], ids=["spaces", "non-ASCII"])
def test_unquoted_path_says_how_to_quote(infer_cli, tmp_path: Path, args: list[str], hint: str) -> None:
    """A path with spaces (split by the shell) or non-ASCII letters, unquoted: one line saying how to quote it."""
    proc = infer_cli(*args, *SMALL, check=False)
    assert proc.returncode == 1
    assert error_line(proc) == f"dfvo-infer: error: {hint}"


def test_quoted_path_with_spaces_and_umlauts_reaches_the_reader(infer_cli, tmp_path: Path) -> None:
    """The quoting the hint gives works: the folder (with spaces and an umlaut) is named by the data reader."""
    folder = tmp_path / "my frames ü"
    folder.mkdir()
    proc = infer_cli("data=folder", f"data.root='{folder}'", "data.fx=200", "data.fy=200", "data.cx=160",
                     "data.cy=48", f"out_dir={tmp_path / 'out'}", *SMALL, check=False)
    assert f"folder {folder} contains no images" in error_line(proc)


@pytest.mark.parametrize("step", ["0", pytest.param("-1", marks=pytest.mark.slow)])  # one check: 0 is the fast cover
def test_data_step_must_be_positive(infer_cli, tmp_path: Path, step: str) -> None:
    """``data.step=0`` / ``-1``: one line naming data.step and what is expected (not Python's "slice step cannot
    be zero", not the footage run backwards)."""
    out = tmp_path / "out"
    proc = infer_cli(f"data.step={step}", f"out_dir={out}", *SMALL, *ORACLE, check=False)
    assert proc.returncode == 1
    assert error_line(proc) == (f"dfvo-infer: error: data.step={step}; expected a positive integer (every step-th "
                                f"frame, 1: every frame; the footage is always read forwards) "
                                f"[log: {out / 'infer.log'}]")
    assert not (out / POSES).exists()


def test_checkpoint_that_is_a_folder(infer_cli, tmp_path: Path) -> None:
    """``flow.checkpoint=<a folder>``: "is a folder; expected a .safetensors file" (naming a weights file inside)."""
    folder = tmp_path / "weights"
    folder.mkdir()
    (folder / "flow.safetensors").write_bytes(b"")
    proc = infer_cli("flow=network", f"flow.checkpoint={folder}", f"out_dir={tmp_path / 'out'}", *SMALL,
                     check=False)
    assert proc.returncode == 1
    assert (f"dfvo-infer: error: flow.checkpoint={folder} is a folder; expected a .safetensors file (or a .pt/.ckpt "
            "weights file) (it holds flow.safetensors: pass one of them)") in error_line(proc)


@needs_checkpoints
def test_flow_weights_with_corrupted_data_bytes(infer_cli, tmp_path: Path) -> None:
    """The shipped flow weights with 64 KiB of their data bytes overwritten (the header intact, so the file still
    reads): refused at load time with one line naming the checkpoint, before any frame is tracked."""
    ckpt = tmp_path / "flow.safetensors"
    data = bytearray((REPO / "dfvo/checkpoints/flow.safetensors").read_bytes())
    header = 8 + int.from_bytes(data[:8], "little")
    start = header + (len(data) - header) // 2
    data[start: start + 65536] = np.random.default_rng(0).integers(0, 256, 65536, dtype=np.uint8).tobytes()
    ckpt.write_bytes(bytes(data))
    out = tmp_path / "out"
    proc = infer_cli("flow=network", f"flow.checkpoint={ckpt}", f"out_dir={out}", "data.num_frames=3", *SMALL,
                     check=False)
    assert proc.returncode == 1
    line = error_line(proc)
    assert re.match(rf"dfvo-infer: error: flow\.checkpoint={re.escape(str(ckpt))}: NaN or inf values in \d+ of "
                    r"\d+ tensors \(e\.g\. \S+: \d+ of \d+ values\); the file is corrupted", line), line
    assert not (out / POSES).exists()


# ------------------------------------------------------------------------------------------------ own folders
@needs_checkpoints
def test_hidden_files_skipped_and_a_stop_mid_run_marks_partial(infer_cli, frames_io, tmp_path: Path) -> None:
    """A folder named in Chinese holding macOS ``._000001.png`` files: they are skipped and reported, every frame
    gets a pose, and no "Glyph missing" warning appears. Then a frame that cannot be read mid-run: one line naming
    it, and the poses before it, their plots and summary.json are written, marked partial (as Ctrl-C does)."""
    world = SyntheticWorld(seed=3, num_frames=5, height=H, width=W, scenario="straight")
    folder = frames_io.write_frames(tmp_path / "东京街道", [world.image(i) for i in range(5)])
    for k in range(5):
        (folder / f"._{k:06d}.png").write_bytes(b"\x00\x05\x16\x07" + b"\x00" * 100)  # AppleDouble, not a PNG
    K = frames_io.intrinsics_overrides(world.intrinsics())
    out = tmp_path / "out"
    proc = infer_cli("data=folder", f"data.root='{folder}'", *K, f"out_dir={out}", *SMALL)
    assert "Glyph" not in proc.stdout + proc.stderr
    log = (out / "infer.log").read_text()
    assert f"image folder: skipped 5 hidden files in {folder} (._000000.png, ._000001.png, ._000002.png, ...: " in log
    assert frames_io.read_kitti(out / "东京街道.txt").shape == (5, 4, 4)
    assert json.loads((out / "summary.json").read_text())["partial"] is False

    (folder / "000003.png").write_bytes((folder / "000003.png").read_bytes()[:200])  # unreadable mid-run
    proc = infer_cli("data=folder", f"data.root='{folder}'", *K, f"out_dir={out}", "batch_size=1", *SMALL,
                     check=False)
    assert proc.returncode == 1
    line = error_line(proc)
    assert re.match(rf"dfvo-infer: error: cannot read image {re.escape(str(folder / '000003.png'))}: expected a "
                    r"complete PNG or JPEG file .*; the first (\d) of 5 poses, their metrics and plots are written, "
                    r"marked partial \[log: ", line), line
    written = int(re.search(r"the first (\d) of 5", line).group(1))
    assert 2 <= written <= 3 and frames_io.read_kitti(out / "东京街道.txt").shape == (written, 4, 4)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["partial"] is True and summary["stopped_by"] == "error" and summary["frames_written"] == written
    assert "000003.png" in summary["error"]
    assert (out / "trajectory.png").is_file() and (out / "frames.png").is_file()


# ------------------------------------------------------------------------------------------------ console
def test_infer_without_out_dir_names_the_output_folder(infer_cli) -> None:
    """``python infer.py`` without out_dir: the last console line names the (time-stamped) output folder."""
    proc = infer_cli("data.num_frames=3", *SMALL, *ORACLE)
    last = [line for line in proc.stdout.splitlines() if line.strip()][-1]
    m = re.fullmatch(rf"dfvo-infer: outputs in ({re.escape(str(infer_cli.cwd))}/outputs/infer/\S+)", last)
    assert m, proc.stdout[-2000:]
    assert (Path(m.group(1)) / POSES).is_file()


@pytest.mark.parametrize("tool, args, line", [
    ([sys.executable, "-m", "dfvo.evaluate"], ["algin=6dof"],
     "error: Could not override 'algin'; Key 'algin' not in 'EvaluateConfig'; the closest valid key is 'align'"),
    ([sys.executable, str(REPO / "infer.py")], ["tracker.scale.methd=simple"],
     "dfvo-infer: error: Could not override 'tracker.scale.methd'; Key 'methd' not in 'ScaleConfig'; the closest "
     "valid key is 'tracker.scale.method'"),
    ([sys.executable, str(REPO / "train.py")], ["trainer.max_step=3"],
     "dfvo-train: error: Could not override 'trainer.max_step'; Key 'max_step' not in 'TrainerConfig'; the closest "
     "valid key is 'trainer.max_steps'"),
], ids=["evaluate", "infer", "train"])
def test_misspelt_key_names_the_closest_valid_key(tmp_path: Path, tool: list[str], args: list[str],
                                                  line: str) -> None:
    """A misspelt key: one line naming the unknown key and the closest valid one, for all three commands (one home:
    :func:`dfvo.cli.errors.run_reporting_errors`); nothing is written to the working folder."""
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    proc = subprocess.run([*tool, *args], cwd=tmp_path, capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == (2 if "dfvo.evaluate" in tool else 1)
    assert error_line(proc) == line
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(("override", "message"), [
    ("num_threads=-2", "num_threads=-2; expected a positive number of torch threads"),
    ("data.camera_height=165", "data.camera_height=165.0; expected metres (the camera's height above the road, at "
                               "most 20 m); for 165.0 cm give 1.65"),
    ("tracker.scale.camera_height=150", "tracker.scale.camera_height=150.0; expected metres"),
    ("img_res.width=20", "img_res.width=20: frames of 1241x376 would be tracked at 32x32; expected at least 64 pixels "
                         "on each side"),
])
def test_round3_settings_are_one_line(infer_cli, override: str, message: str) -> None:
    """Issue 42: a negative thread count and a camera height given in centimetres end in one line naming the
    setting (they used to be a 39-line traceback and a silently 100x longer path); a working size too small to track
    says which width would do (it ran, "100 % constant motion", advising the setting the user gave)."""
    proc = infer_cli("data.num_frames=3", override, check=False)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert message in error_line(proc), proc.stderr[-1000:]


@pytest.mark.parametrize("window", [("data.start=8",), ("data.start=3", "data.end=2")])
def test_folder_frame_window_outside_the_folder_is_one_line(infer_cli, tmp_path: Path, window: tuple[str, ...]) -> None:
    """Issue 42: data=folder with data.start past the folder's end, or start after end: one line naming the folder
    and its frame count (it used to be an IndexError traceback)."""
    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(5):
        Image.fromarray(np.full((48, 64, 3), 40 * i, np.uint8)).save(folder / f"{i:06d}.png")
    proc = infer_cli("data=folder", f"data.root={folder}", "data.fx=50", "data.fy=50", "data.cx=32", "data.cy=24",
                     *window, f"out_dir={tmp_path / 'out'}", check=False)
    assert proc.returncode == 1
    line = error_line(proc)
    assert f"data=folder {folder}" in line and "of its 5 frames; expected at least 2" in line, line


def test_dataset_setting_without_the_dataset_names_data_kind(infer_cli) -> None:
    """Issue 42: `infer.py seq=06 data.root=ROOT` (data= forgotten) says to choose the dataset first; a typo of a
    synthetic setting still gets the closest key."""
    proc = infer_cli("seq=06", "data.root=/somewhere", check=False)
    assert proc.returncode == 1
    assert "has no data.root: choose the dataset first, e.g. data=kitti_odom data.root=..." in error_line(proc)
    proc = infer_cli("data.num_frams=3", check=False)
    assert "the closest valid key is 'data.num_frames'" in error_line(proc)


def test_kitti_raw_oxts_packet_with_nan_latitude_finishes_the_run(infer_cli, tmp_path: Path) -> None:
    """Issue 42: one oxts packet of the real drive 0005 with a NaN latitude: the packet file is named, its frame is
    evaluated without ground truth, metrics and plots are written and the summary is complete (it ended in the
    Python API's advice, no plots, summary.json "unfinished … killed"). The folder has no image_03 (a monocular
    run needs none) and pose_format=tum takes the times of image_02/timestamps.txt (it said the drive had none)."""
    src = REPO.parent / "shared" / "data" / "kitti_raw_test" / "2011_09_26"
    if not src.is_dir():
        pytest.skip(f"{src} not found")
    date = tmp_path / "raw" / "2011_09_26"
    drive = date / "2011_09_26_drive_0005_sync"
    (drive / "oxts" / "data").mkdir(parents=True)
    for f in src.glob("calib_*.txt"):
        (date / f.name).symlink_to(f)
    (drive / "image_02").symlink_to(src / drive.name / "image_02")
    for k, f in enumerate(sorted((src / drive.name / "oxts" / "data").glob("*.txt"))):
        text = f.read_text()
        (drive / "oxts" / "data" / f.name).write_text("nan " + text.split(" ", 1)[1] if k == 2 else text)
    out = tmp_path / "out"
    proc = infer_cli("data=kitti_raw", f"data.root={date.parent}", f"seq={drive.name}", "data.end=5",
                     "pose_format=tum", f"out_dir={out}", check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    log = (out / "infer.log").read_text()
    assert f"oxts packet {drive}/oxts/data/0000000002.txt: NaN or infinite position" in log
    summary = json.loads((out / "summary.json").read_text())
    assert summary["partial"] is False and summary["metrics"]["gt_missing"] == 1
    assert summary["metrics"]["num_frames"] == 4 and summary["metrics"]["rpe_m"] < 0.1
    assert (out / "trajectory.png").stat().st_size > 0 and (out / "frames.png").stat().st_size > 0
    rows = [line.split() for line in (out / f"{drive.name}.txt").read_text().splitlines()]
    assert len(rows) == 5 and all(len(r) == 8 for r in rows)
    assert float(rows[1][0]) - float(rows[0][0]) == pytest.approx(0.10338, abs=1e-4)  # 13:04:32.3458 -> .4492


# ------------------------------------------------------------------------------------------------ bags and logs
def _fake_bag(folder: Path, *names: str) -> Path:
    folder.mkdir(parents=True)
    for name in names:
        (folder / name).write_text("x")
    return folder


@pytest.mark.parametrize("left", [("metadata.yaml", "bag_0.db3"), ("bag_0.db3",)], ids=["earlier run", "killed run"])
def test_rerun_without_rosbag_removes_the_earlier_bag(infer_cli, tmp_path: Path, left: tuple[str, ...]) -> None:
    """Issue 42: a rerun without output.rosbag into a folder holding an earlier run's bag/ (or a SIGKILLed run's,
    without metadata.yaml) leaves only the new run's outputs (the old bag stayed); a folder of the user's own that is
    not a bag stays."""
    out = tmp_path / "out"
    _fake_bag(out / "bag", *left)
    own = _fake_bag(out / "notes", "metadata.yaml")
    infer_cli(f"out_dir={out}", "data.num_frames=3", *SMALL, *ORACLE)
    assert not (out / "bag").exists() and (own / "metadata.yaml").is_file()
    assert (out / POSES).is_file()


def test_bag_that_cannot_be_removed_is_one_line(infer_cli, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 42: an earlier run's bag/ that cannot be removed (read-only, another owner: PermissionError from
    rmtree, as a non-root user gets on a read-only bag/) is one line naming the bag and the file, not
    ``[Errno 13] Permission denied: 'metadata.yaml'``."""
    out = tmp_path / "out"
    bag = _fake_bag(out / "bag", "metadata.yaml", "bag_0.db3")

    def refuse(path, *args, **kwargs):
        raise PermissionError(13, "Permission denied", str(Path(path) / "metadata.yaml"))

    monkeypatch.setattr("shutil.rmtree", refuse)
    proc = infer_cli(f"out_dir={out}", "data.num_frames=3", *SMALL, *ORACLE, check=False)
    assert proc.returncode == 1
    assert error_line(proc).startswith(f"dfvo-infer: error: cannot remove the earlier run's {bag} "
                                       f"({bag}/metadata.yaml: Permission denied); remove it yourself or pass "
                                       "another out_dir=")


@pytest.mark.parametrize("fail_at", [0, 2], ids=["full at start", "fills mid-run"])
def test_rosbag_on_a_full_disk_is_one_line(infer_cli, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                           fail_at: int) -> None:
    """Issue 42: output.rosbag=true on a full disk (sqlite3's ``database or disk is full``, at the start or mid-run):
    one line naming the bag, and mid-run the summary says where it stopped (it was a 54-line traceback and a summary
    left "unfinished … killed")."""
    pytest.importorskip("rosbags")
    import sqlite3

    from dfvo.io.rosbag import OdometryBagWriter

    real = OdometryBagWriter.write

    def write(self, index, *args, **kwargs):
        if index >= fail_at:
            raise sqlite3.OperationalError("database or disk is full")
        return real(self, index, *args, **kwargs)

    monkeypatch.setattr(OdometryBagWriter, "write", write)
    out = tmp_path / "out"
    proc = infer_cli(f"out_dir={out}", "data.num_frames=5", "output.rosbag=true", "batch_size=1", *SMALL, *ORACLE,
                     check=False)
    assert proc.returncode == 1
    line = error_line(proc)
    assert line.startswith(f"dfvo-infer: error: cannot write {out / 'bag'}: database or disk is full (sqlite3); free "
                           "space on its disk or pass another out_dir="), line
    if fail_at:
        summary = json.loads((out / "summary.json").read_text())
        assert summary["partial"] is True and summary["stopped_by"] == "error" and summary["frames_written"] >= 2


def test_log_file_that_cannot_be_opened_is_one_line(infer_cli, tmp_path: Path) -> None:
    """Issue 42: a log file Hydra cannot open (a read-only out_dir; here infer.log is a folder, which fails the same
    way for root too) names the file instead of ``Unable to configure handler 'file'``."""
    out = tmp_path / "out"
    (out / "infer.log").mkdir(parents=True)
    proc = infer_cli(f"out_dir={out}", "data.num_frames=3", *SMALL, *ORACLE, check=False)
    assert proc.returncode == 1
    assert error_line(proc) == (f"dfvo-infer: error: cannot write the log file {out / 'infer.log'}: Is a directory; "
                                "pass out_dir= a writable folder")
