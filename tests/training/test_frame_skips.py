"""Frame-skip snippets (issue 13): data.frame_skips gives (i-s, i, i+s) snippets / (k, k+s) pairs, never across a
sequence boundary, for the synthetic, KITTI odometry and KITTI raw training data."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_module
from torch.utils.data import Dataset

from dfvo.training.datamodule import DFVODataModule
from dfvo.training.snippets import SkipSnippets


class _Frames(Dataset):
    """Frame j: an image filled with j, a pose translated by j."""

    def __init__(self, n: int) -> None:
        self.n = n

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, j: int) -> dict[str, torch.Tensor]:
        pose = torch.eye(4)
        pose[2, 3] = j
        return {"image": torch.full((3, 2, 2), float(j)), "pose": pose, "index": torch.tensor(j),
                "timestamp": torch.tensor(0.1 * j, dtype=torch.float64)}


def _ids(sample: dict[str, torch.Tensor]) -> tuple[int, int, int, int]:
    return (int(sample["image_prev"][0, 0, 0]), int(sample["image"][0, 0, 0]), int(sample["image_next"][0, 0, 0]),
            int(sample["frame_skip"]))


def test_skip_snippets_stay_inside_each_sequence() -> None:
    frames = _Frames(12)
    ds = SkipSnippets(frames, [range(0, 5), range(5, 12)], frame_skips=[1, 3])
    expected = [(p - s, p, p + s, s) for s in (1,) for p in range(1, 4)]
    expected += [(5 + p - s, 5 + p, 5 + p + s, s) for s in (1, 3) for p in range(s, 7 - s)]
    assert [_ids(ds[i]) for i in range(len(ds))] == expected  # the 5-frame sequence has no gap-3 snippet
    sample = ds[len(ds) - 1]
    assert "timestamp" not in sample
    assert float(sample["pose_prev"][2, 3]) == 5 and float(sample["pose_next"][2, 3]) == 11
    with pytest.raises(ValueError, match="frame_skips"):
        SkipSnippets(frames, [range(12)], frame_skips=[0])
    with pytest.raises(ValueError, match="no snippet"):
        SkipSnippets(frames, [range(3)], frame_skips=[2])


def _datamodule(*overrides: str) -> DFVODataModule:
    with initialize_config_module("dfvo.conf.train", version_base="1.3"):
        cfg = compose("train", overrides=["data.height=64", "data.width=96", "data.val_seeds=[]", *overrides])
    dm = DFVODataModule(cfg)
    dm.setup("fit")
    return dm


def test_synthetic_flow_pairs_with_frame_skips() -> None:
    """model=flow_self data=synthetic data.frame_skips=[1,3]: every pair (k, k+s) of each world, with s recorded and
    the images of frames k and k+s."""
    dm = _datamodule("model=flow_self", "data=synthetic", "data.seeds=[0]", "data.num_frames=6",
                     "data.frame_skips=[1,3]")
    ds = dm.train_set
    assert ds.frame_skips == (1, 3) and len(ds) == 5 + 3
    world = ds.worlds[0]
    i = next(j for j, (_, k, s) in enumerate(ds.items) if s == 3 and k == 2)
    sample = ds[i]
    assert int(sample["frame_skip"]) == 3
    assert torch.equal(sample["image"], world.image(2)) and torch.equal(sample["image_next"], world.image(5))
    depth = _datamodule("model=depth_stereo", "data=synthetic", "data.seeds=[0]", "data.num_frames=7",
                        "data.frame_skips=[2]").train_set
    assert depth.frame_skips == (2,) and len(depth) == 3  # targets 2, 3, 4 with neighbours at -2, +2


def test_kitti_odom_snippets_with_frame_skips(kitti_odom_root: Path) -> None:
    from dfvo.data.kitti_odometry import KittiOdometry
    frames = KittiOdometry(kitti_odom_root, "06", 64, 96, stereo=True)
    flow = _datamodule("model=flow_self", "data=kitti_odom", f"data.root={kitti_odom_root}", "data.frame_skips=[1,2]")
    n = len(frames)
    assert len(flow.train_set) == (n - 2) + (n - 4)
    sample = flow.train_set[n - 2]  # the first gap-2 snippet: frames (0, 2, 4)
    assert int(sample["frame_skip"]) == 2 and "image_right" not in sample  # flow needs no stereo partner
    for key, j in (("image_prev", 0), ("image", 2), ("image_next", 4)):
        assert torch.equal(sample[key], frames[j]["image"]), key
    torch.testing.assert_close(sample["pose_next"], frames[4]["pose"])
    stereo = _datamodule("model=depth_stereo", "data=kitti_odom", f"data.root={kitti_odom_root}",
                         "data.frame_skips=[2]").train_set[0]
    assert torch.equal(stereo["image_right"], frames[2]["image_right"])
    assert torch.equal(stereo["image_prev"], frames[0]["image"])


def test_kitti_raw_snippets_with_frame_skips(kitti_raw_root: Path) -> None:
    """Gap 1 of data.frame_skips=[1,2] gives exactly KittiRawSnippets' own snippets (plus the rig's camera height,
    data.camera_height); gap 2 the frames i-2, i+2."""
    from dfvo.data.kitti_raw import KittiRawSnippets
    root = kitti_raw_root.parent
    own = KittiRawSnippets(root, 64, 96, stereo=True, temporal=True)
    ds = _datamodule("model=depth_stereo", "data=kitti_raw", f"data.root={root}", "data.frame_skips=[1,2]",
                     "data.frame_cache_dir=null").train_set
    n = len(own)
    assert len(ds) == n + (n - 2)
    for i in (0, n - 1):
        a, b = ds[i], own[i]
        assert set(a) == set(b) | {"frame_skip", "camera_height"}
        assert float(a["camera_height"]) == pytest.approx(1.65)
        for key in b:
            assert torch.equal(a[key], b[key]), key
    gap2 = ds[n]  # frames (0, 2, 4)
    assert int(gap2["frame_skip"]) == 2
    assert torch.equal(gap2["image_prev"], own[0]["image_prev"]) and torch.equal(gap2["image_next"], own[3]["image"])
    flow = _datamodule("model=flow_self", "data=kitti_raw", f"data.root={root}", "data.frame_skips=[3]",
                       "data.frame_cache_dir=null").train_set
    assert "image_right" not in flow[0] and int(flow[0]["frame_skip"]) == 3
    assert torch.equal(flow[0]["image_next"], own[5]["image"])


def test_mixed_batch_keeps_the_synthetic_true_depth() -> None:
    """A KITTI + synthetic batch (data=kitti_raw_synthetic): the keys every sample has are stacked, and the true
    depth of the synthetic samples is kept with zeros ("no ground truth", what log_depth_l1 leaves out) for the
    KITTI ones, so experiment=depth_scene supervises the synthetic samples of every batch (the key was dropped)."""
    from dfvo.losses.depth_supervision import log_depth_l1
    from dfvo.training.datamodule import collate_common_keys

    real = {"image": torch.rand(3, 4, 6), "T_right_left": torch.eye(4)}
    synthetic = {"image": torch.rand(3, 4, 6), "T_right_left": torch.eye(4), "depth": torch.full((1, 4, 6), 5.0),
                 "flow": torch.zeros(2, 4, 6)}
    batch = collate_common_keys([real, synthetic])
    assert set(batch) == {"image", "T_right_left", "depth"}
    assert torch.equal(batch["depth"][0], torch.zeros(1, 4, 6)) and torch.equal(batch["depth"][1], synthetic["depth"])
    pred = torch.full((2, 1, 4, 6), 5.0 * math.e)  # log error 1 where there is truth
    loss, count = log_depth_l1(pred, batch["depth"], 100.0)
    assert float(count) == 24 and float(loss) == pytest.approx(1.0)
    assert set(collate_common_keys([real, real])) == {"image", "T_right_left"}
    # the stereo matcher's hints of the KITTI samples (data.depth_hints): 0, no hint, for the synthetic ones
    hinted = collate_common_keys([{**real, "depth_hint": torch.full((1, 4, 6), 7.0)}, synthetic])
    assert torch.equal(hinted["depth_hint"][0], torch.full((1, 4, 6), 7.0))
    assert torch.equal(hinted["depth_hint"][1], torch.zeros(1, 4, 6))
