"""Flow datasets: the real FlyingChairs and KITTI 2015 samples, synthetic fixtures in the FlyingThings3D, Sintel and
KITTI 2012 layouts (files written with dfvo.data.flow_io), working-size transforms, layout errors, a training run."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from hydra import compose, initialize_config_dir
from PIL import Image

from dfvo.data.flow_datasets import FlyingChairs, FlyingThings3D, KittiFlow, Sintel, resize_flow
from dfvo.data.flow_io import read_flo, read_kitti_flow, write_flo, write_kitti_flow, write_pfm_flow
from dfvo.data.image_io import DatasetError

REPO = Path(__file__).resolve().parents[2]
SAMPLES = REPO.parent / "shared" / "data" / "flow_samples"
KEYS = {"image", "image_next", "flow_fwd", "flow_fwd_valid", "flow_bwd", "flow_bwd_valid", "index"}


def _sample(rel: str) -> Path:
    path = SAMPLES / rel
    if not path.exists():
        pytest.skip(f"needs {path} (the project's ../shared data folder); not present on this machine")
    return path


def _png(path: Path, seed: int, hw: tuple[int, int] = (12, 16)) -> np.ndarray:
    arr = np.random.default_rng(seed).integers(0, 256, size=(*hw, 3), dtype=np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(arr).save(path)
    return arr


# ------------------------------------------------------------------------------------------- FlyingChairs
def test_flyingchairs_real_samples_and_split() -> None:
    root = _sample("FlyingChairs_release")
    train, val, every = FlyingChairs(root, "train"), FlyingChairs(root, "val"), FlyingChairs(root / "data", "all")
    assert [p.name for p in train.pairs] == ["00001", "00002"] and [p.name for p in val.pairs] == ["00003"]
    assert len(every) == 3
    s = train[0]
    assert set(s) == KEYS
    assert s["image"].shape == s["image_next"].shape == (3, 384, 512) and s["flow_fwd"].shape == (2, 384, 512)
    ppm = np.asarray(Image.open(root / "data" / "00001_img1.ppm"), dtype=np.float32) / 255
    assert torch.allclose(s["image"], torch.from_numpy(ppm).permute(2, 0, 1))
    assert torch.equal(s["flow_fwd"], read_flo(root / "data" / "00001_flow.flo")[0])
    assert bool(s["flow_fwd_valid"].all()) and not bool(s["flow_bwd_valid"].any()) and not s["flow_bwd"].any()


def test_flyingchairs_crop_and_resize() -> None:
    root = _sample("FlyingChairs_release")
    full = FlyingChairs(root, "val")[0]
    c = FlyingChairs(root, "val", height=320, width=448, crop="center")[0]
    assert torch.equal(c["image"], full["image"][:, 32:352, 32:480])
    assert torch.equal(c["flow_fwd"], full["flow_fwd"][:, 32:352, 32:480])
    z = FlyingChairs(root, "val", resize=[192, 384], height=192, width=384)[0]
    ref = F.interpolate(full["flow_fwd"][None], size=(192, 384), mode="bilinear", align_corners=False)[0]
    assert torch.allclose(z["flow_fwd"], ref * torch.tensor([0.75, 0.5]).view(2, 1, 1))
    with pytest.raises(ValueError, match="400x600 does not fit.*384x512"):
        FlyingChairs(root, "val", height=400, width=600)[0]


def test_random_crop_shares_one_window(tmp_path: Path) -> None:
    """A fixture whose flow encodes each pixel's (column, row): the crop's first flow value is its window."""
    img1, img2 = _png(tmp_path / "data" / "00001_img1.ppm", 0, (30, 40)), _png(tmp_path / "data" / "00001_img2.ppm", 1,
                                                                              (30, 40))
    ys, xs = np.mgrid[0:30, 0:40]
    write_flo(tmp_path / "data" / "00001_flow.flo", np.stack([xs, ys]).astype(np.float64))
    torch.manual_seed(0)
    ds = FlyingChairs(tmp_path, "all", height=10, width=20, crop="random")
    windows = set()
    for _ in range(20):
        s = ds[0]
        left, top = (int(v) for v in s["flow_fwd"][:, 0, 0])
        windows.add((top, left))
        assert torch.equal(s["flow_fwd"][0], torch.from_numpy(xs[top:top + 10, left:left + 20]).float())
        for key, img in (("image", img1), ("image_next", img2)):
            crop = torch.from_numpy(img[top:top + 10, left:left + 20].astype(np.float32) / 255).permute(2, 0, 1)
            assert torch.allclose(s[key], crop)
    assert len(windows) > 5  # random windows, not one fixed crop


def test_flyingchairs_layout_errors(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match=r"has no \*_img1.ppm"):
        FlyingChairs(tmp_path)
    _png(tmp_path / "data" / "00001_img1.ppm", 0)
    with pytest.raises(DatasetError, match="00001_img2.ppm"):
        FlyingChairs(tmp_path)
    _png(tmp_path / "data" / "00001_img2.ppm", 1)
    write_flo(tmp_path / "data" / "00001_flow.flo", np.zeros((2, 12, 16)))
    with pytest.raises(DatasetError, match="FlyingChairs_train_val.txt"):
        FlyingChairs(tmp_path, "train")
    assert len(FlyingChairs(tmp_path, "all")) == 1


# ------------------------------------------------------------------------------------------- KITTI
def test_kitti2015_real_sample_sparse_resize() -> None:
    root = _sample("kitti_flow/training")
    ds = KittiFlow(root.parent, version=2015, mask="occ")
    assert len(ds) == 1 and ds.pairs[0].name == "000000" and set(ds.pairs[0].extra) == {"occ"}
    s = ds[0]
    flow, valid = read_kitti_flow(root / "flow_occ" / "000000_10.png")
    assert torch.equal(s["flow_fwd"], flow) and torch.equal(s["flow_fwd_valid"], valid)
    assert s["image"].shape == (3, 375, 1242)
    small = KittiFlow(root, resize=[192, 640], height=192, width=640)[0]
    assert small["flow_fwd"].shape == (2, 192, 640) and small["image"].shape == (3, 192, 640)
    # every valid target pixel holds the mean of the scaled flows of the source pixels that round onto it
    ys, xs = torch.nonzero(valid[0], as_tuple=True)
    xt = torch.round((xs.double() + 0.5) * 640 / 1242 - 0.5).long()
    yt = torch.round((ys.double() + 0.5) * 192 / 375 - 0.5).long()
    v = small["flow_fwd_valid"][0]
    assert int(v.sum()) == len(set((yt * 640 + xt).tolist()))
    k = 1234
    same = (yt == yt[k]) & (xt == xt[k])
    expected = flow[:, ys[same], xs[same]].double().mean(1) * torch.tensor([640 / 1242, 192 / 375]).double()
    assert torch.allclose(small["flow_fwd"][:, yt[k], xt[k]].double(), expected, atol=1e-5)


def test_resize_flow_sparse_keeps_a_constant_field() -> None:
    flow = torch.stack([torch.full((40, 60), 6.0), torch.full((40, 60), -4.0)])
    valid = torch.rand(1, 40, 60, generator=torch.Generator().manual_seed(0)) > 0.8
    out, v = resize_flow(flow, valid, (20, 30))
    assert 0 < int(v.sum()) < 600 and torch.all(out[0][v[0]] == 3.0) and torch.all(out[1][v[0]] == -2.0)
    assert torch.all(out[:, ~v[0]] == 0)


def test_kitti2012_fixture_and_errors(tmp_path: Path) -> None:
    train = tmp_path / "training"
    for name in ("000000", "000001"):
        _png(train / "colored_0" / f"{name}_10.png", 1)
        _png(train / "colored_0" / f"{name}_11.png", 2)
        f = np.stack([np.full((12, 16), 1.5), np.full((12, 16), -2.25)])
        write_kitti_flow(train / "flow_occ" / f"{name}_10.png", f, np.arange(192).reshape(12, 16) % 3 > 0)
        write_kitti_flow(train / "flow_noc" / f"{name}_10.png", f, np.arange(192).reshape(12, 16) % 3 > 1)
    ds = KittiFlow(tmp_path, version=2012, mask="noc")
    assert [p.name for p in ds.pairs] == ["000000", "000001"] and set(ds.pairs[0].extra) == {"occ", "noc"}
    s = ds[1]
    assert int(s["flow_fwd_valid"].sum()) == 64 and s["flow_fwd"][:, 0, 2].tolist() == [1.5, -2.25]
    with pytest.raises(DatasetError, match="image_2"):
        KittiFlow(tmp_path, version=2015)
    (train / "colored_0" / "000001_11.png").unlink()
    with pytest.raises(DatasetError, match="000001_11.png"):
        KittiFlow(tmp_path, version=2012)


# ------------------------------------------------------------------------------------------- FlyingThings3D
def _things(root: Path) -> dict:
    flows = {}
    for k in (6, 7, 8):
        _png(root / "frames_cleanpass" / "TRAIN" / "A" / "0000" / "left" / f"{k:04d}.png", k)
        fut, past = torch.full((2, 12, 16), float(k)), torch.full((2, 12, 16), -float(k))
        d = root / "optical_flow" / "TRAIN" / "A" / "0000"
        if k < 8:
            write_pfm_flow(d / "into_future" / "left" / f"OpticalFlowIntoFuture_{k:04d}_L.pfm", fut)
        write_pfm_flow(d / "into_past" / "left" / f"OpticalFlowIntoPast_{k:04d}_L.pfm", past, little_endian=False)
        flows[k] = (fut, past)
    return flows


def test_flyingthings_fixture_pairs_with_both_directions(tmp_path: Path) -> None:
    _things(tmp_path)
    ds = FlyingThings3D(tmp_path, "train", "clean")
    assert [p.name for p in ds.pairs] == ["A/0000/left/0006", "A/0000/left/0007"]
    s = ds[1]
    assert torch.all(s["flow_fwd"] == 7) and torch.all(s["flow_bwd"] == -8) and bool(s["flow_bwd_valid"].all())
    img = np.asarray(Image.open(tmp_path / "frames_cleanpass/TRAIN/A/0000/left/0008.png"), np.float32) / 255
    assert torch.allclose(s["image_next"], torch.from_numpy(img).permute(2, 0, 1))
    rev = FlyingThings3D(tmp_path, "train", "clean", reverse=True)
    assert len(rev) == 4 and torch.all(rev[1]["flow_fwd"] == -7) and torch.all(rev[1]["flow_bwd"] == 6)
    with pytest.raises(FileNotFoundError, match="frames_finalpass"):
        FlyingThings3D(tmp_path, "train", "final")
    with pytest.raises(FileNotFoundError, match=r"optical_flow.*TEST"):
        (tmp_path / "frames_cleanpass" / "TEST").mkdir()
        FlyingThings3D(tmp_path, "test", "clean")


# ------------------------------------------------------------------------------------------- Sintel
def test_sintel_fixture(tmp_path: Path) -> None:
    for scene in ("alley_1", "cave_2"):
        for k in (1, 2, 3):
            _png(tmp_path / "training" / "final" / scene / f"frame_{k:04d}.png", k, (8, 10))
        for k in (1, 2):
            write_flo(tmp_path / "training" / "flow" / scene / f"frame_{k:04d}.flo", np.full((2, 8, 10), float(k)))
    ds = Sintel(tmp_path, "final")
    assert [p.name for p in ds.pairs] == ["alley_1/0001", "alley_1/0002", "cave_2/0001", "cave_2/0002"]
    assert torch.all(ds[1]["flow_fwd"] == 2) and ds[1]["image"].shape == (3, 8, 10)
    assert len(Sintel(tmp_path / "training", "final", scenes=["cave_2"])) == 2
    with pytest.raises(FileNotFoundError, match="clean"):
        Sintel(tmp_path, "clean")


# ------------------------------------------------------------------------------------------- training
def test_flyingchairs_trains_two_steps(tmp_path: Path) -> None:
    root = _sample("FlyingChairs_release")
    from dfvo.training.runner import run_training
    with initialize_config_dir(config_dir=str(REPO / "dfvo" / "conf" / "train"), version_base="1.3"):
        cfg = compose("train", overrides=[
            f"runs_dir={tmp_path}", "model=flow_supervised", "data=flyingchairs", f"data.root={root}",
            "model.variant=tiny", "data.height=96", "data.width=128", "data.batch_size=2", "trainer.max_steps=2",
            "trainer.enable_progress_bar=false", "trainer.log_every_n_steps=1", "model.log_images_every=0",
            "threads=1", "name=chairs"])
    out = run_training(cfg)
    assert out["global_step"] == 2 and np.isfinite(out["metrics"]["train/loss"])
    assert out["metrics"]["val/epe"] > 0  # the split file's validation pair (00003)
    with initialize_config_dir(config_dir=str(REPO / "dfvo" / "conf" / "train"), version_base="1.3"):
        bad = compose("train", overrides=[f"runs_dir={tmp_path}", "model=depth_mono", "data=flyingchairs"])
    from dfvo.training.datamodule import DFVODataModule
    with pytest.raises(ValueError, match="flow frame pairs only|optical-flow frame pairs only"):
        DFVODataModule(bad)
