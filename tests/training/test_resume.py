"""resume=auto / resume=never (dfvo.training.resume), atomic checkpoint replacement (dfvo.training.export), the
console progress line and trainer.precision=auto (dfvo.training.precision): issue 37."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_module

from dfvo.io.checkpoint import CheckpointError
from dfvo.training import precision as precision_module
from dfvo.training.callbacks import eta_text
from dfvo.training.export import durable_replace
from dfvo.training.precision import resolve_precision
from dfvo.training.resume import find_resume_point, read_finished, resume_point
from dfvo.training.runner import run_training

IDENTITY = "flow:flow_mix"
# a tiny step-scheduled flow run (one synthetic world, FlowNet "tiny" at 32x96)
TINY = ["model=flow_mix", "data=flow_mix", "model.variant=tiny", "data.height=32", "data.width=96", "data.seeds=[0]",
        "data.num_frames=5", "data.frame_skips=[1]", "data.max_flow=null", "data.val_seeds=[]", "data.batch_size=2",
        "model.log_images_every=0", "threads=1", "trainer.logger=false", "trainer.enable_progress_bar=false",
        "trainer.checkpoint_every_n_steps=2", "trainer.precision=32-true"]


def _cfg(tmp_path: Path, *overrides: str):
    with initialize_config_module("dfvo.conf.train", version_base="1.3"):
        return compose("train", overrides=[f"runs_dir={tmp_path}", f"data.cache_dir={tmp_path / 'cache'}", *TINY,
                                           *overrides])


def _ckpt(path: Path, step: int, identity: str = IDENTITY) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"state_dict": {}, "global_step": step, "dfvo_model": identity}, path)
    return path


def test_resume_auto_picks_the_newest_readable_checkpoint(tmp_path: Path) -> None:
    """Newest first by modification time; a cut file (a power loss) is skipped with its reason; none: step 0;
    only unreadable files: one error naming them."""
    run = tmp_path / "run"
    assert find_resume_point(run, IDENTITY) is None
    older = _ckpt(run / "checkpoints" / "previous.ckpt", 5)
    newer = _ckpt(run / "checkpoints" / "last.ckpt", 10)
    point = find_resume_point(run, IDENTITY)
    assert point is not None and (point.path, point.step, point.skipped) == (newer, 10, ())
    newer.write_bytes(newer.read_bytes()[:40])  # cut short
    point = find_resume_point(run, IDENTITY)
    assert point is not None and (point.path, point.step) == (older, 5) and "last.ckpt" in point.skipped[0]
    older.write_bytes(b"")
    with pytest.raises(CheckpointError, match="no usable checkpoint"):
        find_resume_point(run, IDENTITY)


def test_resume_never_refuses_a_folder_holding_a_run(tmp_path: Path) -> None:
    """resume=never (the default) in a folder with a checkpoint: one line naming resume=auto; ckpt_path= names what
    to resume and wins; a checkpoint of another model is refused; a bad mode is named."""
    run = tmp_path / "run"
    assert resume_point(run, IDENTITY, "never", None) is None
    last = _ckpt(run / "checkpoints" / "last.ckpt", 3)
    with pytest.raises(ValueError, match="already holds a run .* resume=auto continues it"):
        resume_point(run, IDENTITY, "never", None)
    assert resume_point(run, IDENTITY, "never", str(last)).step == 3
    assert resume_point(run, IDENTITY, "auto", None).step == 3
    with pytest.raises(CheckpointError, match="holds a 'flow:flow_mix' run .*not a 'depth:depth_stereo' one"):
        resume_point(run, "depth:depth_stereo", "auto", None)
    with pytest.raises(ValueError, match=r"resume='sometimes'; expected one of \['never', 'auto'\]"):
        resume_point(run, IDENTITY, "sometimes", None)


def test_durable_replace_keeps_a_whole_previous_file(tmp_path: Path) -> None:
    """The new file replaces the old one whole; the old one stays as the previous copy; no temporary is left."""
    path, previous = tmp_path / "last.ckpt", tmp_path / "previous.ckpt"
    for text in ("one", "two", "three"):
        tmp = tmp_path / "last.ckpt.tmp"
        tmp.write_text(text)
        durable_replace(tmp, path, keep_previous=previous)
    assert path.read_text() == "three" and previous.read_text() == "two"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.ckpt", "previous.ckpt"]


def test_resume_auto_continues_a_stopped_run_to_the_same_weights(tmp_path: Path) -> None:
    """A run of 6 steps stopped by max_steps at step 4, then resume=auto with the full length: the same weights as
    the uninterrupted run, bitwise; finished.json marks only the run that ended normally; a finished run resumed
    again trains nothing."""
    phases = "model.phases=[{name:sup,steps:6,lr:1.0e-3}]"
    whole = run_training(_cfg(tmp_path, phases, "name=whole"))
    assert read_finished(tmp_path / "whole")["step"] == 6
    part = run_training(_cfg(tmp_path, phases, "name=part", "trainer.max_steps=4"))
    assert part["global_step"] == 4
    rest = run_training(_cfg(tmp_path, phases, "name=part", "resume=auto"))
    assert rest["global_step"] == 6 and json.loads((tmp_path / "part" / "finished.json").read_text())["step"] == 6
    a, b = whole["module"].state_dict(), rest["module"].state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    again = run_training(_cfg(tmp_path, phases, "name=part", "resume=auto"))
    assert again["global_step"] == 6
    with pytest.raises(ValueError, match="already holds a run"):
        run_training(_cfg(tmp_path, phases, "name=part"))


def test_keep_weights_every_n_steps(tmp_path: Path) -> None:
    """trainer.keep_weights_every_n_steps=2 keeps the fp16 export of steps 2 and 4, each saying its step."""
    from safetensors import safe_open

    run_training(_cfg(tmp_path, "model.phases=[{name:sup,steps:4,lr:1.0e-3}]", "name=k",
                      "trainer.keep_weights_every_n_steps=2"))
    kept = sorted(p.name for p in (tmp_path / "k").glob("weights_step*.safetensors"))
    assert kept == ["weights_step2.safetensors", "weights_step4.safetensors"]
    with safe_open(str(tmp_path / "k" / "weights_step2.safetensors"), "pt") as f:
        assert f.metadata()["global_step"] == "2" and f.metadata()["task"] == "flow"


def test_eta_text() -> None:
    assert eta_text(59 * 60) == "00:59" and eta_text(26 * 3600 + 120) == "1d 02:02" and eta_text(float("nan")) == "--"


def test_precision_auto_follows_the_cpu_flags(monkeypatch: pytest.MonkeyPatch) -> None:
    """auto: bf16-mixed on a CPU listing avx512_bf16 or amx_bf16, 32-true on one without; a set value is kept."""
    monkeypatch.setattr(precision_module, "cpu_flags", lambda: {"avx2", "avx512f", "avx512_bf16"})
    assert resolve_precision("auto", "cpu")[0] == "bf16-mixed"
    monkeypatch.setattr(precision_module, "cpu_flags", lambda: {"avx2", "amx_bf16"})
    assert resolve_precision("auto", "cpu")[0] == "bf16-mixed"
    monkeypatch.setattr(precision_module, "cpu_flags", lambda: {"avx2", "fma"})
    chosen, why = resolve_precision("auto", "cpu")
    assert chosen == "32-true" and "no bf16" in why
    assert resolve_precision("32-true", "cpu")[0] == "32-true"
    assert resolve_precision("bf16-mixed", "cpu")[0] == "bf16-mixed"


def test_weight_average_follows_the_ema_formula() -> None:
    """WeightAverage keeps avg <- d avg + (1 - d) w of the exported network, parameters and buffers, starting from
    the weights of the first step (hand-computed with d = 0.5)."""
    from types import SimpleNamespace

    from dfvo.training.weight_average import WeightAverage, averaged_network

    class Tiny(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.net = torch.nn.Sequential(torch.nn.Linear(2, 1), torch.nn.BatchNorm1d(1))

        def export_network(self):
            return self.net, {}

    module = Tiny()
    keeper = WeightAverage(0.5)
    keeper.on_fit_start(SimpleNamespace(global_step=0), module)
    values = [1.0, 3.0, 7.0]
    for v in values:
        with torch.no_grad():
            module.net[0].weight.fill_(v)
            module.net[1].running_mean.fill_(10 * v)
        keeper.on_train_batch_end(None, module, None, None, 0)
    avg = averaged_network(module)
    expected = 0.5 * (0.5 * 1.0 + 0.5 * 3.0) + 0.5 * 7.0  # the first update copies, then the EMA
    assert torch.allclose(avg[0].weight, torch.full_like(avg[0].weight, expected))
    assert torch.allclose(avg[1].running_mean, torch.full_like(avg[1].running_mean, 10 * expected))
    assert torch.equal(module.net[0].weight, torch.full_like(module.net[0].weight, 7.0))  # the raw weights stay
    with pytest.raises(ValueError, match="trainer.ema_decay=1.5"):
        WeightAverage(1.5)
    from dfvo.training.config import TrainerConfig

    with pytest.raises(ValueError, match="trainer.ema_decay=0.999 with trainer.precision=bf16-true"):
        TrainerConfig(ema_decay=0.999, precision="bf16-true")
    assert TrainerConfig(ema_decay=0.999, precision="bf16-mixed").ema_decay == 0.999


def test_ema_export_resumes_exactly_and_differs_from_the_raw_weights(tmp_path: Path) -> None:
    """trainer.ema_decay: the exported weights.safetensors is the average (metadata ``weights: ema 0.5``), not the
    raw weights; a run stopped at step 4 and resumed to step 6 exports the same average as the uninterrupted run
    (the average is in the checkpoint)."""
    from safetensors import safe_open
    from safetensors.torch import load_file

    phases = "model.phases=[{name:sup,steps:6,lr:1.0e-3}]"
    whole = run_training(_cfg(tmp_path, phases, "name=whole", "trainer.ema_decay=0.5"))
    run_training(_cfg(tmp_path, phases, "name=part", "trainer.max_steps=4", "trainer.ema_decay=0.5"))
    run_training(_cfg(tmp_path, phases, "name=part", "resume=auto", "trainer.ema_decay=0.5"))
    a, b = (load_file(str(tmp_path / n / "weights.safetensors")) for n in ("whole", "part"))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    with safe_open(str(tmp_path / "whole" / "weights.safetensors"), "pt") as f:
        assert f.metadata()["weights"] == "ema 0.5" and f.metadata()["global_step"] == "6"
    raw = {k: v.half() for k, v in whole["module"].export_network()[0].state_dict().items()}
    assert any(not torch.equal(raw[k], a[k]) for k in a if a[k].is_floating_point())
