"""Flow training: a known translation is learnt, the Lightning module and online finetuning run."""

from __future__ import annotations

from pathlib import Path

import lightning as L
import pytest
import torch
import torch.nn.functional as F
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from torch.utils.data import DataLoader

from dfvo.io.checkpoint import CheckpointError
from dfvo.losses.flow_losses import endpoint_error, multiscale_epe
from dfvo.matching.flow_warp import warp_by_flow
from dfvo.models.flow_net import FlowNet
from dfvo.synthetic import SyntheticFlowDataset, SyntheticWorld
from dfvo.training.flow_module import FlowModule, load_flow_weights
from dfvo.training.online_flow import OnlineFlowConfig, OnlineFlowFinetuner
from dfvo.training.runner import run_training


def _pairs(n: int, size: int, g: torch.Generator, translation: bool, max_shift: float = 4.0):
    """img2 = smooth random texture, img1(x) = img2(x + F(x)) exactly, so F is the true flow 1->2."""
    big = size + 16
    tex = F.interpolate(torch.rand(n, 3, big // 4, big // 4, generator=g), size=(big, big), mode="bicubic",
                        align_corners=False).clamp(0, 1)
    if translation:
        flow = ((torch.rand(n, 2, 1, 1, generator=g) * 2 - 1) * max_shift).expand(n, 2, big, big).contiguous()
    else:  # smooth random field: a richer training signal than one shift per image
        coarse = (torch.rand(n, 2, 3, 3, generator=g) * 2 - 1) * max_shift
        flow = F.interpolate(coarse, size=(big, big), mode="bicubic", align_corners=False)
    img1, _ = warp_by_flow(tex, flow)
    c = slice(8, 8 + size)
    return img1[:, :, c, c], tex[:, :, c, c], flow[:, :, c, c].contiguous()


@pytest.mark.slow  # ~40-80 s on the shared 2-core CPU
def test_short_supervised_run_recovers_a_translation() -> None:
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    net = FlowNet("tiny")
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    for _ in range(300):
        a, b, f = _pairs(8, 64, g, translation=False)
        loss, _ = multiscale_epe(net(a, b, all_scales=True), f)
        opt.zero_grad()
        loss.backward()
        opt.step()
    a, b, f = _pairs(8, 64, torch.Generator().manual_seed(123), translation=True)
    with torch.no_grad():
        pred = net(a, b)
    zero_epe = f.norm(dim=1).mean()
    assert endpoint_error(pred, f) < 0.4 * zero_epe
    shift_err = (pred[..., 8:-8, 8:-8].mean(dim=(2, 3)) - f[:, :, 0, 0]).norm(dim=1)
    assert shift_err.mean() < 0.6 and shift_err.max() < 1.5


def _cfg(mode: str, tmp_path: Path, init_from: str | None = None):
    return OmegaConf.create({"model": {"task": "flow", "name": f"flow_{mode}", "mode": mode, "variant": "tiny",
                                       "lr": 1e-3, "lr_milestones": [15], "lr_gamma": 0.1, "init_from": init_from,
                                       "log_images_every": 1,
                                       "loss": {"alpha": 0.85, "w_smooth": 0.1, "w_consistency": 5e-3,
                                                "occlusion": True}}})


@pytest.mark.parametrize("mode", ["supervised", "self"])
def test_flow_module_trains_and_logs_images(mode: str, tmp_path: Path) -> None:
    ds = SyntheticFlowDataset([0], num_frames=4, height=64, width=96)
    module = FlowModule(_cfg(mode, tmp_path))
    before = [p.detach().clone() for p in module.net.parameters()]
    logger = L.pytorch.loggers.TensorBoardLogger(str(tmp_path), name="flow")
    trainer = L.Trainer(max_steps=2, logger=logger, enable_checkpointing=True, default_root_dir=str(tmp_path),
                        limit_val_batches=1, enable_progress_bar=False, enable_model_summary=False,
                        accelerator="cpu", devices=1)
    trainer.fit(module, DataLoader(ds, batch_size=2), DataLoader(ds, batch_size=2))
    assert torch.isfinite(trainer.callback_metrics["train/loss"])
    assert "val/epe" in trainer.callback_metrics or mode == "self"
    assert any((a - b).abs().sum() > 0 for a, b in zip(module.net.parameters(), before))
    events = list(Path(logger.log_dir).glob("events.out.tfevents.*"))
    assert events and max(e.stat().st_size for e in events) > 10_000  # images were written
    ckpt = tmp_path / "m.ckpt"
    trainer.save_checkpoint(ckpt)
    reloaded = FlowModule(_cfg("self", tmp_path, init_from=str(ckpt)))
    for a, b in zip(reloaded.net.parameters(), module.net.parameters()):
        torch.testing.assert_close(a, b)
    # the module rebuilt from the config stored in the checkpoint: same mode, variant and weights
    rebuilt = FlowModule.load_from_checkpoint(ckpt, map_location="cpu")
    assert rebuilt.mode == mode and rebuilt.model_cfg.variant == "tiny" and rebuilt.model_cfg.lr == 1e-3
    for a, b in zip(rebuilt.net.parameters(), module.net.parameters()):
        assert torch.equal(a, b)


def test_load_flow_weights_errors(tmp_path: Path) -> None:
    with pytest.raises(CheckpointError, match="init_from"):
        load_flow_weights(FlowNet("tiny"), tmp_path / "missing.ckpt")
    torch.save(FlowNet("small").state_dict(), tmp_path / "small.pt")
    with pytest.raises(Exception, match="small.pt"):
        load_flow_weights(FlowNet("tiny"), tmp_path / "small.pt")
    with pytest.raises(ValueError, match="model.mode"):
        FlowModule(OmegaConf.create({"model": {"mode": "weird"}}))


def test_online_finetuning_adapts_then_stops() -> None:
    world = SyntheticWorld(seed=2, num_frames=5, height=64, width=96, scenario="straight")
    torch.manual_seed(0)
    net = FlowNet("tiny")
    tuner = OnlineFlowFinetuner(net, OnlineFlowConfig(lr=1e-3, max_frames=3))
    before = [p.detach().clone() for p in net.parameters()]
    losses = [tuner.step(world.image(i)[None], world.image(i + 1)[None]) for i in range(4)]
    assert all(isinstance(v, float) and v > 0 for v in losses[:3]) and losses[3] is None
    assert tuner.num_steps == 3 and not tuner.active and not net.training
    assert any((a - b).abs().sum() > 0 for a, b in zip(net.parameters(), before))
    frozen = [p.detach().clone() for p in net.parameters()]
    assert tuner.step(world.image(0)[None], world.image(1)[None]) is None
    assert all(torch.equal(a, b) for a, b in zip(net.parameters(), frozen))
    tuner.reset()
    assert tuner.active and OnlineFlowConfig().lr == 1e-5 and OnlineFlowConfig().max_frames == 200


REPO = Path(__file__).resolve().parents[2]


TRAIN_PY_TINY = ["model.variant=tiny", "trainer.max_steps=2", "trainer.max_epochs=1",
                 "trainer.enable_progress_bar=false", "data.val_num_frames=3", "threads=1"]


def _train(tmp_path: Path, *overrides: str) -> Path:
    import subprocess
    import sys

    cmd = [sys.executable, "train.py", *TRAIN_PY_TINY, f"runs_dir={tmp_path}", *overrides]
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return tmp_path


@pytest.mark.slow  # fast covers: test_train_outputs.py::test_flow_weights_export_runs_in_infer (model=flow_supervised
# data=synthetic through run_training), test_flow_module_trains_and_logs_images, the train.py entry point of depth
def test_train_py_flow_supervised(tmp_path: Path) -> None:
    """`python train.py model=flow_supervised data=synthetic` with tiny settings writes checkpoints and logs."""
    _train(tmp_path, "model=flow_supervised", "data=synthetic", "data.height=64", "data.width=96",
           "data.seeds=[0]", "data.num_frames=4")
    assert (tmp_path / "flow_supervised_synthetic" / "checkpoints" / "last.ckpt").is_file()
    assert list((tmp_path / "flow_supervised_synthetic").rglob("events.out.tfevents.*"))


def test_flow_self_on_kitti_raw(tmp_path: Path, kitti_raw_root: Path) -> None:
    """`model=flow_self data=kitti_raw data.frame_skips=[1,2,3]` on ../shared/data/kitti_raw with tiny settings (2
    shuffled steps over the snippets of every gap), run in this process as train.py runs it."""
    with initialize_config_dir(config_dir=str(REPO / "dfvo" / "conf" / "train"), version_base="1.3"):
        cfg = compose("train", overrides=[*TRAIN_PY_TINY, f"runs_dir={tmp_path}", "model=flow_self", "data=kitti_raw",
                                          f"data.root={kitti_raw_root.parent}", "data.height=64", "data.width=192",
                                          "data.batch_size=2", "data.frame_skips=[1,2,3]"])
    out = run_training(cfg)
    assert out["global_step"] == 2 and torch.isfinite(torch.tensor(out["metrics"]["train/loss"]))
    assert (tmp_path / "flow_self_kitti_raw" / "checkpoints" / "last.ckpt").is_file()


def test_unreadable_init_from_names_the_setting(tmp_path: Path) -> None:
    """Junk, empty and non-state-dict files given as model.init_from raise a ValueError naming the setting, the path
    and the expected formats (before any training)."""
    junk, empty, junk_st, listing = (tmp_path / n for n in ("junk.ckpt", "empty.pt", "junk.safetensors", "list.pt"))
    junk.write_bytes(bytes(range(256)) * 4)
    empty.write_bytes(b"")
    junk_st.write_bytes(b"\xff" * 64)
    torch.save([1, 2, 3], listing)
    for path in (junk, empty, junk_st, listing):
        with pytest.raises(ValueError, match=rf"model.init_from={path}: .*flow network"):
            load_flow_weights(FlowNet("tiny"), path)
        with pytest.raises(ValueError, match=rf"model.init_from={path}"):
            FlowModule(_cfg("self", tmp_path, init_from=str(path)))
    with pytest.raises(CheckpointError, match="model.init_from=.*missing.ckpt.* does not exist"):
        load_flow_weights(FlowNet("tiny"), tmp_path / "missing.ckpt")


@pytest.mark.parametrize("data", ["kitti_raw", "kitti_odom", "kitti_raw_synthetic"])
def test_supervised_flow_on_data_without_true_flow_fails_at_setup(tmp_path: Path, data: str) -> None:
    """model=flow_supervised with a dataset without true flow stops before training (no checkpoint, no step)."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(REPO / "dfvo" / "conf" / "train"), version_base="1.3"):
        cfg = compose("train", overrides=["model=flow_supervised", f"data={data}", f"runs_dir={tmp_path}", "name=x"])
    with pytest.raises(ValueError, match=rf"model=flow_supervised .*data={data}.*data=synthetic.*model=flow_self"):
        run_training(cfg)
    assert not (tmp_path / "x" / "checkpoints").exists()
