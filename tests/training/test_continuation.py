"""continue_from (dfvo.training.continuation): a depth run whose checkpoints are lost continues from its weights export
with the epochs to go and the whole run's rate schedule (issue 37: a new machine keeps a depth run's training)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_module
from safetensors import safe_open

from dfvo.io.checkpoint import CheckpointError
from dfvo.training.continuation import continued_config, read_continuation
from dfvo.training.runner import build_module, run_training

# a tiny synthetic depth run: 2 samples a epoch at batch 1 = 2 steps an epoch, 4 epochs = 8 steps, rate x0.1 from
# step int(0.5 * 8) = 4 of the whole run
TINY = ["model=depth_mono_sc", "data=synthetic", "data.num_frames=5", "data.seeds=[0]", "data.height=64",
        "data.width=128", "data.batch_size=1", "data.max_train_samples=2", "data.val_num_frames=3",
        "trainer.max_epochs=4", "model.lr_drop_fraction=0.5", "model.monitor=null", "model.log_images_every=0",
        "trainer.logger=false", "trainer.enable_progress_bar=false", "trainer.precision=32-true", "threads=1"]
IDENTITY = "depth:depth_mono_sc"


def _cfg(tmp_path: Path, *overrides: str):
    with initialize_config_module("dfvo.conf.train", version_base="1.3"):
        return compose("train", overrides=[f"runs_dir={tmp_path}", *TINY, *overrides])


def _rate_factors(module: torch.nn.Module, steps: int) -> list[float]:
    """The rate multiplier of each step of the run the module was trained in (its scheduler's lambda)."""
    scheduler = module.trainer.lr_scheduler_configs[0].scheduler
    return [scheduler.lr_lambdas[0](k) for k in range(steps)]


def test_a_lost_run_continues_from_its_weights_with_the_whole_runs_schedule(tmp_path: Path) -> None:
    whole = run_training(_cfg(tmp_path, "name=whole"))
    assert whole["global_step"] == 8
    assert _rate_factors(whole["module"], 8) == [1.0] * 4 + [0.1] * 4

    # stopped at step 3 (epoch 1), then its checkpoints are lost: only weights.safetensors is left
    part = run_training(_cfg(tmp_path, "name=part", "trainer.max_steps=3"))
    with safe_open(part["weights"], "pt") as f:
        assert (f.metadata()["global_step"], f.metadata()["epoch"]) == ("3", "1")
    kept = tmp_path / "kept.safetensors"
    shutil.copy(part["weights"], kept)
    shutil.rmtree(tmp_path / "part")

    cfg = _cfg(tmp_path, "name=part", "resume=auto", f"continue_from={kept}")
    cont = read_continuation(cfg, IDENTITY)
    assert (cont.steps_before, cont.epochs_before) == (3, 1)
    start = build_module(continued_config(cfg, cont))  # the depth network starts from the file's weights
    with safe_open(str(kept), "pt") as f:
        for k, v in start.depth_net.state_dict().items():
            torch.testing.assert_close(v, f.get_tensor(k).to(v.dtype))

    rest = run_training(cfg)
    # epoch 1 trained again whole: epochs 1, 2, 3 = 6 steps; the rate drops at the whole run's step 4 = its step 1
    assert rest["global_step"] == 6
    assert _rate_factors(rest["module"], 6) == [1.0] + [0.1] * 5
    with safe_open(rest["weights"], "pt") as f:  # the export counts the whole run: a continuation can be continued
        assert (f.metadata()["global_step"], f.metadata()["epoch"]) == ("9", "3")
    again_cont = read_continuation(_cfg(tmp_path, f"continue_from={rest['weights']}"), IDENTITY)
    assert (again_cont.steps_before, again_cont.epochs_before) == (9, 3)
    # resumed from its own checkpoint with the same continue_from: nothing left to train, the same schedule
    again = run_training(cfg)
    assert again["global_step"] == 6


def test_continue_from_refusals(tmp_path: Path) -> None:
    part = run_training(_cfg(tmp_path, "name=p", "trainer.max_steps=3"))
    with pytest.raises(ValueError, match=r"continue_from=.*epoch 1; expected an epoch below trainer.max_epochs=1"):
        read_continuation(_cfg(tmp_path, f"continue_from={part['weights']}", "trainer.max_epochs=1"), IDENTITY)
    with pytest.raises(CheckpointError, match=r"continue_from=.*holds a 'depth:depth_mono_sc' run's weights, not a "
                                              r"'depth:depth_stereo' one"):
        read_continuation(_cfg(tmp_path, f"continue_from={part['weights']}"), "depth:depth_stereo")
    with pytest.raises(CheckpointError, match=r"continue_from=.*nothing\.safetensors"):
        read_continuation(_cfg(tmp_path, f"continue_from={tmp_path / 'nothing.safetensors'}"), IDENTITY)
    flow = _cfg(tmp_path, f"continue_from={part['weights']}", "model=flow_supervised")
    with pytest.raises(ValueError, match="only depth runs continue from their weights"):
        read_continuation(flow, "flow:flow_supervised")
