"""Issue 16, robustness: the events a vision user's footage has, each in a short synthetic sequence with exact
ground truth (``infer.py data=folder`` on PNGs written from :class:`~dfvo.synthetic.SyntheticWorld`, or the
world itself): a burst of duplicated frames, a dropped frame, exposure steps, a lens cap, a truck filling the view,
very small parallax. Each run must keep one pose per frame, say in ``frames.csv`` what it did on the event's frames
(tracker, fallback_reason), and track normally again afterwards.

"Normal" is measured on the same run: the median error of the relative translation over the frames before the event
(the shipped networks at 96x320 miss each ~1 m step by ~10-30 %), with a floor of 25 % of the median true step.
The shipped networks give the flow and depth where the case is about what real images do; the oracle (exact flow and
depth of the world) where the case is about the tracker alone.
"""

from __future__ import annotations

import csv
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

from dfvo.synthetic import SyntheticWorld

REPO = Path(__file__).resolve().parents[2]
H, W = 96, 320
SMALL = [f"img_res.height={H}", f"img_res.width={W}", "progress=false", "num_threads=1"]
needs_checkpoints = pytest.mark.skipif(not (REPO / "dfvo/checkpoints/flow.safetensors").is_file(),
                                       reason="no shipped checkpoints in dfvo/checkpoints")
SETTLE = 2  # frames after an event before tracking must be back to normal


@dataclass
class Run:
    """A finished run: true and predicted poses (N,4,4) and the rows of frames.csv."""

    gt: np.ndarray
    pred: np.ndarray
    rows: list[dict[str, str]]

    def relative(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per frame k = 1..N-1 (index k-1): true step length, predicted step length, translation error (m) and
        rotation error (deg) of the relative motion ``T_prev_cur``."""
        rel_gt = np.linalg.inv(self.gt[:-1]) @ self.gt[1:]
        rel_pred = np.linalg.inv(self.pred[:-1]) @ self.pred[1:]
        err = np.linalg.inv(rel_gt) @ rel_pred
        cos = np.clip((np.trace(err[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1)
        return (np.linalg.norm(rel_gt[:, :3, 3], axis=1), np.linalg.norm(rel_pred[:, :3, 3], axis=1),
                np.linalg.norm(err[:, :3, 3], axis=1), np.degrees(np.arccos(cos)))

    def table(self) -> str:
        """Per-frame errors and flags, for failure messages."""
        step, pred, t_err, r_err = self.relative()
        return "\n".join(f"{k:3d} true {step[k - 1]:.3f} m, pred {pred[k - 1]:.3f} m, err {t_err[k - 1]:.3f} m "
                         f"{r_err[k - 1]:.2f} deg  {r['tracker']:>15}  {r['fallback_reason']}"
                         for k, r in enumerate(self.rows) if k > 0)


def check_one_pose_per_frame(run: Run, n: int) -> None:
    assert run.pred.shape == (n, 4, 4) and np.isfinite(run.pred).all()
    assert [int(r["frame"]) for r in run.rows] == list(range(n))
    assert all(r["tracker"] in ("E", "PnP", "constant_motion") for r in run.rows[1:]), run.table()


def flagged(row: dict[str, str]) -> bool:
    """The frame says it was not tracked the normal way (a fallback tracker, or a reason)."""
    return row["tracker"] != "E" or bool(row["fallback_reason"])


def check_back_to_normal(run: Run, after: Sequence[int], before: Sequence[int] | None = None) -> None:
    """Median translation error over frames ``after`` within max(2 x the median over ``before``, 25 % of the median
    true step), median rotation error under 0.5 degrees, and no frame after the event repeating the last motion."""
    step, _, t_err, r_err = run.relative()
    a = np.asarray(after) - 1
    normal = 0.25 * float(np.median(step[a]))
    if before is not None:
        normal = max(normal, 2.0 * float(np.median(t_err[np.asarray(before) - 1])))
    assert np.median(t_err[a]) <= normal and np.median(r_err[a]) < 0.5, (
        f"after the event: median error {np.median(t_err[a]):.3f} m / {np.median(r_err[a]):.2f} deg, normal "
        f"<= {normal:.3f} m / 0.5 deg\n{run.table()}")
    assert not any(run.rows[k]["tracker"] == "constant_motion" for k in after), run.table()


def run_folder(infer_cli, frames_io, tmp_path: Path, world: SyntheticWorld, ids: Sequence[int],
               transform: Callable[[int, torch.Tensor], torch.Tensor] | None = None, *extra: str) -> Run:
    """Write the world's frames ``ids`` (optionally changed by ``transform(k, image)``) as PNGs, run ``data=folder``
    with the world's intrinsics (the shipped networks unless ``extra`` says otherwise), read the results."""
    images = [world.image(i) for i in ids]
    if transform is not None:
        images = [transform(k, img) for k, img in enumerate(images)]
    folder = frames_io.write_frames(tmp_path / "frames", images)
    out = tmp_path / "out"
    infer_cli("data=folder", f"data.root={folder}", *frames_io.intrinsics_overrides(world.intrinsics()),
              f"out_dir={out}", *SMALL, *extra, timeout=900)
    rows = list(csv.DictReader((out / "frames.csv").open()))
    return Run(world.poses().double().numpy()[list(ids)], frames_io.read_kitti(out / "frames.txt"), rows)


def straight(n: int, **kwargs) -> SyntheticWorld:
    return SyntheticWorld(seed=0, num_frames=n, height=H, width=W, scenario="straight", **kwargs)


# ------------------------------------------------------------------------------------------------ duplicated frames
@needs_checkpoints
@pytest.mark.slow
def test_burst_of_duplicated_frames(infer_cli, frames_io, tmp_path: Path) -> None:
    """Frame 5 repeated three times (a frame grabber that stalls): the three copies have no motion (truth: zero), so
    their poses must stay put (< 5 % of a normal step), say so in frames.csv, and tracking resumes after them."""
    world = straight(14)
    ids = [*range(6), 5, 5, 5, *range(6, 14)]
    run = run_folder(infer_cli, frames_io, tmp_path, world, ids)
    check_one_pose_per_frame(run, len(ids))
    step, pred, _, _ = run.relative()
    dup = [6, 7, 8]
    assert all(pred[k - 1] < 0.05 * np.median(step) for k in dup), run.table()
    assert all(flagged(run.rows[k]) for k in dup), run.table()
    check_back_to_normal(run, after=range(9 + SETTLE, len(ids)), before=range(1, 6))


# ------------------------------------------------------------------------------------------------ dropped frame
@needs_checkpoints
@pytest.mark.slow
def test_dropped_frame(infer_cli, frames_io, tmp_path: Path) -> None:
    """Frame 7 missing: the pair (6, 8) moves twice as far; its pose must be that double step (within the
    networks' normal scale error), and the frames after it track normally."""
    world = straight(15)
    ids = [*range(7), *range(8, 15)]
    run = run_folder(infer_cli, frames_io, tmp_path, world, ids)
    check_one_pose_per_frame(run, len(ids))
    step, pred, t_err, _ = run.relative()
    jump = 7  # frame 7 of the sequence is world frame 8
    assert step[jump - 1] > 1.8 * np.median(step)
    assert 0.6 * step[jump - 1] < pred[jump - 1] < 1.4 * step[jump - 1], run.table()
    check_back_to_normal(run, before=range(1, jump), after=range(jump + SETTLE, len(ids)))


# ------------------------------------------------------------------------------------------------ exposure steps
@needs_checkpoints
@pytest.mark.slow
def test_exposure_steps(infer_cli, frames_io, tmp_path: Path) -> None:
    """The gain jumps by 1.5x at frame 6 and back at frame 10 (auto-exposure): on the two step frames the pose is
    either as good as normal or flagged (a fallback with its reason); tracking resumes after."""
    world = straight(15)
    run = run_folder(infer_cli, frames_io, tmp_path, world, range(15),
                     lambda k, img: (img * 1.5).clamp(0, 1) if 6 <= k < 10 else img)
    check_one_pose_per_frame(run, 15)
    step, _, t_err, _ = run.relative()
    normal = max(2.0 * float(np.median(t_err[:5])), 0.25 * float(np.median(step)))
    for k in (6, 10):
        assert t_err[k - 1] <= normal or flagged(run.rows[k]), run.table()
    check_back_to_normal(run, before=range(1, 6), after=range(10 + SETTLE, 15))


# ------------------------------------------------------------------------------------------------ lens cap
@needs_checkpoints
@pytest.mark.slow
def test_lens_cap(infer_cli, frames_io, tmp_path: Path) -> None:
    """Frames 6-8 black (a lens cap, a tunnel without lights): the four pairs touching them have nothing to track,
    so each must be flagged (a fallback with its reason), every frame keeps a pose, and tracking resumes."""
    world = straight(15)
    run = run_folder(infer_cli, frames_io, tmp_path, world, range(15),
                     lambda k, img: torch.zeros_like(img) if 6 <= k <= 8 else img)
    check_one_pose_per_frame(run, 15)
    for k in (6, 7, 8, 9):
        assert run.rows[k]["tracker"] == "constant_motion" and run.rows[k]["fallback_reason"], run.table()
    check_back_to_normal(run, before=range(1, 6), after=range(9 + SETTLE, 15))


# ------------------------------------------------------------------------------------------------ moving truck
MOVING_CAR_FRAMES = range(77, 101)  # drive world, seed 0: drive 77-80, a truck pulls out ahead 81-92, drive 93-100


def run_synthetic(infer_cli, frames_io, out: Path, *extra: str) -> Run:
    """``data=synthetic`` on :data:`MOVING_CAR_FRAMES` of the default drive world, written to ``out``."""
    first, end = MOVING_CAR_FRAMES.start, MOVING_CAR_FRAMES.stop
    infer_cli("data.num_frames=112", f"data.start={first}", f"data.end={end}", f"out_dir={out}", *SMALL, *extra,
              timeout=900)
    world = SyntheticWorld(seed=0, num_frames=112, height=H, width=W)
    assert world.segment_names()[first + TRUCK.start:first + TRUCK.stop] == ["moving_car"] * len(TRUCK)
    rows = list(csv.DictReader((out / "frames.csv").open()))
    return Run(world.poses().double().numpy()[first:end], frames_io.read_kitti(out / "synthetic_drive_s0.txt"), rows)


TRUCK = range(4, 16)  # frames of the run during the truck's manoeuvre


@pytest.fixture(scope="module")
def truck_oracle(module_infer_cli, frames_io) -> Run:
    """The truck sequence with exact flow and depth (flow=oracle depth=oracle), run once for the module; without the
    photometric road scale, an image measurement that at this test's 96x320 errs by a few per cent (the oracle's
    exactness is that of its flow and depth)."""
    return run_synthetic(module_infer_cli, frames_io, module_infer_cli.cwd.parent / "out", "flow=oracle",
                         "depth=oracle", "tracker.road_alignment.enabled=false")


def test_truck_filling_the_view_oracle_resumes(truck_oracle: Run) -> None:
    """A truck pulls out just ahead and fills half to two thirds of the view (frames 4-15 of the run), moving with
    the camera. With exact flow and depth every frame keeps a pose and, once the manoeuvre is over, the error is
    back at the oracle's ~1 mm."""
    check_one_pose_per_frame(truck_oracle, len(MOVING_CAR_FRAMES))
    _, _, t_err, r_err = truck_oracle.relative()
    after = np.arange(TRUCK.stop + SETTLE, len(MOVING_CAR_FRAMES)) - 1
    assert np.median(t_err[after]) < 0.01 and np.median(r_err[after]) < 0.05, truck_oracle.table()


def test_truck_filling_the_view_oracle_right_or_flagged(truck_oracle: Run) -> None:
    """While the truck fills the view, each frame's pose is right (translation error within 10 % of the true step)
    or flagged in frames.csv (a fallback tracker or a reason): never silently wrong."""
    step, _, t_err, _ = truck_oracle.relative()
    for k in TRUCK:
        assert t_err[k - 1] <= 0.1 * step[k - 1] or flagged(truck_oracle.rows[k]), truck_oracle.table()


@needs_checkpoints
@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="tracker with the shipped networks: after the truck's manoeuvre the translation "
                   "is back to normal (median 0.28 m <= 0.54 m, no constant motion) but the rotation is not: E and PnP "
                   "on the networks' flow around the truck ahead miss it by 0.5-2.8 deg on 5 of the 6 frames (median "
                   "0.82 deg, normal < 0.5 deg); see docs/scale.md")
def test_truck_filling_the_view_networks(infer_cli, frames_io, tmp_path: Path) -> None:
    """The same truck with the shipped networks: every frame keeps a pose, and after the manoeuvre tracking is
    back to normal (the frames before the truck pulls out set "normal")."""
    run = run_synthetic(infer_cli, frames_io, tmp_path / "out")
    check_one_pose_per_frame(run, len(MOVING_CAR_FRAMES))
    check_back_to_normal(run, before=range(1, TRUCK.start), after=range(TRUCK.stop + SETTLE, len(MOVING_CAR_FRAMES)))


# ------------------------------------------------------------------------------------------------ small parallax
@needs_checkpoints
@pytest.mark.slow
def test_very_small_parallax(infer_cli, frames_io, tmp_path: Path) -> None:
    """A near-still camera: 5 cm a frame (a twentieth of the normal ~1 m, ~1.5 px of flow at 96x320) for 8 frames,
    then driving off (5 cm -> 10 -> 25 -> 50 cm -> 1 m a frame). On the slow frames: no false motion (error under
    10 cm, a tenth of a normal step), and each frame is accurate (error under half its step or 2 cm) or says in
    frames.csv how it was tracked instead; once driving, tracking is normal."""
    steps = [1] * 8 + [2, 5, 10] + [20] * 7  # in world frames of 5 cm
    ids = np.concatenate([[0], np.cumsum(steps)]).tolist()
    world = straight(ids[-1] + 1, speed=0.05)
    run = run_folder(infer_cli, frames_io, tmp_path, world, ids)
    check_one_pose_per_frame(run, len(ids))
    step, pred, t_err, _ = run.relative()
    slow = range(1, 9)
    assert np.all(step[np.asarray(slow) - 1] < 0.06), step
    for k in slow:
        assert t_err[k - 1] < 0.1, run.table()
        assert t_err[k - 1] <= max(0.5 * step[k - 1], 0.02) or flagged(run.rows[k]), run.table()
    check_back_to_normal(run, after=range(12 + SETTLE, len(ids)))
