"""Training integration: synthetic and KITTI raw runs, exact resume, model-type check, NaN stop, bad roots."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from dfvo.training.runner import CKPT_KEY, NaNGuard, run_training

REPO = Path(__file__).resolve().parents[1]
TINY = ["data.height=64", "data.width=128", "data.batch_size=1", "data.val_num_frames=3",
        "trainer.enable_progress_bar=false", "trainer.log_every_n_steps=1",
        "model.log_images_every=1", "threads=1"]


SYN = ["data.num_frames=5", "data.seeds=[0]"]


def _cfg(tmp_path: Path, *overrides: str):
    syn = SYN if not any(o.startswith("data=") and o != "data=synthetic" for o in overrides) else []
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose("train", overrides=[f"runs_dir={tmp_path}", *TINY, *syn, *overrides])


def test_synthetic_few_steps(tmp_path: Path) -> None:
    # monitor "epoch" (min): the best checkpoint stays at epoch 0, last.ckpt must still follow every epoch
    cfg = _cfg(tmp_path, "model=depth_mono_sc", "data=synthetic", "data.max_train_samples=1", "trainer.max_epochs=2",
               "model.monitor=epoch", "name=syn")
    out = run_training(cfg)
    assert out["global_step"] == 2
    assert "epoch=0" in out["best_ckpt"]
    assert torch.load(out["last_ckpt"], map_location="cpu", weights_only=False)["global_step"] == 2
    m = out["metrics"]
    assert {"train/loss", "train/photometric_s3", "train/consistency_s0", "val/abs_rel", "val/a1"} <= set(m)
    assert 0 < m["train/loss"] < 1 and 0 <= m["val/a1"] <= 1
    ckpt = torch.load(out["last_ckpt"], map_location="cpu", weights_only=False)
    assert ckpt[CKPT_KEY] == "depth:depth_mono_sc"
    assert list((tmp_path / "syn" / "tb").glob("events.out.tfevents.*"))
    from dfvo.training.depth_module import DepthPoseModule
    loaded = DepthPoseModule.load_from_checkpoint(out["last_ckpt"], map_location="cpu").eval()
    x = torch.rand(1, 3, 64, 128)
    with torch.no_grad():
        assert torch.equal(loaded(x), out["module"].eval()(x))


def test_kitti_raw_few_steps(tmp_path: Path, kitti_raw_root: Path) -> None:
    cfg = _cfg(tmp_path, "model=depth_stereo", "data=kitti_raw", f"data.root={kitti_raw_root.parent}",
               "trainer.max_steps=2", "data.val_seeds=[]", "model.monitor=null", "name=kitti")
    out = run_training(cfg)
    assert out["global_step"] == 2 and torch.isfinite(torch.tensor(out["metrics"]["train/loss"]))
    assert "train/photometric_s0" in out["metrics"]


def _weights(path: str) -> dict[str, torch.Tensor]:
    return torch.load(path, map_location="cpu", weights_only=False)["state_dict"]


class _Interrupt(RuntimeError):
    pass


def test_resume_is_exact(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A run interrupted after epoch 1 and resumed from last.ckpt ends with the same weights and loss."""
    from dfvo.training.depth_module import DepthPoseModule
    common = ["model=depth_stereo", "data=synthetic", "data.max_train_samples=2", "data.batch_size=2", "data.width=64",
              "data.val_seeds=[]", "model.monitor=null", "trainer.logger=false", "trainer.max_epochs=2"]
    full = run_training(_cfg(tmp_path, *common, "name=full"))

    def crash(self) -> None:
        if self.current_epoch == 1:
            raise _Interrupt("simulated crash at the start of epoch 2")

    with monkeypatch.context() as m:
        m.setattr(DepthPoseModule, "on_train_epoch_start", crash, raising=False)
        with pytest.raises(_Interrupt):
            run_training(_cfg(tmp_path, *common, "name=half"))
    last = tmp_path / "half" / "checkpoints" / "last.ckpt"
    assert torch.load(last, map_location="cpu", weights_only=False)["global_step"] == 1
    resumed = run_training(_cfg(tmp_path, *common, "name=half", f"ckpt_path={last}"))
    assert full["global_step"] == resumed["global_step"] == 2
    a, b = _weights(full["last_ckpt"]), _weights(resumed["last_ckpt"])
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    assert full["metrics"]["train/loss"] == resumed["metrics"]["train/loss"]


def test_checkpoint_of_other_model_type_is_rejected(tmp_path: Path) -> None:
    first = run_training(_cfg(tmp_path, "model=depth_stereo", "trainer.max_steps=1", "data.val_seeds=[]",
                              "model.monitor=null", "trainer.logger=false", "name=a"))
    with pytest.raises(ValueError, match="depth:depth_stereo.*depth:depth_mono"):
        run_training(_cfg(tmp_path, "model=depth_mono", "trainer.max_steps=2", "name=b",
                          f"ckpt_path={first['last_ckpt']}"))


def test_nan_loss_stops_with_message(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from dfvo.training.depth_module import DepthPoseModule
    original = DepthPoseModule._losses

    def nan_losses(self, batch):
        loss, terms, vis = original(self, batch)
        return loss * float("nan"), terms, vis

    monkeypatch.setattr(DepthPoseModule, "_losses", nan_losses)
    with pytest.raises(FloatingPointError, match="training loss is nan at step"):
        run_training(_cfg(tmp_path, "model=depth_mono", "trainer.max_steps=3", "data.val_seeds=[]",
                          "model.monitor=null", "trainer.logger=false", "name=nan"))


def test_nan_guard_passes_finite_loss() -> None:
    class Stub:
        global_step, current_epoch = 0, 0
    NaNGuard().on_train_batch_end(Stub(), None, {"loss": torch.tensor(0.5)}, None, 0)
    with pytest.raises(FloatingPointError):
        NaNGuard().on_train_batch_end(Stub(), None, torch.tensor(float("inf")), None, 0)


def test_bad_data_root_names_the_path(tmp_path: Path) -> None:
    cfg = _cfg(tmp_path, "data=kitti_raw", f"data.root={tmp_path / 'nowhere'}", "trainer.max_steps=1")
    with pytest.raises(Exception, match="nowhere"):
        run_training(cfg)


def test_unknown_task_and_missing_keys(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="model.task"):
        run_training(_cfg(tmp_path, "model.task=segmentation"))
    from dfvo.training.depth_module import DepthPoseModule
    module = DepthPoseModule(_cfg(tmp_path, "model=depth_stereo"))
    with pytest.raises(KeyError, match="image_right"):
        module._losses({"image": torch.rand(1, 3, 64, 64), "image_prev": torch.rand(1, 3, 64, 64),
                        "image_next": torch.rand(1, 3, 64, 64), "K": torch.eye(3)[None]})


def test_train_py_entry_point(tmp_path: Path) -> None:
    """``python train.py`` composes the Hydra config and trains (subprocess, as a user runs it)."""
    cmd = [sys.executable, "train.py", "model=depth_mono", "data=synthetic", "trainer.max_steps=1",
           "data.val_seeds=[]", "model.monitor=null", f"runs_dir={tmp_path}", "name=cli", *TINY, *SYN]
    res = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    assert "done: step 1" in res.stdout
    assert (tmp_path / "cli" / "checkpoints" / "last.ckpt").is_file()


@pytest.mark.slow
def test_ddp_two_cpu_processes(tmp_path: Path) -> None:
    """``trainer=ddp`` with two CPU processes (gloo) runs a couple of steps."""
    cmd = [sys.executable, "train.py", "model=depth_stereo", "data=synthetic", "trainer=ddp", "trainer.devices=2",
           "trainer.accelerator=cpu", "trainer.max_steps=2", "data.val_seeds=[]", "model.monitor=null",
           f"runs_dir={tmp_path}", "name=ddp", *TINY, *SYN]
    res = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "MEMBER: 2/2" in res.stdout + res.stderr  # Lightning started two processes
    assert "done: step 2" in res.stdout


def test_kitti_odom_snippets_few_steps(tmp_path: Path, kitti_odom_root: Path) -> None:
    cfg = _cfg(tmp_path, "model=depth_stereo", "data=kitti_odom", f"data.root={kitti_odom_root}",
               "data.max_train_samples=1", "trainer.max_steps=1", "data.val_seeds=[]", "model.monitor=null",
               "trainer.logger=false", "name=odom")
    out = run_training(cfg)
    assert out["global_step"] == 1 and torch.isfinite(torch.tensor(out["metrics"]["train/loss"]))


def test_registry_builds_flow_module(tmp_path: Path) -> None:
    from dfvo.training.runner import build_module, model_identity
    cfg = _cfg(tmp_path, "model=flow_supervised")
    module = build_module(cfg)
    assert type(module).__name__ == "FlowModule"
    assert model_identity(cfg).startswith("flow:") and model_identity(cfg) != model_identity(_cfg(tmp_path))
