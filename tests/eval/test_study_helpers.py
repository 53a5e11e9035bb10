"""The helpers the accuracy studies share (dfvo.eval.error_decomposition, dfvo.eval.epipolar), against hand-derived
values and the synthetic world's exact flow and poses."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from dfvo.eval.epipolar import fundamental_from_pose
from dfvo.eval.error_decomposition import compose, relative, scale_free
from dfvo.geometry.two_view import sampson_sq
from dfvo.synthetic import SyntheticWorld


def _poses(n: int, seed: int = 0) -> np.ndarray:
    """n camera poses T_w_k along a wiggly path, the first the identity."""
    rng = np.random.default_rng(seed)
    rel = []
    for _ in range(n - 1):
        a = rng.normal(scale=0.02, size=3)
        K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
        T = np.eye(4)
        T[:3, :3] = np.eye(3) + np.sin(np.linalg.norm(a)) / np.linalg.norm(a) * K + \
            (1 - np.cos(np.linalg.norm(a))) / np.linalg.norm(a) ** 2 * K @ K
        T[:3, 3] = [rng.normal(scale=0.1), rng.normal(scale=0.05), 1.0 + rng.uniform()]
        rel.append(T)
    return compose(np.stack(rel))


def test_relative_and_compose_invert_each_other():
    gt = _poses(12)
    np.testing.assert_allclose(compose(relative(gt)), gt, atol=1e-12)


def test_scale_free_separates_the_lengths_from_the_directions():
    gt = _poses(12)
    rel = relative(gt)
    factors = np.linspace(0.5, 2.0, len(rel))
    scaled = rel.copy()
    scaled[:, :3, 3] *= factors[:, None]  # right directions and rotations, wrong lengths
    true_lengths, moving, direction, ratio = scale_free(gt, compose(scaled))
    assert moving.all()
    np.testing.assert_allclose(ratio, factors, rtol=1e-12)
    np.testing.assert_allclose(direction, 0.0, atol=1e-5)
    np.testing.assert_allclose(true_lengths, gt, atol=1e-9)  # lengths restored: the ground truth again
    turned = rel.copy()
    turned[0, :3, 3] = np.linalg.norm(rel[0, :3, 3]) * np.array([1.0, 0.0, 0.0])  # one pair sideways, same length
    _, _, direction, ratio = scale_free(gt, compose(turned))
    expected = np.degrees(np.arccos(rel[0, 0, 3] / np.linalg.norm(rel[0, :3, 3])))
    assert abs(direction[0] - expected) < 1e-6 and abs(ratio[0] - 1.0) < 1e-12


def test_true_flow_lies_on_the_epipolar_lines_of_the_true_pose():
    world = SyntheticWorld(seed=3, num_frames=3, height=48, width=160)
    poses = world.poses().numpy()
    K = world.intrinsics().double().numpy()
    flow, valid = world.flow(0, 1)
    static = valid[0] & ~world.dynamic_mask(0)[0]
    v, u = torch.nonzero(static, as_tuple=True)
    x0 = torch.stack([u, v], -1).double()
    x1 = x0 + flow[:, v, u].T.double()
    F = torch.from_numpy(fundamental_from_pose(np.linalg.inv(poses[0]) @ poses[1], K))[None, None]
    dist = sampson_sq(F, x0[None], x1[None])[0, 0].sqrt()
    assert len(dist) > 1000 and float(dist.median()) < 1e-3 and float(dist.max()) < 0.05
    sideways = np.linalg.inv(poses[0]) @ poses[1]
    sideways[:3, 3] = np.linalg.norm(sideways[:3, 3]) * np.array([1.0, 0.0, 0.0])  # the camera moving right instead
    wrong = torch.from_numpy(fundamental_from_pose(sideways, K))[None, None]
    assert float(sampson_sq(wrong, x0[None], x1[None])[0, 0].sqrt().median()) > 0.2  # another pose does not fit


def test_length_panel_configs_keep_list_values_whole() -> None:
    """``studies/length_panel.py --configs``: ``NAME:a=[1,2],b=3`` is two overrides, one entry needs no ``;``, names
    of its table are split on ``,``, an unknown name is one clear error."""
    import pytest

    from studies.length_panel import CONFIGS, parse_configs

    assert parse_configs("lv2:x.levels=2,x.iterations=[3,2]") == {"lv2": ["x.levels=2", "x.iterations=[3,2]"]}
    assert parse_configs("a:k=[1,2,3];b:m=1,n=[4,5]") == {"a": ["k=[1,2,3]"], "b": ["m=1", "n=[4,5]"]}
    assert parse_configs("default,flow=dis") == {"default": CONFIGS["default"], "flow=dis": CONFIGS["flow=dis"]}
    with pytest.raises(SystemExit, match="unknown 'nope'"):
        parse_configs("default,nope")


def test_length_panel_cases_include_the_raw_and_hand_held_sequences(tmp_path: Path) -> None:
    """``studies/length_panel.py``: KITTI raw 0005 and handheld_markers join the cases when the shared data folder
    beside ``--kitti-root`` holds them (the hand-held one with its intrinsics file's values and
    ``experiment=handheld``), and not when it does not; a configuration that names its own experiment replaces the
    case's."""
    import argparse

    import numpy as np

    from studies.length_panel import HANDHELD_MARKERS_INTRINSICS, cases, infer_overrides

    args = argparse.Namespace(kitti_root=str(tmp_path / "kitti_odom"), synthetic_frames=10, video=None)
    assert not {"kitti_raw_0005", "handheld_markers"} & set(cases(args))
    (tmp_path / "kitti_raw_test" / "2011_09_26" / "2011_09_26_drive_0005_sync").mkdir(parents=True)
    (tmp_path / "handheld_markers" / "images").mkdir(parents=True)
    found = cases(args)
    assert f"data.root={tmp_path / 'kitti_raw_test'}" in found["kitti_raw_0005"]
    assert "experiment=handheld" in found["handheld_markers"]
    hand = found["handheld_markers"]
    assert infer_overrides(hand, ["flow=dis"]) == [*hand, "flow=dis"]
    paper = infer_overrides(hand, ["experiment=paper"])
    assert "experiment=handheld" not in paper and paper[-1] == "experiment=paper" and len(paper) == len(hand)
    shared = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "handheld_markers" / "K.txt"
    if shared.is_file():  # the intrinsics are the sequence's own
        K = np.loadtxt(shared)
        assert np.allclose([K[0, 0], K[1, 1], K[0, 2], K[1, 2]],
                           [HANDHELD_MARKERS_INTRINSICS[k] for k in ("fx", "fy", "cx", "cy")], atol=1e-6)


def test_length_panel_takes_the_hand_held_worlds_by_seed_and_tabulates_them(tmp_path: Path) -> None:
    """``--handheld-seeds``: each seed's planar and corner hand-held worlds join the cases (a range or a list; a bad
    value is one clear error); their table gives each run's constant-motion frames, 7-DoF ATE, true-length RPE and
    ``auto``'s verdict, and sums the constant-motion frames (a hand-made panel)."""
    import argparse

    import pytest

    from studies.length_panel import cases, handheld_seeds, handheld_table, is_handheld_world

    assert handheld_seeds("1000-1002") == [1000, 1001, 1002] and handheld_seeds("7,9") == [7, 9]
    assert handheld_seeds(None) == [] and handheld_seeds("") == []
    with pytest.raises(SystemExit, match="--handheld-seeds='10-x'"):
        handheld_seeds("10-x")
    args = argparse.Namespace(kitti_root=str(tmp_path / "kitti_odom"), synthetic_frames=12, video=None,
                              handheld_seeds="1000,1001")
    found = cases(args)
    assert found["synthetic_handheld_planar_s1001"] == ["data=synthetic", "seq=handheld_planar", "data.seed=1001",
                                                        "data.num_frames=12"]
    assert "synthetic_handheld_s1000" in found and not is_handheld_world("synthetic_drive")
    assert not any(is_handheld_world(c) for c in cases(argparse.Namespace(**{**vars(args), "handheld_seeds": None})))

    def run(cm: int, ate: float, rpe: float, motion: str, judged: int, revised: int | None) -> dict:
        return {"constant_motion": cm, "as_run": {"ate_7dof_m": ate}, "true_lengths": {"rpe_m": rpe},
                "motion": {"motion": motion, "judged_from_frame": judged, "revised_from_frame": revised}}

    result = {"runs": {"a": {"synthetic_handheld_planar_s1000": run(3, 0.0412, 0.00123, "handheld", 28, 33),
                             "synthetic_handheld_s1000": run(1, 0.02, 0.0005, "handheld", 6, None),
                             "kitti07": {"error": "x"}},
                       "b": {"synthetic_handheld_planar_s1000": {"error": "boom"}}}}
    text = handheld_table(result, ["kitti07", "synthetic_handheld_planar_s1000", "synthetic_handheld_s1000"])
    lines = text.splitlines()
    assert lines[0] == ("| configuration | synthetic_handheld_planar_s1000 | synthetic_handheld_s1000 | "
                        "constant motion in all |")
    assert lines[2] == ("| a | 3 CM, 0.0412 / 0.00123, handheld@28/33 | 1 CM, 0.0200 / 0.00050, handheld@6/None "
                        "| 4 |")
    assert lines[3] == "| b | error | — | 0 |"
    assert handheld_table(result, ["kitti07"]) == ""


def test_the_camera_height_in_use_replays_the_trackers_causal_estimator() -> None:
    """``studies.road_height.heights_in_use``: a road read at 2.4 m on the first frames, then at 1.65 m. By hand with
    the default estimator (3 frames with a plane, spread <= 15 %): no height on frames 1-3 (too few planes), 2.4 m
    on frames 4-6 (the median of 2.4, 2.4, 2.4 and then one, two 1.65 m), none on frame 7 (median 2.025 m, spread
    1.4826 x 0.375 / 2.025 = 27 %), 1.65 m from frame 8: worst 2.4 m, 7 of 10 frames off by more than 5 %. The
    whole sequence's median would say 1.65 m."""
    from dfvo.tracking.config import CameraHeightConfig
    from studies.road_height import heights_in_use

    heights = [2.4, 2.4, None, 2.4] + [1.65] * 6
    assert heights_in_use(heights, CameraHeightConfig()) == {"in_use_worst_m": 2.4, "in_use_off_5pct": 0.7}
    assert heights_in_use([1.65] * 5, CameraHeightConfig()) == {"in_use_worst_m": 1.65, "in_use_off_5pct": 0.4}
    assert heights_in_use([None] * 4, CameraHeightConfig()) == {"in_use_worst_m": None, "in_use_off_5pct": 1.0}


def test_depth_against_stereo_splits_the_road_from_the_rows_above():
    """studies/depth_vs_stereo.region_ratios: a prediction 1.5x too far above the lower third and right on it reads
    1.5 and 1.0; pixels above the crop's top, without stereo depth or beyond 80 m are not scored."""
    from studies.depth_vs_stereo import region_ratios
    h, w = 30, 8
    stereo = np.full((h, w), 10.0)
    stereo[:, 0] = 0.0  # no match
    stereo[:, 1] = 95.0  # beyond 80 m
    pred = stereo.copy()
    pred[:20] *= 1.5  # rows 0..19 (above 2/3 of 30)
    pred[:12] = 1000.0  # above the crop's top (0.4 x 30 = 12): not scored
    r = region_ratios(pred, stereo)
    assert r["lower third"] == 1.0 and abs(r["upper rows"] - 1.5) < 1e-12
    assert r["pixels"] == (h - 12) * (w - 2)
