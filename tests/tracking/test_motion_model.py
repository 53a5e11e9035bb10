"""``tracker.motion``: a car's or a hand's settings, and ``auto`` judging which from the first frames."""

from __future__ import annotations

import math

import pytest
import torch

from dfvo.synthetic import SyntheticWorld
from dfvo.tracking import TrackerConfig, VisualOdometry
from dfvo.tracking.config import GateConfig, HandheldConfig, ModelSelectionConfig, MotionAutoConfig, ScaleConfig
from dfvo.tracking.motion_model import (
    MotionJudge,
    elevation_deg,
    may_use_homography,
    motion_settings,
    off_axis_deg,
)


def _direction(deg: float, azimuth_deg: float = 0.0) -> torch.Tensor:
    """A unit translation ``deg`` off the optical axis (z), turned ``azimuth_deg`` about it from the x axis."""
    a, b = math.radians(deg), math.radians(azimuth_deg)
    return torch.tensor([math.sin(a) * math.cos(b), math.sin(a) * math.sin(b), math.cos(a)], dtype=torch.float64)


def test_off_axis_angle_is_measured_either_way_along_the_axis() -> None:
    assert off_axis_deg(torch.tensor([0.0, 0.0, 2.0])) == pytest.approx(0.0)
    assert off_axis_deg(torch.tensor([0.0, 0.0, -0.5])) == pytest.approx(0.0)  # a car reversing
    assert off_axis_deg(torch.tensor([1.0, 0.0, 1.0])) == pytest.approx(45.0)
    assert off_axis_deg(torch.tensor([0.0, -3.0, 0.0])) == pytest.approx(90.0)
    assert math.isnan(off_axis_deg(torch.zeros(3)))


def test_elevation_is_measured_either_way_out_of_the_horizontal_plane() -> None:
    assert elevation_deg(torch.tensor([0.0, 0.0, 2.0])) == pytest.approx(0.0)  # forward
    assert elevation_deg(torch.tensor([-3.0, 0.0, 0.5])) == pytest.approx(0.0)  # sideways, level
    assert elevation_deg(torch.tensor([0.0, 1.0, 1.0])) == pytest.approx(45.0)  # down (y points down)
    assert elevation_deg(torch.tensor([0.0, -1.0, 1.0])) == pytest.approx(45.0)  # up
    assert elevation_deg(torch.tensor([0.0, -0.2, 0.0])) == pytest.approx(90.0)
    assert math.isnan(elevation_deg(torch.zeros(3)))


def test_the_judge_counts_measured_frames_with_parallax_and_judges_once() -> None:
    """Hand-derived: with ``frames=3`` the judgement is the median of the first three directions whose parallax is
    at least ``min_parallax_px`` (frames without a direction or with too little parallax do not count); it is made
    once, on the frame that completes the count, and later frames do not change it."""
    cfg = TrackerConfig(motion_auto=MotionAutoConfig(frames=3, off_axis_deg=25.0, min_parallax_px=1.0))
    judge = MotionJudge(cfg)
    assert judge.motion == "car" and judge.deciding and judge.may_use_homography  # a hand's planar path may come
    assert judge.observe(1, _direction(80.0), 0.5) is None  # too little parallax: a stop's direction is noise
    assert judge.observe(2, None, 3.0) is None  # constant motion, no direction measured
    assert judge.observe(3, _direction(60.0, 90.0), 3.0) == pytest.approx((60.0, 60.0))  # counted: its angles
    assert judge.observe(4, _direction(5.0), 3.0) == pytest.approx((5.0, 0.0))
    assert judge.motion == "car" and judge.reason is None  # not judged yet: a car's settings
    judge.observe(5, _direction(30.0, 200.0), 3.0)  # median of 60, 5, 30 = 30 > 25
    assert judge.motion == "handheld" and not judge.deciding and judge.judged_at == 5
    assert judge.reason is not None and "30.0 deg > motion_auto.off_axis_deg=25" in judge.reason
    assert judge.observe(6, _direction(0.0), 9.0) == pytest.approx((0.0, 0.0)) and judge.motion == "handheld"
    report = judge.report()
    assert report["motion"] == "handheld" and report["judged_from_frame"] == 6 and report["frames_measured"] == 3
    assert report["median_off_axis_deg"] == pytest.approx(30.0) and report["off_axis_deg"] == [60.0, 5.0, 30.0]
    judge.reset()
    assert judge.motion == "car" and judge.deciding and judge.angles == []
    for k, deg in enumerate((2.0, 24.0, 70.0)):  # median 24 <= 25: a car
        judge.observe(k + 1, _direction(deg), 2.0)
    assert judge.motion == "car" and not judge.deciding and judge.revisable
    assert not judge.may_use_homography  # a car's planar pairs go to PnP: the E-tracker skips the decomposition


def test_a_cars_verdict_is_revised_when_the_camera_leaves_the_axis_and_its_horizontal_plane() -> None:
    """Hand-derived, ``frames=3``, ``revise_frames=4``: a car's verdict (median angle to the optical axis of 2, 24,
    10 = 10) is revised on every measured frame from the last four directions' medians of their angle to the axis
    and to the camera's horizontal plane (x-z; a direction ``d`` off the axis at azimuth 90 deg rises ``d``, at 0 deg
    not at all). (axis, plane) after each frame: sideways level steps 80 deg off the axis, a car's (a skid, the
    synthetic drive's sideways steps): (17, 1), then (52, 0): off the axis but level, still a car; a stop does not
    count; 40 up: (60, 0); 50 down: (65, 20): both above 25 and 10 deg: hand-held from that frame on, and then final.
    A camera pitched 15 deg down driving forward (15 deg off the axis and out of the plane) stays a car;
    ``revise_frames=None``: the first verdict is final."""
    cfg = TrackerConfig(motion_auto=MotionAutoConfig(frames=3, off_axis_deg=25.0, min_parallax_px=1.0,
                                                     revise_frames=4, revise_elevation_deg=10.0))
    judge = MotionJudge(cfg)
    for k, (deg, azimuth) in enumerate(((2.0, 90.0), (24.0, 90.0), (10.0, 0.0), (80.0, 0.0), (80.0, 0.0))):
        judge.observe(k + 1, _direction(deg, azimuth), 2.0)
    assert judge.motion == "car" and judge.judged_at == 3 and judge.revisable
    assert [a for a, _ in judge.latest] == pytest.approx([24.0, 10.0, 80.0, 80.0])
    assert [e for _, e in judge.latest] == pytest.approx([24.0, 0.0, 0.0, 0.0], abs=1e-9)
    assert judge.observe(6, _direction(70.0, 90.0), 0.5) is None and judge.motion == "car"  # too little parallax
    judge.observe(7, _direction(40.0, 90.0), 2.0)  # medians 60 and 0: still a car
    assert judge.motion == "car" and judge.revised_at is None
    assert judge.observe(8, _direction(50.0, 270.0), 2.0) == pytest.approx((50.0, 50.0))
    assert judge.motion == "handheld" and judge.revised_at == 8 and not judge.revisable
    assert judge.settings.planar == "homography" and judge.may_use_homography
    for k in range(9, 15):
        judge.observe(k, _direction(0.0), 5.0)
    assert judge.motion == "handheld" and judge.revised_at == 8
    report = judge.report()
    assert report["judged_from_frame"] == 4 and report["revised_from_frame"] == 9
    assert report["off_axis_deg"] == [2.0, 24.0, 10.0]  # the first verdict's angles
    assert "car from frame 4 on" in report["reason"] and "revised: handheld from frame 9 on" in report["reason"]
    assert "65.0 deg > motion_auto.off_axis_deg=25" in report["reason"]
    assert "20.0 deg > motion_auto.revise_elevation_deg=10" in report["reason"]
    judge.reset()
    assert judge.revised_at is None and judge.motion == "car" and judge.deciding and len(judge.latest) == 0
    pitched = MotionJudge(cfg)
    for k in range(12):
        pitched.observe(k + 1, _direction(15.0, 90.0), 2.0)
    assert pitched.motion == "car" and pitched.revised_at is None
    final = MotionJudge(TrackerConfig(motion_auto=MotionAutoConfig(frames=3, min_parallax_px=1.0,
                                                                   revise_frames=None)))
    for k, deg in enumerate((2.0, 24.0, 10.0, *([80.0] * 12))):
        final.observe(k + 1, _direction(deg, 90.0), 2.0)
    assert final.motion == "car" and final.revised_at is None and not final.revisable
    with pytest.raises(ValueError, match="revise_frames"):
        MotionAutoConfig(revise_frames=0)
    with pytest.raises(ValueError, match="revise_elevation_deg"):
        MotionAutoConfig(revise_elevation_deg=90.0)


@pytest.mark.parametrize("setting", ["car", "handheld"])
def test_a_fixed_motion_is_never_judged(setting: str) -> None:
    judge = MotionJudge(TrackerConfig(motion=setting, motion_auto=MotionAutoConfig(frames=1)))
    for k in range(5):
        judge.observe(k + 1, _direction(0.0 if setting == "handheld" else 80.0), 5.0)
    assert judge.motion == setting and judge.judged_at is None and judge.angles == []


def test_the_settings_of_each_motion() -> None:
    """A car's settings are tracker.gate's and tracker.model_selection's as given; a hand's tracker.handheld's (its
    planar path only where GRIC fits a homography); the E-tracker computes the homography's decomposition whenever a
    motion the run may use needs it."""
    cfg = TrackerConfig(gate=GateConfig(confirm_direction_frames=3), motion="car")
    car = motion_settings(cfg, cfg.motion)
    assert (car.confirm_direction_frames, car.confirm_direction_by_pnp_deg, car.planar) == (3, None, "pnp")
    hand = motion_settings(cfg, "handheld")
    assert (hand.confirm_direction_frames, hand.confirm_direction_by_pnp_deg, hand.planar) == (2, 45.0, "homography")
    flow_rule = TrackerConfig(model_selection=ModelSelectionConfig(method="flow"))
    assert motion_settings(flow_rule, "handheld").planar == "pnp"
    assert not may_use_homography(cfg) and may_use_homography(TrackerConfig())  # auto: a hand's may come
    assert may_use_homography(TrackerConfig(motion="handheld"))
    assert not may_use_homography(TrackerConfig(motion="handheld", handheld=HandheldConfig(planar="pnp")))
    with pytest.raises(ValueError, match="tracker.motion"):
        TrackerConfig(motion="drone")
    with pytest.raises(ValueError, match="tracker.handheld.confirm_direction_frames"):
        HandheldConfig(confirm_direction_frames=1)


@pytest.fixture(scope="module")
def city_exact() -> tuple[torch.Tensor, ...]:
    """The synthetic city world (seed 1000, 14 frames at 96x320: a car turning at a junction) with exact flows and
    depths: flows (13,2,H,W) each way, depths (14,1,H,W), K (3,3)."""
    w = SyntheticWorld(seed=1000, num_frames=14, scenario="city", height=96, width=320)
    frames = [w.render(i, right=False) for i in range(14)]
    return (torch.stack([f["flow_fwd"] for f in frames[:-1]]), torch.stack([f["flow_bwd"] for f in frames[:-1]]),
            torch.stack([f["depth"] for f in frames]), w.intrinsics())


def test_auto_judges_a_car_and_keeps_a_cars_poses_exactly(city_exact: tuple[torch.Tensor, ...]) -> None:
    """A car's frames are tracked with a car's settings before and after the judgement: ``auto`` gives the poses of
    ``tracker.motion=car`` bit for bit, and judges a car (the translation ~2 deg off the axis)."""
    ff, fb, d, K = city_exact
    poses, judges = {}, {}
    for motion in ("car", "auto"):
        vo = VisualOdometry(TrackerConfig(motion=motion))
        poses[motion] = torch.stack([r.T_w_cur for r in vo.run(ff, fb, d[:-1], K, depths_next=d[1:])])
        judges[motion] = vo.motion
    assert torch.equal(poses["car"], poses["auto"])
    report = judges["auto"].report()
    assert report["motion"] == "car" and report["frames_measured"] == 5 and max(report["off_axis_deg"]) < 5.0


def test_auto_judges_a_hand_and_takes_its_settings(handheld_exact: tuple[torch.Tensor, ...]) -> None:
    """The synthetic hand-held world (exact flow, depth 10x too far): a car's settings send 8 of its 15 frames to
    constant motion (the direction gate holds the old direction where the hand turns). ``auto`` measures the
    translation 51-61 deg off the optical axis, switches to a hand's settings after 5 measured frames, and from then
    on uses the trackers ``tracker.motion=handheld`` uses (one constant-motion frame); every direction of E itself
    is the true one (the homography's, its planar path, within 15 deg with this depth: 12 deg at most, as with
    ``handheld``)."""
    ff, fb, d, K, P = handheld_exact
    results, judges = {}, {}
    for motion in ("car", "auto", "handheld"):
        vo = VisualOdometry(TrackerConfig(scale=ScaleConfig(camera_height=None), motion=motion))
        results[motion] = vo.run(ff, fb, d[:-1], K, depths_next=d[1:])
        judges[motion] = vo.motion
    judge = judges["auto"]
    report = judge.report()
    assert judge.motion == "handheld" and report["median_off_axis_deg"] > 40.0
    assert report["settings"] == {"confirm_direction_frames": 2, "confirm_direction_by_pnp_deg": 45.0,
                                  "planar": "homography", "confirm_length_frames": 2}
    first = judge.judged_at  # the frame index that completed the judgement; the next frames run a hand's settings
    assert first is not None and first <= 8
    cm = {m: [str(r.diagnostics.tracker) == "constant_motion" for r in res] for m, res in results.items()}
    assert sum(cm["car"]) >= 6 and sum(cm["auto"]) <= sum(cm["car"]) - 5, cm
    assert cm["auto"][first:] == cm["handheld"][first:] and sum(cm["auto"]) <= 1, cm
    used = {m: [str(r.diagnostics.tracker) for r in res] for m, res in results.items()}
    assert used["auto"][first:] == used["handheld"][first:], used
    true = torch.linalg.inv(P[:-1].double()) @ P[1:].double()
    for r, t in zip(results["auto"], true):
        if str(r.diagnostics.tracker) == "E":  # E's own direction is exact; the homography's within 15 deg here
            cos = float(torch.nn.functional.cosine_similarity(r.T_prev_cur[:3, 3], t[:3, 3], dim=0))
            assert math.degrees(math.acos(min(1.0, cos))) < (15.0 if r.diagnostics.homography_motion else 1.0)


def test_auto_streams_as_it_runs_with_the_verdict_inside_a_batch(handheld_exact: tuple[torch.Tensor, ...]) -> None:
    """The verdict changes the settings from the next frame on, inside a batch too: batched ``run`` (batch sizes 4
    and 3, the verdict at the 5th frame falls inside a batch of each) and frame-by-frame ``step`` give the same poses
    and the same verdict."""
    ff, fb, d, K, _ = handheld_exact
    cfg = TrackerConfig(scale=ScaleConfig(camera_height=None))
    poses, verdicts = [], []
    for b in (4, 3):
        vo = VisualOdometry(cfg)
        poses.append(torch.stack([r.T_w_cur for r in vo.run(ff, fb, d[:-1], K, batch_size=b, depths_next=d[1:])]))
        verdicts.append((vo.motion.motion, vo.motion.judged_at))
    vo = VisualOdometry(cfg)
    poses.append(torch.stack([vo.step(ff[k:k + 1], fb[k:k + 1], d[k:k + 1], K[None], depth_cur=d[k + 1:k + 2]).T_w_cur
                              for k in range(ff.shape[0])]))
    verdicts.append((vo.motion.motion, vo.motion.judged_at))
    assert verdicts[0] == ("handheld", 5) and verdicts.count(verdicts[0]) == 3, verdicts
    assert torch.allclose(poses[0], poses[1], atol=1e-9) and torch.allclose(poses[0], poses[2], atol=1e-9)


def test_a_hand_first_moving_along_the_axis_is_judged_a_car_then_revised() -> None:
    """The planar hand-held world's seed 39 (exact flow and depth): its first nine moves run 17-22 deg off the optical
    axis and below the horizon, then 8 deg, then 52 deg off it and out of the horizontal plane. ``auto`` judges a car
    at frame 8; with the first verdict final (``revise_frames=None``) the poses are ``tracker.motion=car``'s bit for
    bit (10 frames on constant motion where the car's gates hold). Revised from the last 10 measured translations,
    the motion turns hand-held inside a batch (batch 8), the next pairs of that batch take the homography's motion
    (decomposed on demand: the batch was tracked with a car's settings), at most one frame falls back after it and
    E's directions are the true ones (1 deg); batched ``run`` and frame-by-frame ``step`` agree."""
    n, batch = 40, 8
    w = SyntheticWorld(seed=39, num_frames=n, scenario="handheld_planar", height=96, width=320)
    frames = [w.render(i, right=False) for i in range(n)]
    ff, fb = torch.stack([f["flow_fwd"] for f in frames[:-1]]), torch.stack([f["flow_bwd"] for f in frames[:-1]])
    d, K, P = torch.stack([f["depth"] for f in frames]), w.intrinsics(), w.poses()
    results, judges = {}, {}
    for name, cfg in (("car", TrackerConfig(motion="car")),
                      ("final", TrackerConfig(motion_auto=MotionAutoConfig(revise_frames=None))),
                      ("auto", TrackerConfig())):
        vo = VisualOdometry(cfg)
        results[name] = vo.run(ff, fb, d[:-1], K, depths_next=d[1:], batch_size=batch)
        judges[name] = vo.motion
    cm = {m: [str(r.diagnostics.tracker) == "constant_motion" for r in res] for m, res in results.items()}
    assert judges["final"].motion == "car" and judges["final"].judged_at == 8
    assert all(torch.equal(a.T_w_cur, b.T_w_cur) for a, b in zip(results["final"], results["car"]))
    assert sum(cm["car"]) >= 8, cm
    auto = judges["auto"]
    assert auto.motion == "handheld" and auto.judged_at == 8, auto.report()
    revised = auto.revised_at  # the frame (pair revised - 1 -> revised) whose translation turned the verdict
    assert revised is not None and revised <= 24 and revised % batch != 0, auto.report()  # inside a batch
    after = results["auto"][revised:]
    assert sum(cm["auto"][revised:]) <= 1 and sum(cm["auto"]) <= sum(cm["car"]) - 8, cm
    in_batch = after[:batch - revised % batch]  # the rest of the revision's batch
    assert any(r.diagnostics.homography_motion for r in in_batch), [str(r.diagnostics.tracker) for r in in_batch]
    true = (torch.linalg.inv(P[:-1].double()) @ P[1:].double())[revised:]
    for r, t in zip(after, true):
        if str(r.diagnostics.tracker) == "E":
            cos = float(torch.nn.functional.cosine_similarity(r.T_prev_cur[:3, 3], t[:3, 3], dim=0))
            assert math.degrees(math.acos(min(1.0, cos))) < 1.0
    measured = [(r.diagnostics.off_axis_deg, r.diagnostics.elevation_deg) for r in results["auto"]]
    assert all(a is None or a < 25.0 for a, _ in measured[:8]), measured
    vo = VisualOdometry(TrackerConfig())
    stepped = [vo.step(ff[k:k + 1], fb[k:k + 1], d[k:k + 1], K[None], depth_cur=d[k + 1:k + 2]) for k in range(n - 1)]
    assert vo.motion.revised_at == revised
    for a, b in zip(results["auto"], stepped):
        assert torch.allclose(a.T_w_cur, b.T_w_cur, atol=1e-9)
